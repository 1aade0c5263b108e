"""Where a ray is sampled, and which samples are worth evaluating.

Samples follow nerf-pytorch at test time: n points from near to far inclusive, Δ_i = (t_{i+1} − t_i)·‖d‖,
the last interval 1e10 (the ray ends in whatever it last hit). Skipping never changes that math: a
sample in an empty occupancy cell or behind an opaque one is simply not evaluated and counts as σ = 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from noisenerf.runtime.compositing import optical_depths
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_SAMPLES_PER_RAY, checked_float, checked_int

LAST_DELTA = 1e10


@dataclass(frozen=True)
class SamplingConfig:
    """Samples per ray and the ray interval, in the ray parameter t (depth, or NDC t in [0, 1])."""

    near: float
    far: float
    n_samples: int

    def __post_init__(self):
        if not (np.isfinite(self.near) and np.isfinite(self.far) and 0 <= self.near < self.far):
            raise UserError(f"sampling needs 0 <= near < far, got near={self.near}, far={self.far}")
        if not 1 <= self.n_samples <= MAX_SAMPLES_PER_RAY:
            raise UserError(f"sampling needs 1 to {MAX_SAMPLES_PER_RAY} samples per ray, got {self.n_samples}")

    @staticmethod
    def from_dict(data) -> "SamplingConfig":
        """From metadata someone else wrote: exactly near, far and an integer n_samples, all checked."""
        if not isinstance(data, dict) or set(data) != {"near", "far", "n_samples"}:
            raise UserError("sampling must be an object with near, far and n_samples")
        return SamplingConfig(checked_float(data["near"], "sampling near"), checked_float(data["far"], "sampling far"),
                              checked_int(data["n_samples"], "sampling n_samples", 1, MAX_SAMPLES_PER_RAY))


def sample_positions(config: SamplingConfig) -> np.ndarray:
    """t of each sample, shared by all rays: (n_samples,) float32, near and far included."""
    if config.n_samples == 1:
        return np.array([config.near], dtype=np.float32)
    return np.linspace(config.near, config.far, config.n_samples, dtype=np.float32)


NETWORKS = ("coarse", "fine")
MAX_HIERARCHY_SAMPLES = 1024  # per pass and ray; nerf-pytorch's configs use at most 256


def render_network(networks) -> str:
    """The network a scene renders with, of the names it has: the fine one where there is one."""
    return "fine" if "fine" in networks else "coarse"


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
                            f"and 1 <= n_importance <= {MAX_HIERARCHY_SAMPLES}, got {counts}")

    def coarse(self, sampling: SamplingConfig) -> SamplingConfig:
        """The coarse pass's uniform sampling over the scene's ray interval."""
        return SamplingConfig(sampling.near, sampling.far, self.n_coarse)


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
    index = np.zeros((cdf.shape[0], n_samples), dtype=np.int64)  # searchsorted(cdf, u, right=True) per ray
    for column in cdf.T:  # one bin edge at a time: memory (n_rays, n_samples), not times n_bins
        index += column[:, None] <= u
    below, above = np.maximum(index - 1, 0), np.minimum(index, cdf.shape[-1] - 1)
    cdf_below, cdf_above = (np.take_along_axis(cdf, i, axis=1) for i in (below, above))
    bin_below, bin_above = (np.take_along_axis(bins, i, axis=1) for i in (below, above))
    denom = cdf_above - cdf_below
    denom = np.where(denom < 1e-5, np.float32(1.0), denom)
    return (bin_below + (u - cdf_below) / denom * (bin_above - bin_below)).astype(np.float32)


def jitter_positions(t_vals: np.ndarray, n_rays: int, rng: np.random.Generator) -> np.ndarray:
    """nerf-pytorch's stratified training samples: one uniform draw between neighbouring midpoints.

    t_vals: (n_samples,) -> (n_rays, n_samples) float32.
    """
    mids = 0.5 * (t_vals[1:] + t_vals[:-1])
    upper = np.concatenate([mids, t_vals[-1:]])
    lower = np.concatenate([t_vals[:1], mids])
    u = rng.random((n_rays, t_vals.shape[0]), dtype=np.float32)
    return (lower + (upper - lower) * u).astype(np.float32)


def sample_along(origins: np.ndarray, directions: np.ndarray, t_vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample points o + t·d and their intervals. origins, directions: (n_rays, 3) float32; t_vals:
    (n_samples,) or (n_rays, n_samples) -> points (n_rays, n_samples, 3), deltas (n_rays, n_samples)."""
    t_vals = np.broadcast_to(t_vals, (origins.shape[0], t_vals.shape[-1])).astype(np.float32)
    points = origins[:, None, :] + t_vals[..., None] * directions[:, None, :]
    deltas = sample_deltas(t_vals, np.linalg.norm(directions, axis=-1))
    return points.astype(np.float32), deltas


def sample_deltas(t_vals: np.ndarray, ray_norms: np.ndarray) -> np.ndarray:
    """Δ_i = (t_{i+1} − t_i)·‖d‖, last 1e10·‖d‖. t_vals: (n_rays, n_samples), ray_norms: (n_rays,)."""
    steps = np.concatenate([np.diff(t_vals, axis=-1), np.full_like(t_vals[:, :1], LAST_DELTA)], axis=-1)
    return (steps * ray_norms[:, None]).astype(np.float32)


