"""nerf-pytorch's hierarchical sampling: a coarse pass's weights place the fine pass's samples."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.sampling import SamplingConfig

MAX_HIERARCHY_SAMPLES = 1024  # per pass and ray; nerf-pytorch's configs use at most 256


@dataclass(frozen=True)
class Hierarchy:
    """nerf-pytorch's two-pass sampling for scenes with a fine network: n_coarse uniform samples (near to
    far) through the coarse network, whose weights place n_importance more (sample_pdf); the fine network
    runs on the sorted union of both."""

    n_coarse: int
    n_importance: int

    def __post_init__(self):
        # the fine samples come from coarse weights[1:-1], which needs three coarse samples at least
        counts = (self.n_coarse, self.n_importance)
        if not all(type(n) is int for n in counts) or not (3 <= self.n_coarse <= MAX_HIERARCHY_SAMPLES
                                                          and 1 <= self.n_importance <= MAX_HIERARCHY_SAMPLES):
            raise UserError(f"hierarchical sampling needs whole numbers 3 <= n_coarse <= {MAX_HIERARCHY_SAMPLES} "
                            f"and 1 <= n_importance <= {MAX_HIERARCHY_SAMPLES}, got {counts}",
                            code="sampling.bad_hierarchy", most=MAX_HIERARCHY_SAMPLES)

    def coarse(self, sampling: SamplingConfig) -> SamplingConfig:
        """The coarse pass's uniform sampling over the scene's ray interval."""
        return SamplingConfig(sampling.near, sampling.far, self.n_coarse)

    @property
    def samples_per_ray(self) -> int:
        """Samples of both passes on one ray."""
        return self.n_coarse + self.n_importance


def sample_pdf(bins: np.ndarray, weights: np.ndarray, n_samples: int) -> np.ndarray:
    """Deterministic inverse-CDF samples of the piecewise-constant pdf given by weights over bins:
    nerf-pytorch's sample_pdf with det=True (its 1e-5 floor and denominator guard included), the numpy
    twin of noisenerf.train.scene.render.sample_pdf.

    bins: (n_rays, n_bins + 1), weights: (n_rays, n_bins) -> (n_rays, n_samples) float32.
    """
    weights = weights.astype(np.float32) + np.float32(1e-5)
    pdf = weights / weights.sum(axis=-1, keepdims=True, dtype=np.float32)
    cdf = np.concatenate([np.zeros_like(pdf[:, :1]), np.cumsum(pdf, axis=-1, dtype=np.float32)], axis=-1)
    u = np.linspace(0.0, 1.0, n_samples, dtype=np.float32)
    cdf_below, cdf_above, bin_below, bin_above = bracketing(cdf, bins, u)
    denom = cdf_above - cdf_below
    denom = np.where(denom < 1e-5, np.float32(1.0), denom)
    return (bin_below + (u - cdf_below) / denom * (bin_above - bin_below)).astype(np.float32)


def bracketing(cdf: np.ndarray, bins: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, ...]:
    """The CDF values and bin edges either side of each u: searchsorted(cdf, u, right=True) per ray, its index
    and the one below clipped to the edges. cdf, bins: (n_rays, m + 1), u: (k,) -> four (n_rays, k) arrays:
    cdf below, cdf above, bin below, bin above."""
    index = np.zeros((cdf.shape[0], u.shape[0]), dtype=np.int64)
    for column in cdf.T:  # one edge at a time: memory (n_rays, k), not times m
        index += column[:, None] <= u
    below, above = np.maximum(index - 1, 0), np.minimum(index, cdf.shape[-1] - 1)
    return (*(np.take_along_axis(cdf, i, axis=1) for i in (below, above)),
            *(np.take_along_axis(bins, i, axis=1) for i in (below, above)))
