"""nerfacto's ordinary render: the proposal sampler, then its compositor (nerfstudio's eval-time render).

Samples live in bins along unit-length rays from `near` to `far`. Stage 0 cuts the ray into n equal bins in
the piecewise spacing s(t) = t/2 below 1, 1 − 1/(2t) beyond (uniform up to distance 1, linear in disparity
after: mip-NeRF 360's, as nerfstudio's UniformLinDispPiecewiseSampler); each proposal network's densities
at its stage's bin midpoints give weights (runtime.compositing, eq. 2) that a deterministic PDF sampler
turns into the next stage's bins, in spacing space, with nerfstudio's histogram padding; the field renders
the last stage. The compositor is nerfstudio's `last_sample` background: Σ w·c + c_last·(1 − Σ w), then
clamped to [0, 1] — no 1e10 last interval, every bin its true width.

Secret views do not use this sampler: a tile is rendered with the uniform sampling the hide chose
(runtime.reveal), which needs no proposal network and no noise on one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, ClassVar, Sequence

import numpy as np

from noisenerf.runtime.compositing import composite, render_weights
from noisenerf.runtime.field_callbacks import FieldFn
from noisenerf.runtime.pdf import bracketing
from noisenerf.runtime.rays import RayBatch
from noisenerf.runtime.render import RenderStats

DensityFn = Callable[[np.ndarray], np.ndarray]  # points (n, 3) -> σ (n,)
WEIGHT_FLOOR = 1e-5  # nerfstudio's PDFSampler eps: rays with less total weight are padded to it


@dataclass(frozen=True)
class ProposalSampling:
    """runtime.fields.nerfacto's `sampler`: bins per proposal stage, the field's bins, histogram padding,
    the ray interval (distance along unit directions)."""

    proposal_samples: tuple[int, ...]
    samples: int
    histogram_padding: float
    near: float
    far: float

    @staticmethod
    def from_architecture(sampler: dict) -> "ProposalSampling":
        """From a checked architecture's sampler."""
        return ProposalSampling(tuple(sampler["proposal_samples"]), sampler["samples"], sampler["histogram_padding"],
                                sampler["near"], sampler["far"])

    @property
    def most_samples(self) -> int:
        """The largest stage: what one ray holds at once."""
        return max(*self.proposal_samples, self.samples)


@dataclass(frozen=True)
class ProposalSampler:
    """nerfacto's ordinary render (a runtime.render.Sampler): the sampling and one density function per
    proposal network. Never skips: the proposal networks already put the samples where the surface is."""

    sampling: ProposalSampling
    densities: Sequence[DensityFn]
    hierarchical: ClassVar[bool] = True
    skips: ClassVar[bool] = False

    @property
    def samples_per_ray(self) -> int:
        return self.sampling.most_samples

    def render(self, rays: RayBatch, field: FieldFn) -> tuple[np.ndarray, RenderStats]:
        colours, evaluated = render_proposal_rays(rays, field, self)
        return colours, RenderStats(len(rays), evaluated, evaluated)


def spacing(t: np.ndarray) -> np.ndarray:
    """s(t) = t/2 for t < 1, 1 − 1/(2t) beyond. (...) float32 -> (...)."""
    with np.errstate(divide="ignore"):
        return np.where(t < 1, t / np.float32(2), np.float32(1) - np.float32(1) / (np.float32(2) * t)).astype(np.float32)


def spacing_inverse(s: np.ndarray) -> np.ndarray:
    """t(s) = 2s for s < 1/2, 1/(2 − 2s) beyond. (...) float32 -> (...)."""
    with np.errstate(divide="ignore"):
        return np.where(s < 0.5, np.float32(2) * s, np.float32(1) / (np.float32(2) - np.float32(2) * s)).astype(np.float32)


def euclidean_bins(bins: np.ndarray, near: float, far: float) -> np.ndarray:
    """Bin edges in spacing space [0, 1] -> distances: t(x·s(far) + (1 − x)·s(near)). (r, m + 1) -> (r, m + 1)."""
    s_near, s_far = (spacing(np.float32(v)) for v in (near, far))
    return spacing_inverse(bins * s_far + (np.float32(1) - bins) * s_near)


