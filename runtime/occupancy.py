"""The occupancy grid: a binary cube over the scene's box whose empty cells are never evaluated."""

from __future__ import annotations

import numpy as np

from noisenerf.runtime.errors import UserError


class OccupancyGrid:
    """A binary grid over an axis-aligned box: False cells are known empty and never evaluated."""

    def __init__(self, aabb, occupied: np.ndarray):
        self.aabb = np.asarray(aabb, dtype=np.float32).reshape(6)
        self.occupied = np.asarray(occupied, dtype=bool)
        if self.occupied.ndim != 3 or len(set(self.occupied.shape)) != 1:
            raise UserError(f"occupancy grid must be a cube, got shape {self.occupied.shape}",
                            code="model.grid_not_cube", shape=self.occupied.shape)

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
