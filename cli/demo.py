"""`noisenerf demo`: the whole product on the embedded default, in well under two minutes on 2 cores.

The shipped demo scene (train/assets/demo_scene, fitted by `noisenerf fit` on the procedural dataset,
see docs/usage.md) hides a generated secret; the scene is exported to ONNX; onnxruntime reveals the secret
with the runtime alone. Writes the scene's ordinary render, the secret, the revealed image and a
side-by-side picture of the three; and a short text file hidden as a payload sealed under the passphrase
DEMO_PASSPHRASE (note.txt -> note.bundle), for `noisenerf-reveal` to open.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import torch

from noisenerf.runtime.files import atomic_folder, write_bytes
from noisenerf.runtime.images import write_image
from noisenerf.runtime.metrics import exact_fraction, psnr, ssim
from noisenerf.runtime.progress import ProgressFn
from noisenerf.train.scene.procedural import DEMO_SCENE, procedural_secret

DEMO_VIEW = 2
SECRET_SIZE = (96, 72)  # width, height: two tiles of 64 px wide, so stitching is shown too
TILE_SIZE = 64
DEMO_PASSPHRASE = "noisenerf demo"  # a demo's passphrase is public: choose your own
NOTE = "Meet at the old lighthouse at dawn.\n"


def side_by_side(images: list[np.ndarray], gap: int = 4) -> np.ndarray:
    """Images (H_i, W_i, 3) uint8 next to each other on white, top-aligned. -> (max H, ΣW + gaps, 3)."""
    height = max(image.shape[0] for image in images)
    width = sum(image.shape[1] for image in images) + gap * (len(images) - 1)
    canvas = np.full((height, width, 3), 255, dtype=np.uint8)
    x = 0
    for image in images:
        canvas[:image.shape[0], x:x + image.shape[1]] = image
        x += image.shape[1] + gap
    return canvas


def run_demo(out_dir: Path, device: torch.device, progress: ProgressFn | None = None) -> dict:
    """The demo's files written into the folder `out_dir` as a whole: a new or empty folder, or an earlier demo's,
    which they replace (any other folder is refused). -> the demo's report."""
    with atomic_folder(out_dir, replace=True, marker="note.bundle", what="demo") as folder:
        report = demo_files(folder, device, progress)
    report["output"] = str(out_dir)
    report["summary"] += [
        f"files in {out_dir}: model.onnx (share with anyone), secret.bundle ({report['bundle_bytes']} bytes, the key), "
        "secret.png, revealed.png, ordinary.png, side_by_side.png, note.txt, note.bundle",
        f"open the sealed note: NOISENERF_PASSPHRASE='{DEMO_PASSPHRASE}' noisenerf-reveal {out_dir / 'model.onnx'} "
        f"{out_dir / 'note.bundle'} -o note.txt",
    ]
    return report


def demo_files(out_dir: Path, device: torch.device, progress: ProgressFn | None) -> dict:
    """The demo's files written into `out_dir` (a new folder) through the public library, as a user's script
    would write them, and its report."""
    from noisenerf import api
    from noisenerf.runtime.api import render, reveal

    timings = {}
    started = time.perf_counter()
    secret = procedural_secret(*SECRET_SIZE)
    write_image(out_dir / "secret.png", secret)
    where = {"tile_size": TILE_SIZE, "view": DEMO_VIEW, "device": str(device), "progress": progress}
    hidden = api.hide(DEMO_SCENE, out_dir / "secret.png", out_dir / "secret.bundle", **where)
    timings["hide"] = time.perf_counter() - started

    started = time.perf_counter()
    write_bytes(out_dir / "note.txt", NOTE.encode(), replace=False)
    api.hide(DEMO_SCENE, output=out_dir / "note.bundle", file=out_dir / "note.txt", passphrase=DEMO_PASSPHRASE,
             **where)
    timings["seal"] = time.perf_counter() - started

    started = time.perf_counter()
    api.export_model(DEMO_SCENE, out_dir / "model.onnx")
    timings["export"] = time.perf_counter() - started

    started = time.perf_counter()
    revealed = reveal(out_dir / "model.onnx", out_dir / "secret.bundle")
    revealed.save(out_dir / "revealed.png")
    timings["reveal"] = time.perf_counter() - started

    ordinary = render(out_dir / "model.onnx", DEMO_VIEW).pixels
    write_image(out_dir / "ordinary.png", ordinary)
    write_image(out_dir / "side_by_side.png", side_by_side([ordinary, secret, revealed.pixels]))
    quality = {"psnr": psnr(revealed.pixels / 255.0, secret / 255.0),
               "ssim": ssim(revealed.pixels / 255.0, secret / 255.0),
               "exact_fraction": exact_fraction(revealed.pixels, secret)}
    report = {"exact": revealed.exact, **quality, "bundle_bytes": hidden["bundle_bytes"],
              "seconds": {k: round(v, 2) for k, v in timings.items()}}
    psnr_text = "inf" if quality["psnr"] == float("inf") else f"{quality['psnr']:.2f}"
    report["summary"] = [
        f"exact: {str(revealed.exact).lower()}",
        f"PSNR {psnr_text} dB, SSIM {quality['ssim']:.4f}, exact 8-bit values {quality['exact_fraction']:.4%}",
        f"hide {timings['hide']:.1f} s, sealed note {timings['seal']:.1f} s, export {timings['export']:.1f} s, "
        f"reveal (onnxruntime) {timings['reveal']:.1f} s",
    ]
    return report