def uniform_bins(n_rays: int, n: int) -> np.ndarray:
    """Stage 0's n equal bins in spacing space, every ray alike. -> (n_rays, n + 1) float32."""
    return np.broadcast_to(np.linspace(0.0, 1.0, n + 1, dtype=np.float32), (n_rays, n + 1))


def pdf_bins(bins: np.ndarray, weights: np.ndarray, n: int, padding: float) -> np.ndarray:
    """nerfstudio's PDFSampler at eval: n bins (n + 1 edges at the CDF's midpoints of n + 1 equal steps) of
    the piecewise-constant density `weights + padding` over `bins`, edges interpolated linearly in spacing
    space. bins: (r, m + 1), weights: (r, m) -> (r, n + 1) float32."""
    weights = weights.astype(np.float32) + np.float32(padding)
    total = weights.sum(axis=-1, keepdims=True, dtype=np.float32)
    pad = np.maximum(np.float32(WEIGHT_FLOOR) - total, np.float32(0))
    weights, total = weights + pad / np.float32(weights.shape[-1]), total + pad
    cdf = np.minimum(np.float32(1), np.cumsum(weights / total, axis=-1, dtype=np.float32))
    cdf = np.concatenate([np.zeros_like(cdf[:, :1]), cdf], axis=-1)
    edges = n + 1
    u = (np.linspace(0.0, 1.0 - 1.0 / edges, edges, dtype=np.float32) + np.float32(1.0 / (2 * edges))).astype(np.float32)
    cdf_below, cdf_above, bin_below, bin_above = bracketing(cdf, bins, u)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip(np.nan_to_num((u - cdf_below) / (cdf_above - cdf_below), nan=0.0, posinf=0.0, neginf=0.0), 0, 1)
    return (bin_below + t.astype(np.float32) * (bin_above - bin_below)).astype(np.float32)


def midpoints(rays: RayBatch, edges: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Points at the bins' middles along the unit view directions, and the bins' widths.
    edges: (r, m + 1) distances -> points (r, m, 3), deltas (r, m)."""
    starts, ends = edges[:, :-1], edges[:, 1:]
    middles = (starts + ends) / np.float32(2)
    points = rays.origins[:, None, :] + rays.viewdirs[:, None, :] * middles[..., None]
    return points.astype(np.float32), (ends - starts).astype(np.float32)


def proposal_edges(rays: RayBatch, networks: ProposalSampler) -> np.ndarray:
    """The field's bin edges (r, samples + 1) in distance: each proposal stage's densities placing the next."""
    sampling = networks.sampling
    bins = uniform_bins(len(rays), sampling.proposal_samples[0])
    counts = (*sampling.proposal_samples[1:], sampling.samples)
    for density, count in zip(networks.densities, counts):
        points, deltas = midpoints(rays, euclidean_bins(bins, sampling.near, sampling.far))
        sigmas = density(points.reshape(-1, 3)).reshape(deltas.shape)
        bins = pdf_bins(bins, render_weights(sigmas, deltas), count, sampling.histogram_padding)
    return euclidean_bins(bins, sampling.near, sampling.far)


def render_proposal_rays(rays: RayBatch, field: FieldFn, networks: ProposalSampler) -> tuple[np.ndarray, int]:
    """Colours (r, 3) of an ordinary nerfacto render, and the field samples evaluated."""
    points, deltas = midpoints(rays, proposal_edges(rays, networks))
    viewdirs = np.broadcast_to(rays.viewdirs[:, None, :], points.shape).reshape(-1, 3)
    rgbs, sigmas = field(points.reshape(-1, 3), np.ascontiguousarray(viewdirs))
    rgbs, sigmas = rgbs.reshape(points.shape), sigmas.reshape(deltas.shape)
    colours = composite(render_weights(sigmas, deltas), rgbs, rgbs[:, -1])
    return np.clip(np.nan_to_num(colours), 0.0, 1.0), deltas.size
