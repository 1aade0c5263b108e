"""The `nerfstudio` experiment: a nerfstudio nerfacto run imported, its ordinary renders against nerfstudio's
own eval renders of the same cameras (a goldens folder written by tools/nerfstudio_goldens.py from that run),
then the bench's photos hidden in it at two cameras (revealed through onnxruntime and in the page) and the coverage experiment's hard secrets at every camera,
revealed through onnxruntime.

Rows (nerfstudio.csv): "import" (seconds to import and export), "render" (one golden camera: our render's
difference from nerfstudio's), "hide" (one photo at one view, as the fields experiment's) and "coverage"
(the hard secrets at every camera of the run, as the coverage experiment's).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from noisenerf.runtime.api import render

from noisenerf.cli.bench import coverage
from noisenerf.cli.bench.context import BenchContext, Measured
from noisenerf.cli.bench.fields import imported_hides, median_of

RENDER_GOAL = 1e-3  # our ordinary render's largest difference from nerfstudio's eval render (float32 noise)


def frame_view(data: Path, file_path: str) -> int:
    """The scene camera of a dataset frame: its place in file-name order (nerfstudio's)."""
    frames = sorted(json.loads((data / "transforms.json").read_text())["frames"], key=lambda f: Path(f["file_path"]).name)
    return [Path(frame["file_path"]).name for frame in frames].index(Path(file_path).name)


def measure_nerfstudio(context: BenchContext) -> Measured:
    from safetensors.numpy import load_file

    from noisenerf.export.onnx_export import export_scene
    from noisenerf.runtime.errors import UserError
    from noisenerf.train.scene.import_nerfstudio import import_nerfstudio

    config = context.config
    if not (config.nerfstudio_run and config.nerfstudio_data):
        raise UserError("the nerfstudio experiment imports a run: give --nerfstudio-run and --nerfstudio-data")
    folder = context.work / "nerfstudio"
    folder.mkdir(exist_ok=True)
    start = time.perf_counter()
    import_nerfstudio(Path(config.nerfstudio_run), folder / "scene", Path(config.nerfstudio_data))
    imported = time.perf_counter()
    export_scene(folder / "scene", folder / "model.onnx")
    rows = [{"row": "import", "import_seconds": imported - start, "export_seconds": time.perf_counter() - imported}]
    if config.nerfstudio_golden:
        golden = load_file(Path(config.nerfstudio_golden) / "golden.safetensors")
        info = json.loads((Path(config.nerfstudio_golden) / "golden.json").read_text())
        for split, camera in info["cameras"].items():
            view = frame_view(Path(config.nerfstudio_data), camera["file_path"])
            result = render(folder / "model.onnx", view)
            theirs = golden[f"{split}_render_rgb"]
            difference = np.abs(result.image - theirs)
            rows.append({"row": "render", "split": split, "view": view, "pixels": theirs.shape[0] * theirs.shape[1],
                         "max_difference": float(difference.max()), "mean_difference": float(difference.mean()),
                         "psnr_vs_nerfstudio": float(-10 * np.log10(max(float((difference ** 2).mean()), 1e-30))),
                         "equal_8bit": float((np.floor(result.image * 255 + 0.5) == np.floor(theirs * 255 + 0.5)).mean()),
                         "render_seconds": result.timings["render"]})
    scene_context, hides = imported_hides(context, folder, "nerfacto")
    rows += hides
    cameras = len(scene_context.scene.config.cameras)
    secrets = coverage.hard_secrets(config.coverage_size, scene_context.scene.config.render.background, seed=config.seed)
    mosaic = {"every hard secret": np.concatenate(list(secrets.values()), axis=1)}
    rows += [{"row": "coverage", **row} for row in coverage.sweep(scene_context, mosaic, range(cameras), "nerfacto run")]
    return Measured(rows)


def describe_nerfstudio(context: BenchContext, measured: Measured) -> list[str]:
    config, rows = context.config, measured.rows
    imported = next(row for row in rows if row["row"] == "import")
    lines = [f"Run `{config.nerfstudio_run}` (dataset `{config.nerfstudio_data}`) imported in "
             f"{imported['import_seconds']:.1f} s and exported in {imported['export_seconds']:.1f} s."]
    renders = [row for row in rows if row["row"] == "render"]
    if renders:
        lines += ["", f"Our ordinary render (`noisenerf-reveal MODEL --view I`) against nerfstudio's eval render of the "
                      f"same camera (`{config.nerfstudio_golden}`):", "",
                  "| camera | view | largest difference | mean difference | PSNR vs nerfstudio dB | 8-bit values equal | "
                  "render s |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {row['split']} | {row['view']} | {row['max_difference']:.2e} | {row['mean_difference']:.1e} | "
                  f"{row['psnr_vs_nerfstudio']:.1f} | {100 * row['equal_8bit']:.2f} % | {row['render_seconds']:.2f} |"
                  for row in renders]
        worst = max(row["max_difference"] for row in renders)
        lines += ["", f"Goal: within float32 noise (largest difference < {RENDER_GOAL:g}): {worst:.2e}: "
                      f"**{'met' if worst < RENDER_GOAL else 'not met'}**."]
    hides = [row for row in rows if row["row"] == "hide"]
    ratio = np.median([row["bundle_bytes"] / row["png_bytes"] for row in hides])
    lines += ["", f"Photos ({config.nerfstudio_width} px wide) hidden with the defaults at two of the run's cameras "
                  "(a third and two thirds round), medians:", "",
              "| bytes/px | bundle ÷ PNG | escaped | hide s | reveal s (onnxruntime) | reveal s (browser) | "
              "exact (onnxruntime, browser) |", "|---|---|---|---|---|---|---|",
              f"| {median_of(rows, 'nerfacto', 'bytes_per_pixel'):.2f} | {ratio:.2f} | "
              f"{median_of(rows, 'nerfacto', 'escaped'):.0f} | {median_of(rows, 'nerfacto', 'hide_seconds'):.2f} | "
              f"{median_of(rows, 'nerfacto', 'reveal_seconds'):.3f} | {median_of(rows, 'nerfacto', 'browser_seconds'):.3f} | "
              f"{sum(row['exact'] for row in hides)}, {sum(row['browser_exact'] is True for row in hides)} / {len(hides)} |"]
    covered = [row for row in rows if row["row"] == "coverage"]
    exact, pixels = sum(row["exact_pixels"] for row in covered), sum(row["pixels"] for row in covered)
    lines += ["", f"Every hard secret ({config.coverage_size}² each, side by side) at every one of the run's "
                  f"{len(covered)} cameras: {exact:,} of {pixels:,} pixels exact: "
                  f"**{'met' if exact == pixels else 'not met'}**."]
    return lines
