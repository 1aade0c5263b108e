"""nerfstudio's `instant-ngp` ordinary render: nerfacc 0.5.2's occupancy-grid marcher, then its compositor.

The grid (nerfacc's OccGridEstimator) has `levels` cubes of resolution³ cells, level l the scene box scaled by
2^l about its centre. Along a ray, the stretches between the boxes' entry and exit distances are each marched
in the finest level containing them (research/ngp-method.md §5, nerfacc/cuda/csrc/grid.cu:30–238): one lattice
of steps from `near`, each step dt = clamp(t·cone_angle, step, 1e10) of the t it starts from; a voxel walk (DDA)
visits the level's cells, and in an occupied cell every step whose middle lies before the cell's exit becomes
an interval [t, t + dt] (intervals may reach past the cell); an empty cell, or the gap before a stretch, is
crossed in steps of the dt it was entered with. The sample is the interval's middle, o + d·(t0 + t1)/2, along
the unit direction. At eval nerfstudio prunes nothing (no density function reaches the estimator), composites
w = T·α with α = 1 − exp(−σ·δ), T = exp(−exclusive cumsum σ·δ) (runtime.compositing), over black (its "random"
background adds nothing at eval), then clamps to [0, 1].

Every step is float32 as the kernel's, with a fused multiply-add where nvcc contracts one by default (the ray
points at a stretch's ends, the first plane crossings): emulated by a float64 product and sum rounded once.
All rays march in lockstep, each doing one step of the kernel's loops per pass.

Secret views do not use this sampler: a tile is rendered with the uniform sampling the hide chose.
"""

from __future__ import annotations

import base64
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from noisenerf.runtime.compositing import composite, render_weights
from noisenerf.runtime.field_callbacks import FieldFn
from noisenerf.runtime.rays import RayBatch
from noisenerf.runtime.render import RenderStats

F32 = np.float32
EPS = F32(1e-6)  # grid.cu:54, the DDA's start and end pulled inside the stretch
DT_MAX = F32(1e10)
BLACK = np.zeros(3, np.float32)
# the lockstep passes' phases, one per loop of the kernel
SEGMENT, CATCH_UP, CELL, SKIP, EMIT, ADVANCE, DONE = range(7)


def fma(a, b, c) -> np.ndarray:
    """a·b + c rounded once to float32 (CUDA's fmaf)."""
    return (np.asarray(a, np.float64) * np.asarray(b, np.float64) + np.asarray(c, np.float64)).astype(F32)


def step_size(t: np.ndarray, marching: "GridMarching") -> np.ndarray:
    """_calc_dt: clamp(t·cone_angle, step, 1e10). (n,) float32 -> (n,)."""
    return np.maximum(F32(marching.step), np.minimum((t * F32(marching.cone_angle)).astype(F32), DT_MAX))


@dataclass(frozen=True, eq=False)
class GridMarching:
    """runtime.fields.nerfacto's grid `sampler`: the step, cone angle, ray interval, the levels' boxes (L, 6)
    float32 and their cells (L, R, R, R) bool, indexed [level, x, y, z]."""

    step: float
    cone_angle: float
    near: float
    far: float
    aabbs: np.ndarray
    occupied: np.ndarray

    @staticmethod
    def from_architecture(sampler: dict) -> "GridMarching":
        """From a checked architecture's grid sampler (its occupancy: one bit per cell, C order, base64)."""
        levels, resolution = sampler["levels"], sampler["resolution"]
        cells = levels * resolution ** 3
        bits = np.unpackbits(np.frombuffer(base64.b64decode(sampler["occupancy"]), np.uint8), count=cells)
        return GridMarching(sampler["step"], sampler["cone_angle"], sampler["near"], sampler["far"],
                            level_boxes(np.asarray(sampler["aabb"], F32), levels),
                            bits.astype(bool).reshape(levels, resolution, resolution, resolution))

    @property
    def resolution(self) -> int:
        return self.occupied.shape[1]


