"""Where a hide's jobs run (jobs.py): `local` (this process, or worker processes of one machine) or `ray`
(ray_executor.py, a Ray cluster). The driver submits jobs and takes their results as they finish; a
result never depends on the executor or its number of workers, since each job is solved from its own
arguments and seed alone.
"""

from __future__ import annotations

import multiprocessing
import pickle
import queue
import signal
from collections import deque
from typing import Iterator

import torch

from noisenerf.train.hide.jobs import FieldWeights, Job, forget, run_job

EXECUTORS = ("local", "ray")


class Executor:
    """Runs submitted jobs; `results` yields (job, result) in the order they finish until none is left
    (jobs submitted while iterating included). A job that fails stops the iteration with its error.
    `slots`: how many jobs it runs at once (the driver keeps that many tiles, and one more, in flight)."""

    slots: int = 1

    def submit(self, job: Job, prepared: object = None) -> None:
        raise NotImplementedError

    def results(self) -> Iterator[tuple[Job, object]]:
        raise NotImplementedError

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        forget()  # the views the driver assembled with, and those of jobs run in this process


POOL_WEIGHTS: FieldWeights | None = None  # a pool worker's copy of the hide's weights (start_worker)


def start_worker(weights: FieldWeights) -> None:
    """A pool worker: the weights once, one torch thread (ExactSolver.threads' reasons), and Ctrl-C is the
    parent's to handle."""
    global POOL_WEIGHTS
    POOL_WEIGHTS = weights
    torch.set_num_threads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def pool_job(pickled: bytes) -> bytes:
    """A pool worker's side of LocalExecutor: pickled (job, prepared) -> pickled result. Plain pickle
    (between our own processes, never from a file) keeps tensors out of shared memory, where
    multiprocessing's torch reducers would put them."""
    return pickle.dumps(run_job(POOL_WEIGHTS, *pickle.loads(pickled)))


class LocalExecutor(Executor):
    """Jobs in this process, or spread over worker processes with one torch thread each (no OpenMP pool
    spinning beside other work). The workers start once two jobs wait at the same time, so a hide of one
    job never pays their start (~1 s), and stop with the hide, at once (terminated)."""

    def __init__(self, weights: FieldWeights, workers: int):
        self.weights, self.slots = weights, max(1, workers)
        self.waiting: deque[tuple[Job, object]] = deque()
        self.finished: queue.Queue = queue.Queue()  # (job, pickled result, error) from the pool's thread
        self.running = 0
        self.pool = None

    def submit(self, job: Job, prepared: object = None) -> None:
        self.waiting.append((job, prepared))

    def results(self) -> Iterator[tuple[Job, object]]:
        while self.waiting or self.running:
            if self.pool is None and (self.slots == 1 or len(self.waiting) == 1):
                job, prepared = self.waiting.popleft()
                yield job, run_job(self.weights, job, prepared)
                continue
            self.dispatch()
            job, result, error = self.finished.get()
            self.running -= 1
            if error is not None:
                raise error
            yield job, pickle.loads(result)

    def dispatch(self) -> None:
        """Every waiting job to the pool, started on first use."""
        if self.pool is None:
            self.pool = multiprocessing.get_context("spawn").Pool(self.slots, initializer=start_worker,
                                                                  initargs=(self.weights,))
        while self.waiting:
            job, prepared = self.waiting.popleft()
            self.running += 1
            self.pool.apply_async(pool_job, (pickle.dumps((job, prepared)),),
                                  callback=lambda result, job=job: self.finished.put((job, result, None)),
                                  error_callback=lambda error, job=job: self.finished.put((job, None, error)))

    def __exit__(self, *exc) -> None:
        super().__exit__(*exc)
        if self.pool is not None:  # every result is in hand, or the hide failed: nothing to wait for
            self.pool.terminate()  # (a clean close waited ~0.5 s for the workers' interpreters to exit)
            self.pool.join()


def open_executor(name: str, weights: FieldWeights, workers: int, device: torch.device,
                  address: str | None = None, verbose: bool = False) -> Executor:
    """The executor `--executor` names: local with `workers` processes, or ray at `address` (None:
    RAY_ADDRESS, else a local cluster started for the hide; its logs on stderr only when verbose)."""
    if name == "ray":
        from noisenerf.train.hide.ray_executor import RayExecutor

        return RayExecutor(weights, device, address, verbose)
    return LocalExecutor(weights, workers)
