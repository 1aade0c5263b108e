"""Where a ray is sampled: sample positions t, points o + t·d and their intervals.

Samples follow nerf-pytorch at test time: n points from near to far inclusive, Δ_i = (t_{i+1} − t_i)·‖d‖,
the last interval 1e10 (the ray ends in whatever it last hit). Which of them are evaluated is
runtime.marching's; the hierarchy's extra samples are runtime.pdf's.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

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
            raise UserError(f"sampling needs 0 <= near < far, got near={self.near}, far={self.far}",
                            code="sampling.bad_range", near=self.near, far=self.far)
        if not 1 <= self.n_samples <= MAX_SAMPLES_PER_RAY:
            raise UserError(f"sampling needs 1 to {MAX_SAMPLES_PER_RAY} samples per ray, got {self.n_samples}",
                            code="sampling.bad_count", n_samples=self.n_samples, most=MAX_SAMPLES_PER_RAY)

    @staticmethod
    def from_dict(data) -> "SamplingConfig":
        """From metadata someone else wrote: exactly near, far and an integer n_samples, all checked."""
        if not isinstance(data, dict) or set(data) != {"near", "far", "n_samples"}:
            raise UserError("sampling must be an object with near, far and n_samples", code="sampling.not_object")
        return SamplingConfig(checked_float(data["near"], "sampling near", code="sampling.near"),
                              checked_float(data["far"], "sampling far", code="sampling.far"),
                              checked_int(data["n_samples"], "sampling n_samples", 1, MAX_SAMPLES_PER_RAY,
                                          code="sampling.n_samples"))


def sample_positions(config: SamplingConfig) -> np.ndarray:
    """t of each sample, shared by all rays: (n_samples,) float32, near and far included."""
    if config.n_samples == 1:
        return np.array([config.near], dtype=np.float32)
    return np.linspace(config.near, config.far, config.n_samples, dtype=np.float32)


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
