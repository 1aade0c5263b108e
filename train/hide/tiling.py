"""Cutting a secret into tiles, each hidden at its own viewpoint.

Tiles form a row-major grid of tile_size squares, edge tiles taking what is left. Tile k is seen from
scene camera (view + k) mod n_cameras while distinct cameras last; beyond that, from that camera
turned about its own up axis by YAW_STEP_DEGREES per round, so every tile still has a viewpoint of its
own (and forward-facing scenes stay forward-facing). Each tile camera keeps its scene camera's
horizontal field of view at the tile's size.
"""

from __future__ import annotations

import math

import numpy as np

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError

MIN_TILE_SIZE = 16
DEFAULT_TILE_SIZE = 512  # a secret larger than this is cut into tiles (hide --tile-size)
YAW_STEP_DEGREES = 2.0


def part_rows(width: int, height: int, part_pixels: int) -> int:
    """Rows of a (height, width) tile in each of its parts (the last what is left): whole rows, as many as
    part_pixels holds, at least one, at most the tile's. A compact tile's coefficients are coded in bands of these
    rows (runtime/interlaced.py), each part its own."""
    return min(height, max(1, part_pixels // width))


def tile_rects(width: int, height: int, tile_size: int) -> list[tuple[int, int, int, int]]:
    """Row-major (x0, y0, w, h) rectangles covering width × height."""
    if tile_size < MIN_TILE_SIZE:
        raise UserError(f"--tile-size must be at least {MIN_TILE_SIZE} px, got {tile_size}")
    return [(x, y, min(tile_size, width - x), min(tile_size, height - y))
            for y in range(0, height, tile_size) for x in range(0, width, tile_size)]


def yawed(c2w: np.ndarray, degrees: float) -> np.ndarray:
    """The camera turned about its own up (y) axis. c2w: (4, 4) -> (4, 4)."""
    angle = math.radians(degrees)
    turn = np.array([[math.cos(angle), 0, math.sin(angle)], [0, 1, 0], [-math.sin(angle), 0, math.cos(angle)]])
    out = np.array(c2w, dtype=np.float64)
    out[:3, :3] = out[:3, :3] @ turn
    return out


def tile_camera(cameras: tuple[Camera, ...], view: int, k: int, rect: tuple[int, int, int, int]) -> Camera:
    """The camera that tile k (of the given rectangle) is hidden in."""
    base = cameras[(view + k) % len(cameras)]
    rounds = k // len(cameras)
    if rounds:
        c2w = yawed(base.matrix(), YAW_STEP_DEGREES * rounds)
        base = Camera.from_dict({**base.to_dict(), "c2w": c2w.tolist()})
    return base.resized(rect[2], rect[3])
