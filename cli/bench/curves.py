"""One solver over a single-tile secret view, measured as a quality curve: the exact solver iteration by
iteration, the paper's block by block (the paper-mode and skipping experiments)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable

import numpy as np
import torch

from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.metrics import ssim_authors, tile_quality
from noisenerf.train.hide.exact import ExactProblem, NoiseSpace, Refinement, SolveCounts, solve_exact
from noisenerf.train.hide.paper import recorded_points, skip_shares, solve_blocks, survey
from noisenerf.train.hide.settings import ExactSettings, PaperSettings
from noisenerf.train.hide.plan import HideConfig, plan
from noisenerf.train.hide.secret_view import SecretView
from noisenerf.train.hide.tiling import MIN_TILE_SIZE
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.scene import Scene

from noisenerf.cli.bench.context import Stopwatch, synchronized_time


def secret_view(scene: Scene, secret: np.ndarray, view: int, n_samples: int, device: torch.device = torch.device("cpu"),
                field: Field | None = None) -> SecretView:
    """The single-tile secret view of `secret` at scene camera `view` with n_samples per ray, on `field`
    (default: the tile's network, the coarse one for paper mode as the authors render, else the render field)."""
    config = HideConfig(method="exact" if n_samples == 1 else "paper", n_samples=n_samples, view=view,
                        tile_size=max(*secret.shape[:2], MIN_TILE_SIZE))
    tile = plan(scene, secret, config).tiles[0]
    return SecretView(field or scene.fields()[tile.network], tile, scene.config.render, device)


def secret_quality(colors: torch.Tensor, secret: np.ndarray) -> dict:
    """hide.quality of a rendered tile (n, 3) against the secret (h, w, 3) uint8."""
    return tile_quality(colors.cpu().numpy(), secret.reshape(-1, 3), secret.shape[:2])


@dataclass(frozen=True, eq=False, kw_only=True)
class WatchedProblem(ExactProblem):
    """An exact problem measured iteration by iteration: `observe(index (m,), noise (m, 1, dims), counts)` after
    every Levenberg–Marquardt step, and with `retiring` off, finished pixels kept in the batch (what
    retiring them saves)."""

    observe: Callable[[torch.Tensor, torch.Tensor, SolveCounts], None]
    retiring: bool = True

    def batch(self, state: Refinement) -> torch.Tensor:
        return super().batch(state) if self.retiring else state.active

    def step(self, state: Refinement) -> None:
        super().step(state)
        self.observe(self.index, self.space.expand(state.params), self.counts)


def exact_curve(scene: Scene, secret: np.ndarray, view: int, retiring: bool = True,
                device: torch.device = torch.device("cpu")) -> tuple[list[dict], dict]:
    """Quality of the whole secret after every LM iteration of the exact solver in the full noise (the ray
    layout, float16), observation excluded; `retiring` off keeps finished pixels in the batch."""
    scene.to(device)
    tile_view = secret_view(scene, secret, view, 1, device)
    pixels = torch.from_numpy(secret.reshape(-1, 3).copy()).to(device)
    current = torch.zeros(tile_view.n_rays, 1, tile_view.noise_dims, device=device)
    index = torch.arange(tile_view.n_rays, device=device)
    watch, rows = Stopwatch(), []

    def record(which, noise, counts):
        with watch.pause():
            current[which] = noise
            with torch.no_grad():
                colors = tile_view.render(index, current)
            rows.append({"method": "exact", "iteration": len(rows) + 1, "seconds": watch.elapsed(),
                         "jacobians_per_pixel": counts.jacobians / len(index), **secret_quality(colors, secret)})

    problem = WatchedProblem(tile_view, index, pixels, NoiseSpace(torch.float16), ExactSettings(),
                             torch.Generator().manual_seed(0), observe=record, retiring=retiring)
    solve_exact(problem)
    return rows, {"seconds": watch.elapsed(), **dataclasses.asdict(problem.counts)}


@dataclass(frozen=True)
class PaperNoise:
    """Paper-mode noise over a whole secret view, as the solver left it."""

    noise: torch.Tensor  # (n, k, dims) float32 on the CPU
    secret_view: SecretView
    secret: np.ndarray  # the secret it hides, uint8 (h, w, 3)


@dataclass
class PaperRun:
    """One paper-mode run over a whole secret view: quality at each recorded iteration and its cost."""

    rows: list[dict]
    seconds: float
    peak_gib: float | None  # device memory (CUDA only)
    dead_fraction: float
    skipping: dict[str, float]  # paper.skip_shares: what skipping left out
    kept: PaperNoise | None = None  # the noise it found, when asked to keep it


def paper_curve(scene: Scene, secret: np.ndarray, view: int, n_samples: int, settings: PaperSettings,
                device: torch.device, label: str = "paper", keep_noise: bool = False) -> PaperRun:
    """The paper's method on the coarse field, block by block as `hide` runs it. Blocks run one after
    another, so the time at iteration t is the run's time × t / iters (recording renders included)."""
    scene.to(device)
    tile_view = secret_view(scene, secret, view, n_samples, device, scene.coarse)
    pixels = torch.from_numpy(secret.reshape(-1, 3).copy()).to(device)
    if device.type == "cuda":
        torch.cuda.reset_peak_memory_stats(device)
    started = synchronized_time(device)
    clean = survey(tile_view, settings.pass_samples)
    points = recorded_points(settings)
    colors = torch.zeros(len(points), tile_view.n_rays, 3)
    kept, work = [], torch.zeros(3, dtype=torch.int64)
    for block in solve_blocks(tile_view, pixels, n_samples, settings, clean, torch.float32):
        colors[:, block.index.cpu()] = block.colors
        work += block.work
        if keep_noise:
            kept.append(block.noise)
    seconds = synchronized_time(device) - started
    peak = torch.cuda.max_memory_allocated(device) / 2 ** 30 if device.type == "cuda" else None
    rows = []
    for i, t in enumerate(points):
        image = to_uint8(colors[i].numpy()).reshape(secret.shape) / 255.0
        rows.append({"method": label, "iteration": t, "seconds": seconds * t / settings.iters,
                     "loss": float(((colors[i] - pixels.cpu().float() / 255.0) ** 2).sum(-1).mean()),
                     **secret_quality(colors[i], secret), "ssim_authors": ssim_authors(image, secret / 255.0)})
    return PaperRun(rows, seconds, peak, float((~clean.alive).float().mean()),
                    skip_shares(work, tile_view.n_rays, tile_view.n_samples, settings.iters),
                    PaperNoise(torch.cat(kept).float(), tile_view, secret) if keep_noise else None)
