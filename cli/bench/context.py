"""What the experiments of one bench run share (BenchContext), what each hands back (Measured, Section),
and the clocks they measure with."""

from __future__ import annotations

import contextlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Mapping

import numpy as np
import torch

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import resize_image, to_uint8
from noisenerf.runtime.model import Model
from noisenerf.runtime.reveal import Revealed, reveal_tiles
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.scene import Scene

from noisenerf.cli.bench.config import BenchConfig


@dataclass(frozen=True)
class BenchContext:
    """One run's inputs, fixed for every experiment, and what the experiments it needs measured."""

    config: BenchConfig
    scene: Scene
    secret: np.ndarray  # config.secret, uint8 (h, w, 3)
    work: Path  # a temporary folder for the bundles the experiments write
    model_path: Path  # the scene exported as ONNX
    model: Model  # model_path loaded by the runtime
    # by name, what the experiments in its `needs` measured (registry.Experiment.run sets it), read-only
    needed: Mapping[str, Measured] = field(default_factory=lambda: MappingProxyType({}))

    @property
    def device(self) -> torch.device:
        """Where the paper-mode experiments run (paper_quality, error_vs_time, ablation); the others use the CPU."""
        return torch.device(self.config.device)

    def hide(self, secret: np.ndarray, name: str, config: HideConfig, **where) -> dict:
        """hide() on the CPU into WORK/<name>.bundle, overwriting it, without progress bars; its report. An
        inexact hide still writes its bundle: the experiments report exactness rather than stop there.
        where: hide()'s workers and executor, when an experiment chooses them."""
        return hide(self.scene, secret, self.work / f"{name}.bundle", config, torch.device("cpu"), force=True, allow_inexact=True, **where)

    def hide_and_reveal(self, secret: np.ndarray, name: str, config: HideConfig) -> tuple[dict, Revealed, float]:
        """self.hide, then the bundle revealed with onnxruntime: hide's report, the reveal, its seconds."""
        report = self.hide(secret, name, config)
        revealed, seconds = timed(reveal_tiles, load_bundle(self.work / f"{name}.bundle", self.model.mask_secret), self.model.render_config,
                                  self.model.fields())
        return report, revealed, seconds


@dataclass(frozen=True)
class Measured:
    """What an experiment measured: the rows of its CSV. Subclasses add what only its report states."""

    rows: list[dict]
    secret_size: tuple[int, int] | None = None  # (width, height) of the secret it hid, where its report gives it


@dataclass
class Section:
    """One experiment's result: CSV rows, markdown lines, and plots already written."""

    name: str
    title: str
    rows: list[dict]
    lines: list[str]
    plots: list[str] = field(default_factory=list)


def small_secret(secret: np.ndarray, width: int) -> np.ndarray:
    """The secret resized to `width`, its height in proportion but at least 11 (SSIM's window)."""
    return resized(secret, width, max(11, round(secret.shape[0] * width / secret.shape[1])))


def resized(secret: np.ndarray, width: int, height: int) -> np.ndarray:
    """An 8-bit image (h, w, 3) resized to (height, width, 3), 8-bit."""
    return to_uint8(resize_image(secret.astype(np.float32) / 255.0, width, height))


def size_of(image: np.ndarray) -> tuple[int, int]:
    """(width, height) of an (h, w, 3) image."""
    return image.shape[1], image.shape[0]


class Stopwatch:
    """Wall time that can be paused, so measuring quality mid-run does not count as solving."""

    def __init__(self):
        self.started, self.paused = time.perf_counter(), 0.0

    def elapsed(self) -> float:
        return time.perf_counter() - self.started - self.paused

    @contextlib.contextmanager
    def pause(self):
        at = time.perf_counter()
        try:
            yield
        finally:
            self.paused += time.perf_counter() - at


def timed(function, *args, **kwargs):
    started = time.perf_counter()
    result = function(*args, **kwargs)
    return result, time.perf_counter() - started


def synchronized_time(device: torch.device) -> float:
    if device.type == "cuda":
        torch.cuda.synchronize(device)
    return time.perf_counter()


def peak_rss_gib() -> float:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20


@contextlib.contextmanager
def peak_sampled(sample, every: float = 0.05):
    """Samples `sample()` in a thread while the block runs; the yielded list ends holding the peak."""
    peak, done = [0], threading.Event()

    def watch():
        while not done.is_set():
            peak[0] = max(peak[0], sample())
            done.wait(every)

    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    try:
        yield peak
    finally:
        done.set()
        thread.join()
