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

from noisenerf.train.hide.jobs import FieldWeights, Job, JobRunner

EXECUTORS = ("local", "ray")
WORKER_CHECK_SECONDS = 1.0  # how often a wait for results looks for a worker process that died


class Executor:
    """Runs submitted jobs; `results` yields (job, result) in the order they finish until none is left
    (jobs submitted while iterating included). A job that fails stops the iteration with its error.
    `slots`: how many jobs it runs at once (the driver keeps that many tiles, and one more, in flight).
    `runner` runs the jobs of this process (the driver assembles tiles with its views); it is let go of with
    the executor, so a hide leaves no device memory behind."""

    slots: int = 1

    def __init__(self):
        self.runner = JobRunner()

    def submit(self, job: Job, prepared: object = None) -> None:
        raise NotImplementedError

    def results(self) -> Iterator[tuple[Job, object]]:
        raise NotImplementedError

    def __enter__(self) -> Executor:
        return self

    def __exit__(self, *exc) -> None:
        self.runner = JobRunner()


def worker_loop(weights: FieldWeights, todo, done) -> None:
    """A worker process of LocalExecutor: (number, pickled (job, prepared)) from `todo` until None, (number,
    pickled result, None) or (number, None, error) to `done`; one torch thread (ExactSolver.threads' reasons),
    and Ctrl-C is the parent's to handle. Plain pickle (between our own processes, never from a file) keeps
    tensors out of shared memory, where multiprocessing's torch reducers would put them."""
    torch.set_num_threads(1)
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    runner = JobRunner()
    for number, pickled in iter(todo.get, None):
        try:
            done.put((number, pickle.dumps(runner.run(weights, *pickle.loads(pickled))), None))
        except Exception as error:  # the job's own error, raised in the driver
            done.put((number, None, sendable(error)))


def sendable(error: Exception) -> Exception:
    """The error itself if it survives pickling (the queue's feeder thread would drop it silently, leaving the
    driver waiting), else a RuntimeError naming it."""
    try:
        pickle.loads(pickle.dumps(error))
    except Exception:
        return RuntimeError(f"{type(error).__name__}: {error}")
    return error


class LocalExecutor(Executor):
    """Jobs in this process, or spread over worker processes with one torch thread each (no OpenMP pool
    spinning beside other work). The workers start once two jobs wait at the same time, so a hide of one
    job never pays their start (~1 s), and stop with the hide, at once (terminated)."""

    def __init__(self, weights: FieldWeights, workers: int):
        super().__init__()
        self.weights, self.slots = weights, max(1, workers)
        self.waiting: deque[tuple[Job, object]] = deque()
        self.running: dict[int, Job] = {}  # submitted to the workers, by number
        self.submitted = 0
        self.workers: list = []
        self.todo = self.done = None

    def submit(self, job: Job, prepared: object = None) -> None:
        self.waiting.append((job, prepared))

    def results(self) -> Iterator[tuple[Job, object]]:
        while self.waiting or self.running:
            if not self.workers and (self.slots == 1 or len(self.waiting) == 1):
                job, prepared = self.waiting.popleft()
                yield job, self.runner.run(self.weights, job, prepared)
                continue
            self.dispatch()
            number, result, error = self.next_done()
            job = self.running.pop(number)
            if error is not None:
                raise error
            yield job, pickle.loads(result)

    def dispatch(self) -> None:
        """Every waiting job to the workers, started on first use."""
        if not self.workers:
            context = multiprocessing.get_context("spawn")
            self.todo, self.done = context.Queue(), context.Queue()
            self.workers = [context.Process(target=worker_loop, args=(self.weights, self.todo, self.done), daemon=True)
                            for _ in range(self.slots)]
            for worker in self.workers:
                worker.start()
        while self.waiting:
            job, prepared = self.waiting.popleft()
            self.running[self.submitted] = job
            self.todo.put((self.submitted, pickle.dumps((job, prepared))))
            self.submitted += 1

    def next_done(self) -> tuple[int, bytes | None, Exception | None]:
        """The next finished job's message; a worker that died (killed, out of memory) stops the hide."""
        while True:
            try:
                return self.done.get(timeout=WORKER_CHECK_SECONDS)
            except queue.Empty:
                dead = next((worker for worker in self.workers if not worker.is_alive()), None)
                if dead is not None:
                    raise RuntimeError(f"a hide worker process ended with exit code {dead.exitcode}")

    def __exit__(self, *exc) -> None:
        super().__exit__(*exc)
        for worker in self.workers:  # every result is in hand, or the hide failed: nothing to wait for
            worker.terminate()
        for worker in self.workers:
            worker.join()
        for channel in (self.todo, self.done):
            if channel is not None:  # jobs never taken are dropped, not flushed to dead workers at exit
                channel.cancel_join_thread()
                channel.close()


def open_executor(name: str, weights: FieldWeights, workers: int, device: torch.device,
                  address: str | None = None, verbose: bool = False) -> Executor:
    """The executor `--executor` names: local with `workers` processes, or ray at `address` (None:
    RAY_ADDRESS, else a local cluster started for the hide; its logs on stderr only when verbose)."""
    if name == "ray":
        from noisenerf.train.hide.ray_executor import RayExecutor

        return RayExecutor(weights, device, address, verbose)
    return LocalExecutor(weights, workers)
