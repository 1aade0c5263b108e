"""The interface every hiding method's solver implements.

A method (`--method NAME`) is described torch-free by its Method (methods.py: settings, defaults,
checks, flags); its Solver is how it solves one tile, resumably, and names its Method. `solvers.py`
registers them. A method cuts a tile into parts (`part_pixels` rays each), solved independently by `solve_part`,
after the tile's shared job `prepare` where it `prepares`; both are pure (jobs.py runs them wherever an
executor puts them), and `assemble` makes the tile from the parts' results. `run.hide` plans, saves parts
for a resume, and assembles. A new method is one Method (methods.py), one module with its Solver, and one
registry line (solvers.py).
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, ClassVar

import torch

from noisenerf.runtime.layouts import TileNoise
from noisenerf.train.hide.methods import Method
from noisenerf.train.hide.secret_view import SecretView

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig


@dataclass(frozen=True)
class TileSolution:
    """One solved tile: the noise as a reveal expands it (n, 1 or n_samples, dims) float32, what the
    method reports about it, and what the bundle stores (in the storage dtype, of the layout's kind)."""

    noise: torch.Tensor
    report: dict
    stored: TileNoise


def storage_dtype(name: str) -> torch.dtype:
    """The torch dtype of a bundle dtype name (runtime/bundle.DTYPES names them as torch does)."""
    return getattr(torch, name)


def part_seed(config: HideConfig, tile: int, part: int) -> int:
    """The seed of one part's solve (part −1: the tile's compact basis). The strides keep the seeds of one
    run's parts distinct while a tile has fewer than 10,007 parts (a 512² tile has 16 on a CPU); primes,
    so that runs with neighbouring seeds do not repeat each other's part seeds in step."""
    return config.seed * 1_000_003 + tile * 10_007 + part


class Solver:
    """A hiding method. Subclasses set the class attributes and implement the parts' methods."""

    method: ClassVar[Method]  # what it is to the CLI, HideConfig and the driver (methods.METHODS)

    def threads(self, device: torch.device):
        """A context in which the solve runs (thread settings); nothing by default."""
        return contextlib.nullcontext()

    def prepares(self, config: HideConfig) -> bool:
        """Whether a tile's parts need a shared result (`prepare`) first."""
        return False

    def prepare(self, secret_view: SecretView, pixels: torch.Tensor, config: HideConfig, tile_index: int) -> object:
        """The shared result of tile `tile_index` from its view and pixels (n, 3) uint8: pure, run as a job."""
        raise NotImplementedError

    def part_pixels(self, config: HideConfig) -> int:
        """Rays per part: solved, saved and resumed together."""
        raise NotImplementedError

    def solve_part(self, secret_view: SecretView, rows: range, pixels: torch.Tensor, config: HideConfig, tile_index: int,
                   part: int, prepared: object, width: int) -> dict[str, torch.Tensor]:
        """Part `part` of tile `tile_index`, the tile's rays `rows` (whole rows of the tile, `width` rays each:
        tiling.part_rows) with their pixels (m, 3) uint8: its tensors as saved for a resume. Pure, run as a job;
        `prepared` is the tile's shared result (None without one)."""
        raise NotImplementedError

    def part_layout(self, config: HideConfig, rows: int, dims: int, prepared: object) -> tuple[dict, Callable]:
        """What a saved part of `rows` rays must hold, (shape, dtype) by name, and the check of its values
        beyond that (ResumeStore.load)."""
        raise NotImplementedError

    def assemble(self, secret_view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                 prepared: object, parts: list[dict[str, torch.Tensor]]) -> TileSolution:
        """The solved tile from its parts' results, in order; pixels (n, 3) uint8 of a (height, width) tile."""
        raise NotImplementedError
