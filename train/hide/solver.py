"""The interface every hiding method implements.

A method (`--method NAME`) is one Solver: it owns its settings dataclasses (each recorded in the bundle
under its `key`), its defaults (layouts, samples per ray, network), its checks, its CLI flags and how it
solves one tile, resumably (its flags are declared in cli/main.py, torch-free). `methods.py` registers
them; `run.hide` plans tiles, renders each tile's secret view and hands it to the method, with a
ChunkPool of worker processes for independent parts. A new method is one module with a Solver plus one
registry line.
"""

from __future__ import annotations

import argparse
import contextlib
import multiprocessing
import pickle
import signal
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, ClassVar, Iterator

import torch

from noisenerf.runtime.bundle import TileNoise
from noisenerf.train.hide.secret_view import SecretView

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig
    from noisenerf.train.hide.progress import Progress


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


def chunk_seed(config: HideConfig, tile: int, chunk: int) -> int:
    """The seed of one chunk's solve (chunk −1: the tile's compact basis). The strides keep the seeds of one
    run's chunks distinct while a tile has fewer than 10,007 chunks (a 512² tile has 16 on a CPU); primes,
    so that runs with neighbouring seeds do not repeat each other's chunk seeds in step."""
    return config.seed * 1_000_003 + tile * 10_007 + chunk


def run_job(item: tuple[int, Callable, bytes]) -> tuple[int, bytes]:
    """A worker's side of ChunkPool.solve_all: (i, solve, pickled args) -> (i, pickled result). Plain pickle
    (between our own processes, never from a file) keeps tensors out of shared memory, where
    multiprocessing's torch reducers would put them, and no_grad keeps results picklable."""
    i, solve, job = item
    with torch.no_grad():
        return i, pickle.dumps(solve(*pickle.loads(job)))


def start_worker() -> None:
    """One torch thread (ExactSolver.threads' reasons); Ctrl-C is the parent's to handle."""
    torch.set_num_threads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


class ChunkPool:
    """Worker processes a solver may spread independent chunks over, each with one torch thread (the
    reasons of ExactSolver.threads: no OpenMP pool spinning beside other work). They start at the first
    `solve_all` with more than one job, so a hide of one chunk never pays their start (~1 s), and stop
    with the hide, at once (terminated). Results never depend on the number of workers: each chunk is
    solved from its own inputs and seed, exactly as in one process."""

    def __init__(self, workers: int):
        self.workers = max(1, workers)
        self.pool = None

    def solve_all(self, solve: Callable, jobs: list[tuple]) -> Iterator[tuple[int, object]]:
        """(i, solve(*jobs[i])) for every job, in the order they finish; `solve` must be a module-level
        function when there are workers. A job that raises stops the rest."""
        if self.workers == 1 or len(jobs) <= 1:
            for i, job in enumerate(jobs):
                yield i, solve(*job)
            return
        if self.pool is None:
            self.pool = multiprocessing.get_context("spawn").Pool(self.workers, initializer=start_worker)
        pickled = [(i, solve, pickle.dumps(job)) for i, job in enumerate(jobs)]
        for i, result in self.pool.imap_unordered(run_job, pickled):
            yield i, pickle.loads(result)

    def __enter__(self) -> ChunkPool:
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:  # every result is in hand, or the hide failed: nothing to wait for
            self.pool.terminate()  # (a clean close waited ~0.5 s for the workers' interpreters to exit)
            self.pool.join()


class Solver:
    """A hiding method. Subclasses set the class attributes and implement solve_tile."""

    name: ClassVar[str]  # the --method value, recorded in bundles
    settings_types: ClassVar[tuple[type, ...]]  # frozen dataclasses with a `key`, their defaults in every config
    layouts: ClassVar[tuple[str, ...]]  # noise layouts it can write, the default first
    default_samples: ClassVar[int]  # samples per ray of its secret view
    default_network: ClassVar[str | None] = None  # None: the scene's render network
    exact: ClassVar[bool] = False  # whether it promises every 8-bit value: run.hide then refuses to write less

    def check(self, config: HideConfig) -> None:
        """Refuse settings this method cannot honour (UserError)."""

    def settings_from_arguments(self, args: argparse.Namespace, device: torch.device) -> tuple:
        """Its settings as `noisenerf hide`'s flags ask, for `device`. The flags themselves are declared in
        cli/main.py, whose parser must not import torch (instant --help, one clear line without it)."""
        return ()

    def threads(self, device: torch.device):
        """A context in which the solve runs (thread settings); nothing by default."""
        return contextlib.nullcontext()

    def solve_tile(self, secret_view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                   progress: Progress, k: int, bar, pool: ChunkPool) -> TileSolution:
        """Solve tile k: pixels (n, 3) uint8 of a (height, width) tile, saving resumable parts in progress;
        independent parts may go to the pool's workers."""
        raise NotImplementedError
