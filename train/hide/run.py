"""`noisenerf hide`: train the noise that makes a frozen scene render a secret (Noise-NeRF).

The secret is planned into tiles (plan.py), one viewpoint each; the chosen method (methods.py) cuts each
tile into parts, solved as pure jobs (jobs.py) wherever the executor runs them (executors.py), several
tiles at once (one more than the executor runs jobs at once). The Driver alone saves each finished part
beside the output (OUT.partial/, progress.py), so an interrupted hide run again with the same arguments
resumes where it stopped and writes a byte-identical bundle, and assembles the tiles; hide writes the bundle.
It holds the secret's 8-bit pixels, the finished tiles' noise as the bundle stores it, and the tiles in
flight, so its memory grows with the tile size, not the secret's, beyond what the bundle itself will hold.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

import noisenerf
from noisenerf.runtime.bundle import Bundle, Tile, secret_digest
from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.errors import InexactResult, UserError
from noisenerf.runtime.files import check_output_path, write_bytes
from noisenerf.runtime.layouts import LAYOUTS
from noisenerf.runtime.limits import checked_image_size
from noisenerf.runtime.masking import mask_salt
from noisenerf.runtime.metrics import tile_quality
from noisenerf.runtime.progress import Counter, ProgressFn
from noisenerf.runtime.sealing import Keys, tagged
from noisenerf.train.hide.executors import EXECUTORS, open_executor
from noisenerf.train.hide.jobs import PREPARE, FieldWeights, Job
from noisenerf.train.hide.methods import EXACT_MARGIN_LEVELS
from noisenerf.train.hide.plan import HideConfig, plan, run_key
from noisenerf.train.hide.resume import ResumeStore
from noisenerf.train.hide.settings import pass_samples_for
from noisenerf.train.hide.solvers import SOLVERS
from noisenerf.train.hide.tiling import part_rows
from noisenerf.train.scene.scene import Scene


PAYLOAD_IS_EXACT = "a payload is revealed whole or not at all: --allow-inexact is for images"


@dataclass
class TileWork:
    """A tile on its way through the hide: its pixels (n, 3) uint8 on the CPU, its parts' rows, its shared
    result once known, its parts' results as they come, and which of those a resume loaded from disk."""

    tile_index: int
    tile: Tile
    pixels: torch.Tensor
    parts: list[range]
    started: float
    prepared: object = None
    solved: dict = field(default_factory=dict)
    loaded: set = field(default_factory=set)


