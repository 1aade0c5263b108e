"""`noisenerf bench`: measurements behind the numbers in the README and the issues' closing notes.

Each experiment measures its comparison side by side in one run (a ratio), on the machine it runs on;
absolute times are labelled with that machine (`machine()`).
"""

from __future__ import annotations

import os
import platform
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret
from noisenerf.runtime.metrics import psnr
from noisenerf.runtime.model import load_model
from noisenerf.runtime.render import render_view
from noisenerf.runtime.reveal import reveal
from noisenerf.train.datasets import load_dataset
from noisenerf.train.hide import HideConfig, hide
from noisenerf.train.renderer import numpy_field
from noisenerf.train.scene import load_scene


def machine() -> dict:
    return {"cpu": platform.processor() or platform.machine(), "cores": os.cpu_count(),
            "torch_threads": torch.get_num_threads(), "python": platform.python_version(),
            "torch": torch.__version__}


def skipping(scene_dir: Path, data_dir: Path, resolution: int | None) -> dict:
    """Ordinary renders of every test view with and without the occupancy grid and early termination."""
    scene = load_scene(scene_dir)
    dataset = load_dataset(data_dir, resolution=resolution)
    field = numpy_field(scene.render_field)
    views = list(dataset.splits.get("test") or dataset.splits["train"])
    result = {}
    for name, grid, early_stop in (("dense", None, 0.0), ("skipping", scene.grid, None)):
        started, evaluated, dense, scores = time.perf_counter(), 0, 0, []
        for index in views:
            image, stats = render_view(dataset.cameras[index], scene.config.render, field, grid, early_stop=early_stop)
            scores.append(psnr(image, dataset.images[index]))
            evaluated += stats.n_samples_evaluated
            dense += stats.n_samples_dense
        result[name] = {"samples_evaluated": evaluated, "samples_dense": dense, "psnr": float(np.mean(scores)),
                        "seconds": round(time.perf_counter() - started, 2)}
    result["evaluation_ratio"] = result["dense"]["samples_evaluated"] / result["skipping"]["samples_evaluated"]
    result["psnr_change_db"] = result["skipping"]["psnr"] - result["dense"]["psnr"]
    result["views"] = len(views)
    return result


def hide_secrets(scene_dir: Path, secrets: list[Path], config: HideConfig, device: torch.device) -> dict:
    """Hide each secret, then reveal it with onnxruntime from the exported model: exactness and times."""
    from noisenerf.export.onnx_export import export_scene

    scene = load_scene(scene_dir)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        model_path = Path(tmp) / "model.onnx"
        export_scene(scene_dir, model_path)
        model = load_model(model_path)
        for path in secrets:
            secret, _ = load_secret(path)
            bundle_path = Path(tmp) / "secret.bundle"
            report = hide(scene, secret, bundle_path, config, device, force=True, show_progress=False)
            started = time.perf_counter()
            revealed = reveal(load_bundle(bundle_path), model.render_config, model.field)
            rows.append({"secret": path.name, "width": secret.shape[1], "height": secret.shape[0],
                         "hide_seconds": report["seconds"], "reveal_seconds": round(time.perf_counter() - started, 2),
                         "torch_exact_fraction": report["exact_fraction"], "onnx_exact": revealed.exact,
                         "bytes_per_pixel": report["bytes_per_pixel"], "bundle_bytes": report["bundle_bytes"],
                         "tiles": report["tiles"]})
    return {"config": config.to_dict(), "secrets": rows,
            "all_exact": all(r["onnx_exact"] and r["torch_exact_fraction"] == 1.0 for r in rows)}


def reveal_throughput(scene_dir: Path, bundle_path: Path, threads: int) -> dict:
    """Reveal one bundle with onnxruntime and with torch eager, same thread count: rays/s of each."""
    from noisenerf.export.onnx_export import export_scene

    torch.set_num_threads(threads)
    scene = load_scene(scene_dir)
    bundle = load_bundle(bundle_path)
    with tempfile.TemporaryDirectory() as tmp:
        export_scene(scene_dir, Path(tmp) / "model.onnx")
        model = load_model(Path(tmp) / "model.onnx", threads=threads)
        timings = {}
        for name, field in (("onnxruntime", model.field), ("torch", numpy_field(scene.render_field))):
            started = time.perf_counter()
            revealed = reveal(bundle, scene.config.render, field)
            timings[name] = {"seconds": time.perf_counter() - started, "exact": revealed.exact}
    rays = bundle.width * bundle.height
    for row in timings.values():
        row["rays_per_second"] = rays / row["seconds"]
    return {"threads": threads, "rays": rays, **timings,
            "onnx_over_torch": timings["onnxruntime"]["rays_per_second"] / timings["torch"]["rays_per_second"]}
