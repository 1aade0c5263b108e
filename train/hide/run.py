"""`noisenerf hide`: train the noise that makes a frozen scene render a secret (Noise-NeRF).

The secret is planned into tiles (plan.py), one viewpoint each; each tile's secret view (secret_view.py)
goes to the chosen method (methods.py), which solves it in resumable parts saved beside the output
(OUT.partial/, progress.py), so an interrupted hide run again with the same arguments resumes where it
stopped and writes a byte-identical bundle.
"""

from __future__ import annotations

import dataclasses
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

import noisenerf
from noisenerf.runtime.bundle import Bundle, secret_digest
from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.errors import InexactResult, UserError
from noisenerf.runtime.files import check_output_path
from noisenerf.runtime.limits import MAX_RAY_LAYOUT_SAMPLES, checked_image_size
from noisenerf.runtime.metrics import tile_quality
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.plan import HideConfig, plan, run_key
from noisenerf.train.hide.progress import Progress
from noisenerf.train.hide.secret_view import SecretView, pass_samples_for
from noisenerf.train.hide.solver import ChunkPool
from noisenerf.train.scene.scene import Scene


PAYLOAD_IS_EXACT = "a payload is revealed whole or not at all: --allow-inexact is for images"


def hide(scene: Scene, secret: np.ndarray, output: Path, config: HideConfig, device: torch.device,
         force: bool = False, show_progress: bool = True, payload: dict | None = None,
         workers: int | None = None, allow_inexact: bool = False) -> dict:
    """Hide `secret` (H, W, 3) uint8 in the scene; write the bundle to `output`; return the report.
    payload: the bundle's payload object when the secret carries one (train.payload), else None.
    A method that promises exactness (Solver.exact) and leaves a tile's pixels off raises InexactResult at
    that tile, writing no bundle and keeping the solved chunks for a resume, unless allow_inexact (never for
    a payload, which is revealed whole or not at all).
    workers: processes a CPU solve may spread its chunks over (None: every core this process may use);
    the bundle's bytes never depend on it. They are spawned, so a script that calls hide on a secret of
    several chunks guards its top level with `if __name__ == "__main__":`, as multiprocessing requires."""
    output = check_output_path(output, force=force)
    checked_image_size(secret.shape[1], secret.shape[0], "the secret image")  # what a bundle may hold
    if config.layout == "ray" and config.n_samples > MAX_RAY_LAYOUT_SAMPLES:
        raise UserError(f"the ray layout serves at most {MAX_RAY_LAYOUT_SAMPLES} samples per ray, "
                        f"not {config.n_samples}")
    hide_plan = plan(scene, secret, config)
    scene.to(device)
    field = scene.render_field
    solver = METHODS[config.method]
    if allow_inexact and payload is not None:
        raise UserError(PAYLOAD_IS_EXACT)
    workers = (available_cores() if workers is None else workers) if device.type == "cpu" else 1
    with Progress(output, run_key(scene, secret, config)) as progress, ChunkPool(workers) as pool:
        tiles, reports = [], []
        started = time.perf_counter()
        bar = tqdm(total=secret.shape[0] * secret.shape[1], unit="px", desc=f"hide ({config.method})",
                   disable=not show_progress, dynamic_ncols=True)
        for k, tile in enumerate(hide_plan.tiles):
            tile_start = time.perf_counter()
            x0, y0, w, h = tile.rect
            secret_view = SecretView(scene.fields()[tile.network], tile, scene.config.render, device)
            pixels = torch.tensor(secret[y0:y0 + h, x0:x0 + w].reshape(-1, 3), device=device)
            with solver.threads(device):  # the check below is a few large passes, for every core
                solved = solver.solve_tile(secret_view, pixels, (h, w), config, progress, k, bar, pool)
            colors = secret_view.render_all(solved.noise, pass_samples_for(device))
            quality = tile_quality(colors.cpu().numpy(), pixels.cpu().numpy(), (h, w))
            if solver.exact and quality["inexact_pixels"] and not allow_inexact:
                raise InexactResult(
                    f"tile {k} (view {tile.view}, {w}x{h} px at x={x0}, y={y0}) has {quality['inexact_pixels']} "
                    f"pixels off, by up to {quality['max_error']} levels; no bundle written (solved parts kept in "
                    f"{progress.directory} for a resume; --allow-inexact writes the bundle anyway)")
            tiles.append(dataclasses.replace(tile, noise=solved.stored))
            reports.append({"rect": list(tile.rect), "view": tile.view, **quality,
                            **solved.report, "seconds": round(time.perf_counter() - tile_start, 2)})
        bar.close()
        bundle = Bundle(model_fingerprint=scene.fingerprint(), width=secret.shape[1], height=secret.shape[0],
                        secret_sha256=secret_digest(secret), layout=config.layout,
                        noise_dims=field.config.noise_dims, dtype=config.dtype, tiles=tuple(tiles),
                        extra={"method": config.method, "noisenerf": noisenerf.__version__,
                               "config": config.to_dict()}, payload=payload,
                        coefficients=tiles[0].noise.stored.shape[-1] if config.layout == "compact" else None)
        bundle.save(output)
        progress.clear()
    n_pixels = secret.shape[0] * secret.shape[1]
    exact_pixels = sum(r["exact_fraction"] * r["rect"][2] * r["rect"][3] for r in reports)
    return {
        "bundle": str(output), "method": config.method, "layout": config.layout, "dtype": config.dtype,
        "width": secret.shape[1], "height": secret.shape[0], "tiles": reports,
        "exact_fraction": exact_pixels / n_pixels, "exact": all(r["exact_fraction"] == 1.0 for r in reports),
        "bundle_bytes": output.stat().st_size, "bytes_per_pixel": output.stat().st_size / n_pixels,
        "seconds": round(time.perf_counter() - started, 2),
    }
