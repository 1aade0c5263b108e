"""Exactness on CUDA, for a machine with a GPU (issue 49's device check; CI never runs it): photos hidden at two
views of the demo scene (MLP) and of a random hash grid, on the CPU and on CUDA, each bundle revealed by onnxruntime's
CPU provider, by its CUDA provider (where onnxruntime-gpu is installed) with TF32 off (the runtime's) and on, and by
the torch field on CUDA with TF32 off and on; per reveal whether it is exact, its smallest rounding margin in levels
and its largest difference from the CPU provider's render. JSON lines on stdout:

    python tools/cuda_exactness.py WIDTH PHOTO...

onnxruntime-gpu's wheel (255 MB) is larger than one device call carries; its files, xz-compressed and split in parts
of 58 MiB, travel in four calls and are joined there (docs/methods.md#the-rounding-margin has the figures).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np
import onnxruntime as ort
import torch

import noisenerf
from noisenerf.cli.bench.context import small_secret
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime import session as session_module
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret
from noisenerf.runtime.metrics import rounding_margins
from noisenerf.runtime.model import load_model
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.procedural import DEMO_SCENE
from noisenerf.train.scene.random_scene import random_scene
from noisenerf.train.scene.render import numpy_fields
from noisenerf.train.scene.scene import load_scene


def torch_tf32(on: bool) -> None:
    torch.backends.cuda.matmul.allow_tf32 = on
    torch.set_float32_matmul_precision("high" if on else "highest")


def provider_model(path: Path, tf32: bool):
    """The model on onnxruntime's CUDA provider, TF32 as asked (the runtime's option is off)."""
    session_module.PROVIDER_OPTIONS["CUDAExecutionProvider"] = {"use_tf32": "1" if tf32 else "0"}
    try:
        return load_model(path, device="cuda")
    finally:
        session_module.PROVIDER_OPTIONS["CUDAExecutionProvider"] = {"use_tf32": "0"}


def main(width: int, photos: list[str]) -> None:
    if hasattr(ort, "preload_dlls"):
        ort.preload_dlls()
    provider = "CUDAExecutionProvider" in ort.get_available_providers()
    print(json.dumps({"gpu": torch.cuda.get_device_name(0), "torch": torch.__version__, "onnxruntime": ort.__version__,
                      "cuda_provider": provider}), flush=True)
    work = Path(sys.argv[0]).resolve().parent.parent / ".cuda_exactness"
    for kind, scene, views in (("mlp", load_scene(DEMO_SCENE), (2, 30)),
                               ("hashgrid", random_scene(seed=2, kind="hashgrid"), (1, 4))):
        folder = work / kind
        folder.mkdir(parents=True, exist_ok=True)
        if not (folder / "model.onnx").exists():
            scene.save(folder / "scene")
            export_scene(folder / "scene", folder / "model.onnx")
        cpu = load_model(folder / "model.onnx")
        others = {f"provider_tf32_{tf32}": provider_model(folder / "model.onnx", tf32) for tf32 in (False, True)} \
            if provider else {}
        for photo in photos:
            secret = small_secret(load_secret(photo)[0], width)
            for view in views:
                for device in ("cpu", "cuda"):
                    path = folder / f"{Path(photo).stem}_{view}_{device}.bundle"
                    started = time.perf_counter()
                    report = hide(scene.to(device), secret, path, HideConfig(view=view), torch.device(device), force=True)
                    row = {"kind": kind, "photo": Path(photo).name, "view": view, "hide_device": device,
                           "hide_seconds": round(time.perf_counter() - started, 2), "hide_margin": report["margin_levels"]}
                    scene.to("cpu")
                    bundle = load_bundle(path, cpu.mask_secret)
                    base = reveal_tiles(bundle, cpu.render_config, cpu.fields(), keep_float=True)
                    revealers = {"cpu_provider": cpu.fields(), **{name: model.fields() for name, model in others.items()}}
                    for name, fields in revealers.items():
                        got = reveal_tiles(bundle, cpu.render_config, fields, keep_float=True)
                        row[name] = {"exact": bool(np.array_equal(got.pixels, secret)),
                                     "margin": float(rounding_margins(got.image, secret).min()),
                                     "levels_from_cpu": float(np.abs(got.image - base.image).max() * 255)}
                    for tf32 in (False, True):
                        torch_tf32(tf32)
                        got = reveal_tiles(bundle, cpu.render_config, numpy_fields(scene.to("cuda").fields()),
                                           keep_float=True)
                        scene.to("cpu")
                        row[f"torch_cuda_tf32_{tf32}"] = {"exact": bool(np.array_equal(got.pixels, secret)),
                                                          "levels_from_cpu": float(np.abs(got.image - base.image).max() * 255)}
                    torch_tf32(False)
                    if provider:
                        row["api_cuda_exact"] = noisenerf.reveal(folder / "model.onnx", path, device="cuda").exact
                    print(json.dumps(row), flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]), sys.argv[2:])