def hide(scene: Scene, secret: np.ndarray, output: Path, config: HideConfig, device: torch.device,
         force: bool = False, progress: ProgressFn | None = None, payload_marker: dict | None = None,
         workers: int | None = None, allow_inexact: bool = False, executor: str = "local",
         ray_address: str | None = None, verbose: bool = False, seal_keys: Keys | None = None) -> dict:
    """Hide `secret` (H, W, 3) uint8 in the scene; write the bundle to `output`; return the report.
    payload_marker: the bundle's payload marker when the secret carries a payload (train.hide.payload), else None; seal_keys: a
    sealed payload's keys, under which the bundle is tagged before it is written.
    progress: told of the pixels solved (runtime.progress; parts solved again are taken back).
    A method that promises exactness (Method.exact) and leaves a tile's pixels off raises InexactResult at
    that tile, writing no bundle and keeping the solved parts for a resume, unless allow_inexact (never for
    a payload, which is revealed whole or not at all).
    executor: where the jobs run (executors.py): "local", over `workers` processes on a CPU (None: every
    core this process may use), or "ray", at ray_address (None: RAY_ADDRESS, else a local cluster); the
    bundle's bytes never depend on either; verbose lets Ray's own log lines through. Local workers are spawned, so a script that calls hide on a
    secret of several jobs guards its top level with `if __name__ == "__main__":`, as multiprocessing requires."""
    output = check_output_path(output, force=force)
    checked_image_size(secret.shape[1], secret.shape[0], "the secret image")  # what a bundle may hold
    if executor not in EXECUTORS:
        raise UserError(f"unknown executor {executor!r} ({' or '.join(EXECUTORS)})")
    hide_plan = plan(scene, secret, config)  # checks the sampling first
    noise_layout = LAYOUTS[config.layout]
    if config.n_samples > noise_layout.max_samples:
        raise UserError(f"the {noise_layout.name} layout serves at most {noise_layout.max_samples} samples per ray, "
                        f"not {config.n_samples}")
    noise_dims = scene.render_field.config.noise_dims
    solver = SOLVERS[config.method]
    if allow_inexact and payload_marker is not None:
        raise UserError(PAYLOAD_IS_EXACT)
    workers = (available_cores() if workers is None else workers) if device.type == "cpu" and solver.method.spreads else 1
    weights = FieldWeights.of(scene, hide_plan.tiles[0].network)
    key, digests = run_key(scene, secret, config), scene.digests()
    with ResumeStore(output, key) as resume, \
            open_executor(executor, weights, workers, device, ray_address, verbose) as jobs:
        started = time.perf_counter()
        driver = Driver(secret, config, device, weights, solver, noise_dims, resume, jobs, allow_inexact,
                        Counter(progress, "hide", secret.shape[0] * secret.shape[1], "px"), hide_plan.tiles)
        driver.run()
        tiles, reports = driver.tiles, driver.reports
        bundle = Bundle(model_fingerprint=digests.fingerprint, width=secret.shape[1], height=secret.shape[0],
                        secret_sha256=secret_digest(secret), layout=config.layout,
                        noise_dims=noise_dims, dtype=config.dtype, tiles=tuple(tiles),
                        extra={"method": config.method, "noisenerf": noisenerf.__version__,
                               "config": config.to_dict()}, payload_marker=payload_marker,
                        coefficients=noise_layout.coefficients_of(tiles[0].noise), mask_salt=mask_salt(key))
        data = bundle.to_bytes(digests.mask_secret)
        write_bytes(output, data if seal_keys is None else tagged(data, seal_keys), replace=force)
        resume.clear()
    n_pixels = secret.shape[0] * secret.shape[1]
    exact_pixels = sum(r["exact_fraction"] * r["rect"][2] * r["rect"][3] for r in reports)
    return {
        "bundle": str(output), "method": config.method, "layout": config.layout, "dtype": config.dtype,
        "width": secret.shape[1], "height": secret.shape[0], "tiles": reports,
        "exact_fraction": exact_pixels / n_pixels, "exact": all(r["exact_fraction"] == 1.0 for r in reports),
        "margin_levels": min(r["margin_levels"] for r in reports),
        "bundle_bytes": output.stat().st_size, "bytes_per_pixel": output.stat().st_size / n_pixels,
        "seconds": round(time.perf_counter() - started, 2),
    }


