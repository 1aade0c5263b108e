"""A hide's unit of work: one job, a pure function of (the field's weights, a tile, a part, settings, seed).

The driver (run.py) plans a tile's jobs from its Solver: first, where the method needs one, the tile's
shared job (part PREPARE: the exact method's compact basis, the paper method's survey of the clean view),
then one job per part (exact parts, paper blocks), each given the shared result. A job reads nothing but
its arguments, so it gives the same result in the driver, in a worker process or on a Ray node; the driver
alone saves parts for a resume, shows progress and assembles tiles (executors.py runs the jobs).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch

from noisenerf.runtime.bundle import Tile
from noisenerf.runtime.render import RenderConfig
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.secret_view import SecretView
from noisenerf.train.hide.solvers import SOLVERS
from noisenerf.train.scene.field_kinds import Field, FieldConfigs, build_field
from noisenerf.train.scene.scene import Scene

PREPARE = -1  # the part number of a tile's shared job (also its seed's part number, solver.part_seed)
VIEWS_KEPT = 2  # secret views a process keeps: a worker's jobs mostly come tile by tile


@dataclass(frozen=True, eq=False)  # arrays have no truth value
class FieldWeights:
    """The network a hide renders, as plain arrays: what goes to the workers once (a local worker's start,
    Ray's object store), never with each job. `key` names it in a worker's caches."""

    key: str
    config: FieldConfigs
    arrays: dict[str, np.ndarray]
    render: RenderConfig

    @staticmethod
    def of(scene: Scene, network: str) -> FieldWeights:
        field = scene.fields()[network]
        arrays = {name: value.detach().cpu().numpy() for name, value in field.state_dict().items()}
        return FieldWeights(f"{scene.fingerprint()}/{network}", field.config, arrays, scene.config.render)


@dataclass(frozen=True, eq=False)  # tensors have no truth value
class Job:
    """Tile `tile_index`'s shared job (part PREPARE) or one of its parts: rows [start, stop) of the tile's rays, with
    their pixels (m, 3) uint8 (the whole tile's for the shared job)."""

    tile_index: int
    part: int
    tile: Tile  # noise still empty
    rows: range
    pixels: torch.Tensor
    config: HideConfig
    device: str


def loaded_field(weights: FieldWeights, device: torch.device) -> Field:
    field = build_field(weights.config)
    field.load_state_dict({name: torch.from_numpy(value.copy()) for name, value in weights.arrays.items()})
    return field.to(device).eval().requires_grad_(False)


class JobRunner:
    """Runs jobs in one process, keeping what consecutive jobs share: the last network loaded and the VIEWS_KEPT
    latest secret views. Whoever runs jobs owns one: an executor for the jobs it runs in the driver's process
    (whose driver assembles tiles with the same views), each local worker's loop, each Ray worker process."""

    def __init__(self):
        self.fields: OrderedDict = OrderedDict()  # (weights key, device) -> Field, one kept
        self.views: OrderedDict = OrderedDict()  # (weights key, device, tile) -> SecretView, VIEWS_KEPT kept

    def view(self, weights: FieldWeights, tile: Tile, device: torch.device) -> SecretView:
        """The whole tile's secret view, as the driver builds it: a part's rays are a subset of it (never a
        view of those rays alone, whose encodings could round differently in torch's vectorised loops)."""
        field = kept(self.fields, (weights.key, str(device)), 1, lambda: loaded_field(weights, device))
        return kept(self.views, (weights.key, str(device), tile), VIEWS_KEPT,
                    lambda: SecretView(field, tile, weights.render, device))

    def run(self, weights: FieldWeights, job: Job, prepared: object = None) -> object:
        """A job's result: the tile's shared result for part PREPARE, else the part's tensors as saved for a
        resume (`prepared`: the tile's shared result, or None where the method needs none)."""
        solver, device = SOLVERS[job.config.method], torch.device(job.device)
        with torch.no_grad(), solver.threads(device):
            view, pixels = self.view(weights, job.tile, device), job.pixels.to(device)
            if job.part == PREPARE:
                return solver.prepare(view, pixels, job.config, job.tile_index)
            return solver.solve_part(view, job.rows, pixels, job.config, job.tile_index, job.part, prepared,
                                     job.tile.rect[2])


def kept(cache: OrderedDict, key, size: int, build):
    """cache[key], built on a miss; the least recently used entries beyond `size` are dropped."""
    if key not in cache:
        cache[key] = build()
        while len(cache) > size:
            cache.popitem(last=False)
    cache.move_to_end(key)
    return cache[key]