def level_boxes(aabb: np.ndarray, levels: int) -> np.ndarray:
    """nerfacc's _enlarge_aabb: level l's box is `aabb` (6,) scaled 2^l about its centre. -> (L, 6) float32."""
    centre, half = (aabb[:3] + aabb[3:]) / F32(2), (aabb[3:] - aabb[:3]) / F32(2)
    return np.stack([np.concatenate([centre - half * F32(2 ** level), centre + half * F32(2 ** level)])
                     for level in range(levels)]).astype(F32)


def box_entries(origins: np.ndarray, inverse: np.ndarray, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The slab test of utils_grid.cuh:10–55 for every ray and box: entry and exit distances (+inf on a miss) and
    whether it hits (touching counts, a box behind the origin does not). (n, 3), (n, 3), (L, 6) -> (n, L) × 3."""
    o, inv = origins[:, None, :], inverse[:, None, :]
    lo, hi = boxes[None, :, :3], boxes[None, :, 3:]
    with np.errstate(invalid="ignore", over="ignore"):
        near_face, far_face = np.where(inv >= 0, lo, hi), np.where(inv >= 0, hi, lo)
        enter, leave = ((near_face - o) * inv).astype(F32), ((far_face - o) * inv).astype(F32)
    t_min, t_max, hit = enter[..., 0], leave[..., 0], np.ones(enter.shape[:2], bool)
    for axis in (1, 2):
        hit &= ~((t_min > leave[..., axis]) | (enter[..., axis] > t_max))
        t_min = np.where(enter[..., axis] > t_min, enter[..., axis], t_min)
        t_max = np.where(leave[..., axis] < t_max, leave[..., axis], t_max)
    hit &= ~(t_max <= 0)
    return np.where(hit, t_min, np.inf).astype(F32), np.where(hit, t_max, np.inf).astype(F32), hit


def stretches(origins: np.ndarray, inverse: np.ndarray, marching: GridMarching
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each ray's stretches between consecutive box events (grid.cu:86–107) and the level marching each:
    -> level (n, 2L − 1) int64, t_min, t_max (n, 2L − 1) float32, valid (n, 2L − 1) bool."""
    t_min, t_max, hit = box_entries(origins, inverse, marching.aabbs)
    levels = len(marching.aabbs)
    events = np.concatenate([t_min, t_max], axis=1)
    order = np.argsort(events, axis=1, kind="stable") if levels > 1 else np.broadcast_to(np.arange(2), events.shape)
    t_sorted = np.take_along_axis(events, order, axis=1)
    rows = np.arange(len(origins))[:, None]
    entering, level = order < levels, order % levels
    this, following = slice(0, 2 * levels - 1), slice(1, 2 * levels)
    leaving_into = ~entering[:, this] & ~entering[:, following]
    level_of = np.where(entering[:, this], level[:, this], level[:, following])
    valid = hit[rows, level[:, this]] & (entering[:, this] | (leaving_into & hit[rows, level[:, following]]))
    start = np.maximum(t_sorted[:, this], F32(marching.near))
    stop = np.minimum(t_sorted[:, following], F32(marching.far))
    return level_of, start, stop, valid & (start < stop)


@dataclass
class Walk:
    """The lockstep state of every ray's march: the kernel's locals, one row per ray."""

    origins: np.ndarray
    directions: np.ndarray
    inverse: np.ndarray
    level: np.ndarray  # (n, 2L − 1) the stretches
    start: np.ndarray
    stop: np.ndarray
    valid: np.ndarray
    segment: np.ndarray  # (n,) the stretch being marched
    phase: np.ndarray
    t: np.ndarray  # t_last
    dt: np.ndarray  # the dt a catch-up or an empty cell is crossed with
    continuous: np.ndarray
    cell: np.ndarray  # (n, 3) int64
    overflow: np.ndarray
    steps: np.ndarray
    crossing: np.ndarray  # (n, 3) float32, tdist
    delta: np.ndarray
    exit: np.ndarray  # t_traverse


def setup_traversal(walk: Walk, rays: np.ndarray, marching: GridMarching) -> None:
    """utils_grid.cuh:58–114 for `rays` entering their stretch: first cell, last cell + step, plane crossings."""
    seg = walk.segment[rays]
    t0, t1 = walk.start[rays, seg], walk.stop[rays, seg]
    box = marching.aabbs[walk.level[rays, seg]]
    lo, hi = box[:, :3], box[:, 3:]
    res = F32(marching.resolution)
    voxel = ((hi - lo) / res).astype(F32)
    o, d, inv = walk.origins[rays], walk.directions[rays], walk.inverse[rays]
    first = fma(d, (t0 + EPS)[:, None], o)
    last = fma(d, (t1 - EPS)[:, None], o)
    top = marching.resolution - 1

    def index(point):
        return np.clip(np.trunc(((point - lo) / (hi - lo)).astype(F32) * res).astype(np.int64), 0, top)

    current, final = index(first), index(last)
    plane = fma((current + (d > 0)).astype(F32), voxel, -first)
    with np.errstate(invalid="ignore", over="ignore"):
        crossing = fma((lo + plane).astype(F32), inv, t0[:, None])
        delta = (voxel * inv * np.sign(d).astype(F32)).astype(F32)
    flat = d == 0
    walk.crossing[rays] = np.where(flat, t1[:, None], crossing)
    walk.delta[rays] = np.where(flat, t1[:, None], delta)
    walk.steps[rays] = np.sign(d).astype(np.int64)
    walk.cell[rays], walk.overflow[rays] = current, final + walk.steps[rays]


def march(origins: np.ndarray, directions: np.ndarray, marching: GridMarching
          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """nerfacc's traverse_grids at eval (module docstring) for unit rays (n, 3): the intervals in the kernel's
    order, ray by ray. -> ray index (m,) int64, t_start (m,), t_end (m,) float32."""
    n = len(origins)
    origins, directions = origins.astype(F32), directions.astype(F32)
    with np.errstate(divide="ignore"):
        inverse = (F32(1) / directions).astype(F32)
    level, start, stop, valid = stretches(origins, inverse, marching)
    walk = Walk(origins, directions, inverse, level, start, stop, valid, np.zeros(n, np.int64),
                np.full(n, SEGMENT), np.full(n, F32(marching.near), F32), np.zeros(n, F32), np.zeros(n, bool),
                np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64), np.zeros((n, 3), np.int64),
                np.zeros((n, 3), F32), np.zeros((n, 3), F32), np.zeros(n, F32))
    emitted: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    stretches_per_ray, res = start.shape[1], marching.resolution
    while True:
        rays = np.flatnonzero(walk.phase == SEGMENT)
        if rays.size:  # the next valid stretch, or the ray is done
            done = walk.segment[rays] >= stretches_per_ray
            walk.phase[rays[done]] = DONE
            rays = rays[~done]
            skip = ~walk.valid[rays, walk.segment[rays]]
            walk.segment[rays[skip]] += 1
            rays = rays[~skip]
            walk.dt[rays] = step_size(walk.t[rays], marching)
            walk.phase[rays] = np.where(walk.continuous[rays], CELL, CATCH_UP)
            setup_traversal(walk, rays, marching)
        rays = np.flatnonzero(walk.phase == CATCH_UP)
        if rays.size:  # march until the step's middle is past the stretch's start
            arrived = walk.t[rays] + walk.dt[rays] * F32(0.5) >= walk.start[rays, walk.segment[rays]]
            walk.phase[rays[arrived]] = CELL
            moving = rays[~arrived]
            walk.t[moving] = walk.t[moving] + walk.dt[moving]
        rays = np.flatnonzero(walk.phase == CELL)
        if rays.size:  # the cell's exit and whether it is occupied
            walk.exit[rays] = np.minimum(walk.crossing[rays].min(axis=1), walk.stop[rays, walk.segment[rays]])
            x, y, z = walk.cell[rays].T
            occupied = marching.occupied.reshape(-1)[((walk.level[rays, walk.segment[rays]] * res + x) * res + y) * res + z]
            walk.dt[rays[~occupied]] = step_size(walk.t[rays[~occupied]], marching)
            walk.continuous[rays[~occupied]] = False
            walk.phase[rays] = np.where(occupied, EMIT, SKIP)
        rays = np.flatnonzero(walk.phase == SKIP)
        if rays.size:  # cross the empty cell in steps of the dt it was entered with
            arrived = walk.t[rays] + walk.dt[rays] * F32(0.5) >= walk.exit[rays]
            walk.phase[rays[arrived]] = ADVANCE
            moving = rays[~arrived]
            walk.t[moving] = walk.t[moving] + walk.dt[moving]
        rays = np.flatnonzero(walk.phase == EMIT)
        if rays.size:  # one interval per step whose middle is before the exit
            dt = step_size(walk.t[rays], marching)
            past = walk.t[rays] + dt * F32(0.5) >= walk.exit[rays]
            walk.phase[rays[past]] = ADVANCE
            rays, dt = rays[~past], dt[~past]
            following = (walk.t[rays] + dt).astype(F32)
            emitted.append((rays, walk.t[rays].copy(), following))
            walk.continuous[rays] = True
            walk.t[rays] = following
            walk.phase[rays[following >= walk.exit[rays]]] = ADVANCE
        rays = np.flatnonzero(walk.phase == ADVANCE)
        if rays.size:  # single_traversal: the nearest plane crossing moves the walk one cell
            c = walk.crossing[rays]
            axis = np.where((c[:, 0] < c[:, 1]) & (c[:, 0] < c[:, 2]), 0, np.where(c[:, 1] < c[:, 2], 1, 2))
            walk.cell[rays, axis] += walk.steps[rays, axis]
            walk.crossing[rays, axis] = walk.crossing[rays, axis] + walk.delta[rays, axis]
            left = walk.cell[rays, axis] == walk.overflow[rays, axis]
            walk.segment[rays[left]] += 1
            walk.phase[rays] = np.where(left, SEGMENT, CELL)
        if (walk.phase == DONE).all():
            break
    if not emitted:
        return np.zeros(0, np.int64), np.zeros(0, F32), np.zeros(0, F32)
    ray_index = np.concatenate([e[0] for e in emitted])
    order = np.argsort(ray_index, kind="stable")
    return (ray_index[order], np.concatenate([e[1] for e in emitted])[order],
            np.concatenate([e[2] for e in emitted])[order])


def padded(ray_index: np.ndarray, values: np.ndarray, n_rays: int) -> np.ndarray:
    """Packed per-sample values (m, ...) as (n_rays, most, ...) rows, zeros after each ray's own."""
    counts = np.bincount(ray_index, minlength=n_rays)
    slot = np.arange(len(ray_index)) - np.repeat(np.cumsum(counts) - counts, counts)
    out = np.zeros((n_rays, max(int(counts.max(initial=0)), 1), *values.shape[1:]), values.dtype)
    out[ray_index, slot] = values
    return out


@dataclass(frozen=True)
class GridMarchingSampler:
    """nerfstudio's instant-ngp ordinary render (a runtime.render.Sampler): nerfacc's marcher through the grid,
    then w = T·α over black. It skips by construction: only intervals in occupied cells are evaluated."""

    marching: GridMarching
    hierarchical: ClassVar[bool] = False
    skips: ClassVar[bool] = True
    samples_per_ray: ClassVar[int] = 1024  # what sets rays per chunk: a ray rarely holds more

    def render(self, rays: RayBatch, field: FieldFn) -> tuple[np.ndarray, RenderStats]:
        ray_index, t_start, t_end = march(rays.origins, rays.viewdirs, self.marching)
        middles = ((t_start + t_end) / F32(2)).astype(F32)
        points = (rays.origins[ray_index] + rays.viewdirs[ray_index] * middles[:, None]).astype(F32)
        rgbs, sigmas = field(points, np.ascontiguousarray(rays.viewdirs[ray_index])) if len(points) else (
            np.zeros((0, 3), F32), np.zeros(0, F32))
        deltas = padded(ray_index, (t_end - t_start).astype(F32), len(rays))
        weights = render_weights(padded(ray_index, np.nan_to_num(np.ravel(sigmas)).astype(F32), len(rays)), deltas)
        colours = composite(weights, padded(ray_index, np.nan_to_num(rgbs).astype(F32), len(rays)), BLACK)
        return np.clip(colours, 0.0, 1.0), RenderStats(len(rays), len(points), len(points))