class OccupancyGrid:
    """A binary grid over an axis-aligned box: False cells are known empty and never evaluated."""

    def __init__(self, aabb, occupied: np.ndarray):
        self.aabb = np.asarray(aabb, dtype=np.float32).reshape(6)
        self.occupied = np.asarray(occupied, dtype=bool)
        if self.occupied.ndim != 3 or len(set(self.occupied.shape)) != 1:
            raise UserError(f"occupancy grid must be a cube, got shape {self.occupied.shape}")

    @property
    def resolution(self) -> int:
        return self.occupied.shape[0]

    def occupancy_fraction(self) -> float:
        return float(self.occupied.mean())

    def contains(self, points: np.ndarray) -> np.ndarray:
        """Whether each point lies in the closed box. (..., 3) -> (...)."""
        return np.all((points >= self.aabb[:3]) & (points <= self.aabb[3:]), axis=-1)

    def box_only(self) -> "OccupancyGrid":
        """The same box with every cell occupied: no skipping inside the scene, nothing outside it."""
        return OccupancyGrid(self.aabb, np.ones_like(self.occupied))

    def lookup(self, points: np.ndarray) -> np.ndarray:
        """Whether each point lies in an occupied cell; points outside the box are empty. The box is closed:
        a point on its upper face (NDC's far plane z = 1, where forward-facing scenes keep their
        background sample) belongs to the last cell. (..., 3) -> (...)."""
        lo, hi = self.aabb[:3], self.aabb[3:]
        inside = self.contains(points)
        cell = np.minimum(np.floor((points - lo) / (hi - lo) * self.resolution), self.resolution - 1)
        idx = np.where(inside[..., None], cell, 0).astype(np.int64)
        return inside & self.occupied[idx[..., 0], idx[..., 1], idx[..., 2]]


def grid_candidates(grid: OccupancyGrid, points: np.ndarray) -> np.ndarray:
    """Samples the grid does not rule out. A ray's last sample is kept wherever it lies in the box,
    whatever its cell says: its interval is 1e10, so a density far below the grid's threshold still
    decides the ray's colour (LLFF keeps its background there, on NDC's far plane).
    points: (n_rays, n_samples, 3) -> (n_rays, n_samples) bool."""
    candidates = grid.lookup(points)
    candidates[:, -1] = grid.contains(points[:, -1])
    return candidates


FieldFn = Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
# field(points (m, 3), viewdirs (m, 3), noise (m, dims)) -> rgb (m, 3), sigma (m,)
NoisyFieldFn = Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
# the render pipeline's callback, nerfacc's rgb_sigma_fn: points (m, 3), viewdirs (m, 3), and which ray (m,)
# and sample (m,) each point is -> rgb (m, 3), sigma (m,); what a field needs besides the point (noise) it
# looks up by those indices
SampleFieldFn = Callable[[np.ndarray, np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]


def plain(field: FieldFn) -> SampleFieldFn:
    """An ordinary field as the pipeline's callback."""
    return lambda points, viewdirs, rays, samples: field(points, viewdirs)


def noisy(field: NoisyFieldFn, noise: np.ndarray) -> SampleFieldFn:
    """A field with noise at every sample: noise (n_rays, 1 or n_samples, dims) float32, one vector per ray
    (ray and compact layouts) or per sample (the paper's layout)."""
    per_ray = noise.shape[1] == 1
    return lambda points, viewdirs, rays, samples: field(points, viewdirs, noise[rays, 0 if per_ray else samples])


@dataclass(frozen=True)
class MarchResult:
    """Dense per-sample outputs with σ = 0, rgb = 0 where a sample was skipped."""

    sigmas: np.ndarray  # (n_rays, n_samples)
    rgbs: np.ndarray  # (n_rays, n_samples, 3)
    evaluated: np.ndarray  # (n_rays, n_samples) bool

    @property
    def n_evaluated(self) -> int:
        return int(self.evaluated.sum())


def march_rays(points: np.ndarray, viewdirs: np.ndarray, deltas: np.ndarray, field: SampleFieldFn,
               grid: OccupancyGrid | None, early_stop: float, chunk_samples: int = 16) -> MarchResult:
    """Evaluate the field front to back, skipping empty cells and rays whose transmittance fell below
    `early_stop` (0 skips only rays whose transmittance is exactly 0, where nothing behind counts).

    points: (n_rays, n_samples, 3), viewdirs: (n_rays, 3), deltas: (n_rays, n_samples); field: SampleFieldFn.
    """
    n_rays, n_samples = deltas.shape
    candidates = grid_candidates(grid, points) if grid is not None else np.ones((n_rays, n_samples), dtype=bool)
    sigmas = np.zeros((n_rays, n_samples), dtype=np.float32)
    rgbs = np.zeros((n_rays, n_samples, 3), dtype=np.float32)
    evaluated = np.zeros((n_rays, n_samples), dtype=bool)
    depth_so_far = np.zeros(n_rays, dtype=np.float32)
    for start in range(0, n_samples, chunk_samples):
        stop = min(start + chunk_samples, n_samples)
        alive = np.exp(-depth_so_far) > early_stop
        chosen = candidates[:, start:stop] & alive[:, None]
        rays, offsets = np.nonzero(chosen)
        if rays.size:
            rgb, sigma = field(points[rays, start + offsets], viewdirs[rays], rays, start + offsets)
            sigmas[rays, start + offsets] = sigma
            rgbs[rays, start + offsets] = rgb
            evaluated[rays, start + offsets] = True
        depth_so_far += optical_depths(sigmas[:, start:stop], deltas[:, start:stop]).sum(axis=1)
    return MarchResult(sigmas, rgbs, evaluated)
