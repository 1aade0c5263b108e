"""Which samples are worth evaluating, and evaluating them front to back (nerfacc's estimator role).

Skipping never changes the render's math: a sample in an empty occupancy cell or behind opaque matter is
simply not evaluated and counts as σ = 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.compositing import optical_depths
from noisenerf.runtime.field_callbacks import SampleFieldFn
from noisenerf.runtime.occupancy import OccupancyGrid


def grid_candidates(grid: OccupancyGrid, points: np.ndarray) -> np.ndarray:
    """Samples the grid does not rule out. A ray's last sample is kept wherever it lies in the box,
    whatever its cell says: its interval is 1e10, so a density far below the grid's threshold still
    decides the ray's colour (LLFF keeps its background there, on NDC's far plane).
    points: (n_rays, n_samples, 3) -> (n_rays, n_samples) bool."""
    candidates = grid.lookup(points)
    candidates[:, -1] = grid.contains(points[:, -1])
    return candidates


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