class Driver:
    """A hide's scheduler: tiles started in order while the executor's slots, plus one, are in flight (enough to
    keep every slot busy, while the driver's memory grows with the tile size, not the secret's); each tile's
    shared job first where its method has one, then its parts, taken from the resume folder where saved and
    sound, else submitted; each finished part saved; each tile assembled and checked once its parts are in.
    A tile left inexact by parts a resume loaded (another run's, or edited and stamped anew) has those parts
    deleted and solved again: a saved part is never trusted over a fresh solve."""

    def __init__(self, secret: np.ndarray, config: HideConfig, device: torch.device, weights: FieldWeights,
                 solver, noise_dims: int, resume: ResumeStore, jobs, allow_inexact: bool, pixels_done: Counter,
                 planned: tuple[Tile, ...]):
        self.secret, self.config, self.device, self.weights = secret, config, device, weights
        self.solver, self.noise_dims, self.resume, self.jobs = solver, noise_dims, resume, jobs
        self.allow_inexact, self.pixels_done = allow_inexact, pixels_done
        self.tiles: list[Tile | None] = [None] * len(planned)  # as stored, once finished
        self.reports: list[dict | None] = [None] * len(planned)
        self.works: dict[int, TileWork] = {}  # the tiles in flight: their pixels, parts and results held till done
        self.waiting = iter(enumerate(planned))

    def run(self) -> None:
        self.start_tiles()
        for done, result in self.jobs.results():
            work = self.works[done.tile_index]
            if done.part == PREPARE:
                work.prepared = result
                if self.start_parts(work):
                    self.finish(work)
            else:
                self.resume.save(done.tile_index, done.part, result)
                work.solved[done.part] = result
                self.pixels_done(len(done.rows))
                if len(work.solved) == len(work.parts):
                    self.finish(work)
            self.start_tiles()

    def job(self, work: TileWork, part: int, rows: range) -> Job:
        # a copy: a slice would pickle (pool, Ray) the whole tile's pixels with every part
        return Job(work.tile_index, part, work.tile, rows, work.pixels[rows.start:rows.stop].clone(), self.config,
                   str(self.device))

    def start_tiles(self) -> None:
        while len(self.works) <= self.jobs.slots:
            index, tile = next(self.waiting, (None, None))
            if tile is None:
                return
            self.works[index] = work = tile_work(index, tile, self.secret, self.solver.part_pixels(self.config))
            if self.solver.prepares(self.config):
                self.jobs.submit(self.job(work, PREPARE, range(len(work.pixels))))
            elif self.start_parts(work):
                self.finish(work)

    def start_parts(self, work: TileWork) -> bool:
        """The tile's saved parts taken, the others submitted. -> whether none is left to solve."""
        for c, rows in enumerate(work.parts):
            layout, sound = self.solver.part_layout(self.config, len(rows), self.noise_dims, work.prepared)
            saved = self.resume.load(work.tile_index, c, layout, sound)
            if saved is None:
                self.jobs.submit(self.job(work, c, rows), work.prepared)
            else:
                work.solved[c] = saved
                work.loaded.add(c)
                self.pixels_done(len(rows))
        return len(work.solved) == len(work.parts)

    def finish(self, work: TileWork) -> None:
        """The tile assembled from its parts, checked by rendering it whole, and let go of."""
        x0, y0, w, h = work.tile.rect
        secret_view = self.jobs.runner.view(self.weights, work.tile, self.device)  # the jobs' own where they ran here
        pixels = work.pixels.to(self.device)
        solved = self.solver.assemble(secret_view, pixels, (h, w), self.config, work.prepared,
                                      [work.solved[c] for c in range(len(work.parts))])
        colors = secret_view.render_all(solved.noise, pass_samples_for(self.device.type))
        quality = tile_quality(colors.cpu().numpy(), pixels.cpu().numpy(), (h, w))
        thin = quality["margin_levels"] < EXACT_MARGIN_LEVELS  # some value rounds wrong, or barely right
        inexact = self.solver.method.exact and thin
        if inexact and work.loaded:
            for c in sorted(work.loaded):
                self.resume.discard(work.tile_index, c)
                del work.solved[c]
                self.pixels_done(-len(work.parts[c]))
                self.jobs.submit(self.job(work, c, work.parts[c]), work.prepared)
            work.loaded.clear()
            return
        if inexact and not self.allow_inexact:
            off = (f"{quality['inexact_pixels']} pixels off, by up to {quality['max_error']} levels"
                   if quality["inexact_pixels"] else
                   f"a value {quality['margin_levels']:.3f} levels from its rounding boundary (an exact hide keeps "
                   f"{EXACT_MARGIN_LEVELS})")
            raise InexactResult(
                f"tile {work.tile_index} (view {work.tile.view}, {w}x{h} px at x={x0}, y={y0}) has {off}; no bundle "
                f"written (solved parts kept in {self.resume.directory} for a resume; --allow-inexact writes the "
                f"bundle anyway)")
        self.tiles[work.tile_index] = dataclasses.replace(work.tile, noise=solved.stored)
        self.reports[work.tile_index] = {"rect": list(work.tile.rect), "view": work.tile.view, **quality, **solved.report,
                                "seconds": round(time.perf_counter() - work.started, 2)}
        del self.works[work.tile_index]


def tile_work(index: int, tile: Tile, secret: np.ndarray, part_pixels: int) -> TileWork:
    """Tile `index`'s pixels and its parts: bands of whole rows, at most `part_pixels` rays each where a row fits
    (tiling.part_rows)."""
    x0, y0, w, h = tile.rect
    rows = part_rows(w, h, part_pixels)
    return TileWork(index, tile, torch.tensor(secret[y0:y0 + h, x0:x0 + w].reshape(-1, 3)),
                    [range(y * w, min(y + rows, h) * w) for y in range(0, h, rows)], time.perf_counter())
