"""`--executor ray`: a hide's jobs as Ray tasks, on a running cluster or a local one started for the hide.

The field's weights go to the object store once (ray.put) and every task reads them from there; a
tile's shared result likewise, once per tile. A task asks for one CPU, or one GPU on CUDA. Ray retries a
task whose worker died (MAX_RETRIES); a task that fails for good stops the hide with one line. Ray is an
optional extra, imported only here, when the executor is chosen.
"""

from __future__ import annotations

import functools
import logging
import os
import socket
from typing import Iterator

import torch

from noisenerf.runtime.errors import UserError
from noisenerf.train.hide.executors import Executor
from noisenerf.train.hide.jobs import PREPARE, FieldWeights, Job, JobRunner

CONNECT_SECONDS = 5.0  # how long an address may take to accept a connection before the hide gives up
MAX_RETRIES = 3  # a task's reruns after its worker dies (a node lost, a process killed); not for errors
INSTALL = "--executor ray needs Ray: pip install 'noisenerf[cluster]'"
ADDRESS_FLAG, RAY_ADDRESS_ENV = "--ray-address", "RAY_ADDRESS"  # where a cluster's address comes from


def import_ray():
    """The ray module, or one clear line on how to install it."""
    try:
        import ray
    except ModuleNotFoundError as error:
        if error.name != "ray":
            raise
        raise UserError(INSTALL) from None
    return ray


class RayExecutor(Executor):
    """Jobs as Ray tasks. Connects to `address` (None: RAY_ADDRESS, else a local cluster it starts and
    stops), unless this process is connected already (then it leaves the connection as it found it). Ray's
    own log lines (and its workers') reach stderr only when verbose."""

    def __init__(self, weights: FieldWeights, device: torch.device, address: str | None, verbose: bool = False):
        super().__init__()
        self.ray = import_ray()
        self.started = not self.ray.is_initialized()
        if self.started:
            address, source = cluster_address(address)
            check_reachable(address, source)
            try:
                self.ray.init(address=address, include_dashboard=False, log_to_driver=verbose,
                              logging_level=logging.INFO if verbose else logging.ERROR)
            except ConnectionError as error:
                raise UserError(f"cannot connect to the Ray cluster at {address or source}: {error}") from None
        resources = {"num_gpus": 1} if device.type == "cuda" else {"num_cpus": 1}
        self.slots = max(1, int(self.ray.cluster_resources().get("GPU" if device.type == "cuda" else "CPU", 1)))
        self.task = self.ray.remote(run_job).options(max_retries=MAX_RETRIES, **resources)
        self.weights = self.ray.put(weights)
        self.prepared: dict[int, tuple[object, object]] = {}  # tile -> (its shared result, its object ref)
        self.pending: dict = {}  # object ref -> job

    def submit(self, job: Job, prepared: object = None) -> None:
        if prepared is not None and self.prepared.get(job.tile_index, (None,))[0] is not prepared:
            self.prepared[job.tile_index] = (prepared, self.ray.put(prepared))
        reference = self.prepared[job.tile_index][1] if prepared is not None else None
        self.pending[self.task.remote(self.weights, job, reference)] = job

    def results(self) -> Iterator[tuple[Job, object]]:
        while self.pending:
            [ready], _ = self.ray.wait(list(self.pending), num_returns=1)
            job = self.pending.pop(ready)
            try:
                result = self.ray.get(ready)
            except self.ray.exceptions.RayError as error:
                raise UserError(f"{describe(job)} failed on the Ray cluster: {cause(error)}") from None
            if all(other.tile_index != job.tile_index for other in self.pending.values()):  # the tile's last job for now
                self.prepared.pop(job.tile_index, None)
            yield job, result

    def __exit__(self, *exc) -> None:
        super().__exit__(*exc)
        for reference in self.pending:  # a failed or interrupted hide leaves nothing running
            self.ray.cancel(reference, force=True)
        if self.started:
            self.ray.shutdown()


def run_job(weights: FieldWeights, job: Job, prepared: object = None) -> object:
    """A Ray task: the job, run by this worker process's runner. Ray reuses a worker process for task after
    task, and a task has no place but its process to keep what consecutive jobs share (an actor would hold a
    CPU for the hide's whole life and give up task retries' plain rescheduling)."""
    return worker_runner().run(weights, job, prepared)


@functools.cache
def worker_runner() -> JobRunner:
    """The runner of this Ray worker process (one per process, built by its first task)."""
    return JobRunner()


def cluster_address(flag: str | None) -> tuple[str | None, str]:
    """The address a hide connects to and where it came from: --ray-address, else RAY_ADDRESS (the default the
    help names, checked as the flag is), else None (a local cluster)."""
    if flag is not None:
        return flag, ADDRESS_FLAG
    return os.environ.get(RAY_ADDRESS_ENV) or None, RAY_ADDRESS_ENV


def check_reachable(address: str | None, source: str = ADDRESS_FLAG, timeout: float = CONNECT_SECONDS) -> None:
    """Refuse at once a cluster address nothing answers at (HOST:PORT or ray://HOST:PORT): ray.init would
    retry for minutes, logging as it goes. None, "auto" and "local" are Ray's to resolve. source: the flag or
    variable the address came from, for the message."""
    if address is None or address in ("auto", "local"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not port.isdigit():
        raise UserError(f"{source} must be HOST:PORT or ray://HOST:PORT, got {address!r:.80}")
    where = address if source == ADDRESS_FLAG else f"{address} (from {source})"
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as error:
        raise UserError(f"cannot reach the Ray cluster at {where}: {error.strerror or error}") from None


def describe(job: Job) -> str:
    return f"tile {job.tile_index}'s {'shared job' if job.part == PREPARE else f'part {job.part}'}"


def cause(error: Exception) -> str:
    """One line for a task's failure: the job's own exception where it raised one, else Ray's."""
    inner = getattr(error, "cause", None) or error
    return f"{type(inner).__name__}: {str(inner).strip().splitlines()[-1] if str(inner).strip() else ''}"
