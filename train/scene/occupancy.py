"""The binary occupancy grid for empty-space skipping, kept from the field's own density.

A cell is occupied when a sample there would be visible: opacity 1 − exp(−σ·step) above a threshold
(σ·step > 0.01, nerfacc's rule), with σ the largest density seen at jittered points in the cell.
During fitting a decaying running maximum is refreshed on a random share of cells every few steps, and
the threshold is never above the mean (also nerfacc's rule), so a young field whose densities are all
still small is never skipped entirely.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
import torch

from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.train.scene.field_kinds import Field


@dataclass(frozen=True)
class OccupancyConfig:
    resolution: int = 64
    opacity_threshold: float = 0.01
    ema_decay: float = 0.95
    update_every: int = 16
    warmup_steps: int = 32
    update_fraction: float = 0.25
    final_samples_per_cell: int = 4
    # the saved grid's cells per side (None: resolution); built once at the end, it can afford to be finer
    # than the grid kept while fitting, and a finer grid misses fewer thin structures and skips more
    final_resolution: int | None = None

    @property
    def saved_resolution(self) -> int:
        return self.final_resolution or self.resolution

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


def cell_points(aabb: np.ndarray, resolution: int, cells: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One uniformly jittered point in each of the given flat cell indices. cells: (m,) -> (m, 3) float32."""
    ijk = np.stack(np.unravel_index(cells, (resolution,) * 3), axis=-1).astype(np.float32)
    lo, hi = aabb[:3], aabb[3:]
    return (lo + (ijk + rng.random(ijk.shape, dtype=np.float32)) / resolution * (hi - lo)).astype(np.float32)


def occupied_cells(opacity: np.ndarray, threshold: float) -> np.ndarray:
    """Cells whose sample opacity exceeds the threshold, or the mean opacity where that is lower, so a
    scene of faint densities (a young field, LLFF's haze) is not skipped away. (m,) -> (m,) bool."""
    if np.isfinite(opacity).all():
        threshold = min(threshold, float(np.mean(opacity)))
    return opacity > threshold


@torch.no_grad()
def cell_densities(field: Field, aabb: np.ndarray, resolution: int, cells: np.ndarray,
                   rng: np.random.Generator, chunk: int = 65536) -> np.ndarray:
    """σ at one jittered point per cell. -> (m,) float32."""
    device = next(field.parameters()).device
    points = torch.from_numpy(cell_points(aabb, resolution, cells, rng)).to(device)
    return torch.cat([field.density(points[i:i + chunk]) for i in range(0, len(points), chunk)]).cpu().numpy()


def build_occupancy_grid(field: Field, aabb, resolution: int, step_size: float,
                         config: OccupancyConfig = OccupancyConfig(), seed: int = 0,
                         within: np.ndarray | None = None) -> OccupancyGrid:
    """A grid from scratch: the max density over several jittered points per cell, thresholded. Only the
    cells `within` allows ((resolution,)*3 bool, e.g. a visual hull) are evaluated; the rest are empty."""
    aabb = np.asarray(aabb, dtype=np.float32)
    rng = np.random.default_rng(seed)
    cells = np.arange(resolution ** 3) if within is None else np.flatnonzero(within)
    density = np.zeros(cells.size, dtype=np.float32)
    for _ in range(config.final_samples_per_cell):
        density = np.maximum(density, cell_densities(field, aabb, resolution, cells, rng))
    occupied = np.zeros(resolution ** 3, dtype=bool)
    occupied[cells] = occupied_cells(density * step_size, config.opacity_threshold)
    return OccupancyGrid(aabb, occupied.reshape((resolution,) * 3))


class OccupancyTracker:
    """The grid during fitting: everything occupied until warm-up ends, then a decaying max of density."""

    def __init__(self, aabb, step_size: float, config: OccupancyConfig, seed: int, hull: np.ndarray | None = None):
        self.aabb = np.asarray(aabb, dtype=np.float32)
        self.step_size, self.config = step_size, config
        self.density = np.full(config.resolution ** 3, np.inf, dtype=np.float32)
        self.rng = np.random.default_rng(seed)
        self.hull = np.ones((config.resolution,) * 3, dtype=bool) if hull is None else hull

    @property
    def grid(self) -> OccupancyGrid:
        occupied = occupied_cells(self.density * self.step_size, self.config.opacity_threshold)
        return OccupancyGrid(self.aabb, occupied.reshape(self.hull.shape) & self.hull)

    def maybe_update(self, field: Field, step: int) -> bool:
        """Refresh part of the grid on schedule (all of it at the end of warm-up). Returns True if updated."""
        if step < self.config.warmup_steps or step % self.config.update_every:
            return False
        n_cells = self.density.size
        if step == self.config.warmup_steps:
            cells = np.arange(n_cells)
            self.density[:] = 0.0
        else:
            cells = self.rng.choice(n_cells, int(n_cells * self.config.update_fraction), replace=False)
        fresh = cell_densities(field, self.aabb, self.config.resolution, cells, self.rng)
        self.density[cells] = np.maximum(self.density[cells] * self.config.ema_decay, fresh)
        return True


def max_filter(mask: np.ndarray, radius: int) -> np.ndarray:
    """Binary dilation by a (2r+1)² square. mask: (H, W) bool -> (H, W) bool."""
    padded = np.pad(mask, radius)
    windows = np.lib.stride_tricks.sliding_window_view(padded, (2 * radius + 1, 2 * radius + 1))
    return windows.any(axis=(-1, -2))


def carve(cameras, alphas: np.ndarray, aabb, resolution: int) -> np.ndarray:
    """Space carving: the visual hull of the training silhouettes on the grid.

    A cell is carved away when some view sees its centre on a pixel with zero alpha coverage, after
    dilating each silhouette by the cell's projected half-diagonal so that cells straddling an edge stay.
    cameras: one per alpha image, alphas: (n, H, W) -> (resolution,)*3 bool, True = may be occupied.
    """
    aabb = np.asarray(aabb, dtype=np.float64)
    cells = np.arange(resolution ** 3)
    ijk = np.stack(np.unravel_index(cells, (resolution,) * 3), axis=-1) + 0.5
    size = (aabb[3:] - aabb[:3]) / resolution
    centres = aabb[:3] + ijk * size
    half_diagonal = 0.5 * float(np.linalg.norm(size))
    keep = np.ones(cells.size, dtype=bool)
    for camera, alpha in zip(cameras, alphas):
        c2w = camera.matrix().astype(np.float64)
        local = (centres - c2w[:3, 3]) @ c2w[:3, :3]  # camera frame: looks down −z
        depth = -local[:, 2]
        ahead = depth > half_diagonal
        px = camera.cx + camera.fx * local[:, 0] / np.where(ahead, depth, 1.0)
        py = camera.cy - camera.fy * local[:, 1] / np.where(ahead, depth, 1.0)
        inside = ahead & (px >= 0) & (px < camera.width) & (py >= 0) & (py < camera.height)
        if not inside.any():
            continue
        radius = int(np.ceil(half_diagonal * camera.fx / depth[inside].min())) + 1
        covered = max_filter(alpha > 0, radius)
        seen_empty = np.zeros_like(keep)
        seen_empty[inside] = ~covered[py[inside].astype(np.int64), px[inside].astype(np.int64)]
        keep &= ~seen_empty
    return keep.reshape((resolution,) * 3)
