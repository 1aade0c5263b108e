"""Key sizes against the secrets' own coding, for comparing two versions of the hide: every photo given,
resized to WIDTH, hidden in SCENE at each of VIEWS with the defaults and revealed with onnxruntime; per hide
the bundle's bytes per pixel and ÷ the photo's PNG (the project's writer), escapes, hide and reveal seconds,
exactness; JSON lines on stdout, the summary last. It uses only what noisenerf has had since its Python API,
so it runs from a checkout of each version compared (CHANGELOG.md's key formats; the bench's `keys`
experiment adds lossless WebP):

    python tools/key_sizes.py SCENE 15,40 128 PHOTO... > sizes.jsonl
"""

from __future__ import annotations

import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import noisenerf
from noisenerf.cli.bench.context import small_secret
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret, write_image
from noisenerf.runtime.model import load_model


def main(scene: str, views: list[int], width: int, photos: list[str]) -> None:
    folder = Path(tempfile.mkdtemp())
    model = folder / "model.onnx"
    noisenerf.export_model(scene, model)
    masked = getattr(load_model(model), "mask_secret", None)  # format 5's bundles read with it; older versions' without
    rows = []
    for path in photos:
        photo = small_secret(load_secret(path)[0], width)
        pixels = photo.shape[0] * photo.shape[1]
        write_image(folder / "photo.png", photo)
        png = (folder / "photo.png").stat().st_size
        for view in views:
            start = time.perf_counter()
            noisenerf.hide(scene, photo, folder / "key.bundle", view=view, force=True)
            hide_seconds = time.perf_counter() - start
            start = time.perf_counter()
            revealed = noisenerf.reveal(model, folder / "key.bundle")
            reveal_seconds = time.perf_counter() - start
            size = (folder / "key.bundle").stat().st_size
            bases = [tile.noise.basis for tile in load_bundle(folder / "key.bundle", *([masked] if masked else [])).tiles]
            rows.append({"photo": Path(path).name, "view": view, "bytes_per_pixel": size / pixels,
                         "over_png": size / png,
                         "escapes": sum(len(basis.escapes) for basis in bases),
                         "branch_escapes": sum(len(getattr(basis, "branch_escapes", ())) for basis in bases),
                         "hide_seconds": hide_seconds, "reveal_seconds": reveal_seconds,
                         "exact": bool(revealed.exact and np.array_equal(revealed.pixels, photo))})
            print(json.dumps(rows[-1]), flush=True)
    over_png = [row["over_png"] for row in rows]
    print(json.dumps({"median_over_png": float(np.median(over_png)), "worst_over_png": max(over_png),
                      "hide_seconds": sum(row["hide_seconds"] for row in rows),
                      "reveal_seconds": sum(row["reveal_seconds"] for row in rows),
                      "all_exact": all(row["exact"] for row in rows)}))


if __name__ == "__main__":  # the hide's worker processes import this module again
    main(sys.argv[1], [int(view) for view in sys.argv[2].split(",")], int(sys.argv[3]), sys.argv[4:])
