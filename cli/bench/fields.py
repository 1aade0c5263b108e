"""The `fields` experiment: each field kind fitted on the same data, at the same resolution, for the same
minutes, on this machine; then the bench's photos hidden in each at views the other experiments do not use,
revealed through onnxruntime and in the browser; each kind's field evaluations per second; and the coverage
sweep (hard secrets at every camera) on the hash-grid fit.

Rows (fields.csv) are of three sorts, told apart by `row`: "curve" (a fit's test PSNR on a seeded subset of
its held-out pixels against training seconds), "hide" (one photo at one view) and "rate" (evaluations per
second); the coverage sweep's rows follow, as coverage.csv's are.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from noisenerf.runtime.api import reveal
from noisenerf.runtime.images import load_secret, write_image
from noisenerf.runtime.model import load_model
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.scene.fit import PRESETS, Budget, fit, fitting_frame, held_out_quality, held_out_views, pooled_quality
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.scene import load_scene

from noisenerf.cli.bench import browser, coverage
from noisenerf.cli.bench.context import BenchContext, Measured, small_secret, timed
from noisenerf.cli.bench.report import curves_plot, verdict

PSNR_GOAL_DB = 30.0  # the hash-grid preset's test PSNR on lego at 200 px within 15 minutes
PSNR_MARGIN_GOAL_DB = 2.0  # and how far above the mlp small preset's, same data, resolution and minutes
NERFACTO_MARGIN_GOAL_DB = {"llff": 0.0, "capture": 4.0}  # nerfacto's test PSNR above the hash grid's, by dataset kind
CAPTURE_PSNR_GOAL_DB = 22.0  # and nerfacto's own on a 360° phone capture at a quarter of its resolution
TEST_RENDER_SHARE_GOAL = 0.10  # a fit's closing test renders ÷ its training time
REVEAL_RATIO_GOAL = 1 / 3  # hash-grid reveal time per pixel ÷ the mlp small preset's
RATE_SAMPLES = 1 << 16  # samples per field-rate batch


@dataclass(frozen=True, kw_only=True)
class FieldsMeasured(Measured):
    fits: dict  # preset -> its fit's report (steps, seconds, eval_seconds, the fit's own test), test over every view
    kind: str  # the dataset's (datasets.Dataset.kind)


def rate_rows(preset: str, scene, model) -> list[dict]:
    """Field evaluations per second of the scene's render field, through onnxruntime (the reveal's) and torch
    (the hide's), on RATE_SAMPLES random points in its box with random noise; best of three."""
    rng = np.random.default_rng(0)
    lo, hi = np.asarray(scene.config.aabb[:3], np.float32), np.asarray(scene.config.aabb[3:], np.float32)
    points = (lo + rng.random((RATE_SAMPLES, 3), dtype=np.float32) * (hi - lo)).astype(np.float32)
    viewdirs = rng.normal(size=(RATE_SAMPLES, 3)).astype(np.float32)
    viewdirs /= np.linalg.norm(viewdirs, axis=1, keepdims=True)
    noise = rng.normal(size=(RATE_SAMPLES, model.noise_dims)).astype(np.float32)
    rows = []
    for backend, field in (("onnxruntime", model.field), ("torch", numpy_field(scene.render_field))):
        seconds = min(timed(field, points, viewdirs, noise)[1] for _ in range(3))
        rows.append({"row": "rate", "preset": preset, "backend": backend, "samples_per_second": RATE_SAMPLES / seconds})
    return rows


def png_bytes(pixels: np.ndarray, folder: Path) -> int:
    """The photo's size as the project's image writer saves it (PNG, default compression)."""
    path = folder / "photo.png"
    write_image(path, pixels)
    return path.stat().st_size


def hide_rows(context: BenchContext, preset: str, views: tuple[int, ...]) -> tuple[list[dict], dict[str, Path]]:
    """The photos (view_width wide) hidden at `views` with the defaults, revealed through onnxruntime and through
    the recipient's Python API from the files; the bundles kept for the browser, by row name."""
    rows, bundles = [], {}
    for path in context.config.photos[:context.config.view_photos] or (context.config.secret,):
        photo = small_secret(load_secret(path)[0], context.config.view_width or 128)
        for view in views:
            name = f"{preset}_{Path(path).stem}_{view}"
            report, revealed, reveal_seconds = context.hide_and_reveal(photo, name, HideConfig(view=view))
            size = (context.work / f"{name}.bundle").stat().st_size
            by_api = reveal(context.model_path, context.work / f"{name}.bundle")
            rows.append({"row": "hide", "preset": preset, "photo": Path(path).name, "view": view,
                         "pixels": photo.shape[0] * photo.shape[1], "bundle_bytes": size,
                         "bytes_per_pixel": size / (photo.shape[0] * photo.shape[1]),
                         "png_bytes": png_bytes(photo, context.work), "exact": bool((revealed.pixels == photo).all()),
                         "api_exact": bool(by_api.exact and (by_api.pixels == photo).all()),
                         "escaped": sum(t.get("escaped", 0) for t in report["tiles"]),
                         "hide_seconds": report["seconds"], "reveal_seconds": reveal_seconds, "name": name})
            bundles[name] = context.work / f"{name}.bundle"
    return rows, bundles


def imported_hides(context: BenchContext, folder: Path, preset: str) -> tuple[BenchContext, list[dict]]:
    """An imported scene (folder/scene, folder/model.onnx) as the bench's context, its photos (nerfstudio_width
    wide) hidden at a third and two thirds round its cameras and revealed through onnxruntime and the page.
    -> that context, the hide rows."""
    from noisenerf.runtime.model import load_model
    from noisenerf.train.scene.scene import load_scene

    scene_context = dataclasses.replace(context, scene=load_scene(folder / "scene"), model_path=folder / "model.onnx",
                                        model=load_model(folder / "model.onnx"),
                                        config=dataclasses.replace(context.config, view_width=context.config.nerfstudio_width))
    cameras = len(scene_context.scene.config.cameras)
    hides, bundles = hide_rows(scene_context, preset, (cameras // 3, 2 * cameras // 3))
    in_browser = browser_results(scene_context, bundles)
    return scene_context, [{**row, "browser_seconds": None, "browser_exact": None, **in_browser.get(row["name"], {})}
                           for row in hides]


def browser_results(context: BenchContext, bundles: dict[str, Path]) -> dict[str, dict]:
    """Each bundle revealed in the single-file page at its default workers: by bundle name, its seconds and
    whether the page found it exact (the revealed pixels' digest is the bundle's); empty where the browser or
    the web build is missing."""
    if browser.browser_missing() is not None:
        return {}
    dist = context.work / "fields_pages"
    shutil.rmtree(dist, ignore_errors=True)
    shutil.copytree(browser.WEB_DIST, dist)
    rows = browser.browser_reveals(dist, bundles, context.model_path, repeats=1)
    return {row["secret"]: {"browser_seconds": row["seconds"], "browser_exact": row["exact"]}
            for row in rows if row["page"] == "single file" and row["default"]}


def every_held_out_view(fit_test: dict, folder: Path, dataset, fit_config) -> dict:
    """The quality over every held-out view: the fit's own closing renders (bounded in time) and the views they
    left, rendered here the same way."""
    rendered = {score["view"] for score in fit_test["per_view"]}
    left = [view for view in held_out_views(dataset) if view not in rendered]
    if not left:
        return fit_test
    return pooled_quality([fit_test, held_out_quality(load_scene(folder), fitting_frame(dataset, fit_config), left)])


def measure_fields(context: BenchContext) -> FieldsMeasured:
    config = context.config
    from noisenerf.export.onnx_export import export_scene
    from noisenerf.runtime.errors import UserError
    from noisenerf.train.scene.datasets import load_dataset

    if config.data is None:
        raise UserError("the fields experiment fits each field kind: give the dataset with --data")
    dataset = load_dataset(config.data, resolution=config.fields_resolution)
    rows, fits, hashgrid_context = [], {}, None
    for preset in config.fields_presets:
        folder = context.work / f"fields_{preset}"
        fit_config = dataclasses.replace(PRESETS[preset], seed=config.seed)
        report = fit(dataset, folder, fit_config, Budget(minutes=config.fields_minutes), torch.device("cpu"),
                     curve_seconds=config.fields_curve_seconds)
        fits[preset] = {**{key: report[key] for key in ("steps", "seconds", "eval_seconds", "samples_evaluated")},
                        "fit_test": report["test"], "test": every_held_out_view(report["test"], folder, dataset, fit_config)}
        rows += [{"row": "curve", "preset": preset, "seconds": point["seconds"], "psnr": point["psnr"]}
                 for point in report["curve"]]
        export_scene(folder, folder / "model.onnx")
        scene_context = dataclasses.replace(context, scene=load_scene(folder), model_path=folder / "model.onnx",
                                            model=load_model(folder / "model.onnx"))
        cameras = len(scene_context.scene.config.cameras)
        hides, bundles = hide_rows(scene_context, preset, (cameras // 3, 2 * cameras // 3))
        in_browser = browser_results(scene_context, bundles)
        rows += [{**row, "browser_seconds": None, "browser_exact": None, **in_browser.get(row["name"], {})}
                 for row in hides]
        rows += rate_rows(preset, scene_context.scene, scene_context.model)
        if preset == "hashgrid":
            hashgrid_context = scene_context
    if hashgrid_context is not None:
        secrets = coverage.hard_secrets(config.coverage_size, hashgrid_context.scene.config.render.background,
                                        seed=config.seed)
        mosaic = {"every hard secret": np.concatenate(list(secrets.values()), axis=1)}
        rows += [{"row": "coverage", **row} for row in coverage.sweep(
            hashgrid_context, mosaic, range(len(hashgrid_context.scene.config.cameras)), "hashgrid fit")]
    return FieldsMeasured(rows, fits=fits, kind=dataset.kind)


def median_of(rows: list[dict], preset: str, key: str) -> float:
    return float(np.median([row[key] for row in rows if row["row"] == "hide" and row["preset"] == preset
                            and row[key] is not None] or [np.nan]))


def describe_fields(context: BenchContext, measured: FieldsMeasured) -> list[str]:
    config, rows, fits = context.config, measured.rows, measured.fits
    lines = [f"Presets fitted on `{config.data}` at {config.fields_resolution} px for {config.fields_minutes:g} "
             "minutes each on this machine (CPU), one after the other; test PSNR over every held-out view (every 8th "
             "of a capture or LLFF scene), and the fit's closing test renders: their seconds and how many held-out "
             "views they rendered (at most a tenth of the training time; the bench renders the rest).", "",
             "| preset | kind | steps | test PSNR dB | SSIM | test renders s | views | ÷ training time |",
             "|---|---|---|---|---|---|---|---|"]
    for preset, report in fits.items():
        lines.append(f"| {preset} | {PRESETS[preset].field.kind} | {report['steps']:,} | {report['test']['psnr']:.2f} | "
                     f"{report['test']['ssim']:.4f} | {report['eval_seconds']:.1f} | "
                     f"{report['fit_test']['views']} of {report['test']['views']} | "
                     f"{report['eval_seconds'] / report['seconds']:.3f} |")
    lines.append("")
    psnr = {preset: report["test"]["psnr"] for preset, report in fits.items()}
    if "hashgrid" in psnr and "small" in psnr:
        grid, small = psnr["hashgrid"], psnr["small"]
        lines.append(f"Goal (lego): the hash grid ≥ {PSNR_GOAL_DB:g} dB and ≥ {PSNR_MARGIN_GOAL_DB:g} dB above the small "
                     f"preset: {grid:.2f} dB, {grid - small:+.2f} dB: "
                     f"**{verdict(grid, PSNR_GOAL_DB, False, grid - small >= PSNR_MARGIN_GOAL_DB)}**.")
    if "hashgrid" in psnr and "nerfacto" in psnr and measured.kind in NERFACTO_MARGIN_GOAL_DB:
        margin, goal = psnr["nerfacto"] - psnr["hashgrid"], NERFACTO_MARGIN_GOAL_DB[measured.kind]
        floor = CAPTURE_PSNR_GOAL_DB if measured.kind == "capture" else None
        lines.append(f"Goal ({measured.kind}): nerfacto ≥ the hash grid + {goal:g} dB"
                     + (f" and ≥ {floor:g} dB: {psnr['nerfacto']:.2f} dB, " if floor else ": ") + f"{margin:+.2f} dB: "
                     f"**{verdict(margin, goal, False, floor is None or psnr['nerfacto'] >= floor)}**.")
    if "nerfacto" in fits:
        nerfacto = fits["nerfacto"]
        share, rendered = nerfacto["eval_seconds"] / nerfacto["seconds"], nerfacto["fit_test"]["views"]
        every = nerfacto["eval_seconds"] / rendered * nerfacto["test"]["views"] / nerfacto["seconds"]
        lines.append(f"Goal: nerfacto's closing test renders ≤ {TEST_RENDER_SHARE_GOAL:.0%} of its training time: "
                     f"{share:.1%} ({rendered} of {nerfacto['test']['views']} held-out views, "
                     f"{nerfacto['eval_seconds'] / rendered:.1f} s a view; every view would take {every:.1%}): "
                     f"**{verdict(share, TEST_RENDER_SHARE_GOAL, True)}**.")
    lines += ["", "Photos hidden with the defaults at two views the other experiments do not use (a third and two thirds "
                  "round the cameras), medians:", "",
              "| preset | bytes/px | bundle ÷ PNG | escaped | hide s | reveal s (onnxruntime) | reveal s (browser) | "
              "exact (onnxruntime, browser) |", "|---|---|---|---|---|---|---|---|"]
    for preset in fits:
        hides = [row for row in rows if row["row"] == "hide" and row["preset"] == preset]
        ratio = np.median([row["bundle_bytes"] / row["png_bytes"] for row in hides])
        lines.append(f"| {preset} | {median_of(rows, preset, 'bytes_per_pixel'):.2f} | {ratio:.2f} | "
                     f"{median_of(rows, preset, 'escaped'):.0f} | {median_of(rows, preset, 'hide_seconds'):.2f} | "
                     f"{median_of(rows, preset, 'reveal_seconds'):.3f} | {median_of(rows, preset, 'browser_seconds'):.3f} | "
                     f"{sum(row['exact'] for row in hides)}, {sum(row['browser_exact'] is True for row in hides)} "
                     f"/ {len(hides)} |")
    rates = {(row["preset"], row["backend"]): row["samples_per_second"] for row in rows if row["row"] == "rate"}
    lines += ["", "Field evaluations per second (65,536 random samples with noise): " + ", ".join(
        f"{preset} {backend} {rate / 1e3:,.0f} k" for (preset, backend), rate in rates.items()) + "."]
    if "hashgrid" in fits and "small" in fits:
        reveal_ratio = median_of(rows, "hashgrid", "reveal_seconds") / median_of(rows, "small", "reveal_seconds")
        bytes_ratio = median_of(rows, "hashgrid", "bytes_per_pixel") / median_of(rows, "small", "bytes_per_pixel")
        lines += ["", f"Goal: hash-grid reveal time per pixel ≤ {REVEAL_RATIO_GOAL:.2f}× the small preset's: "
                      f"{reveal_ratio:.2f}×: **{verdict(reveal_ratio, REVEAL_RATIO_GOAL, True)}**.",
                  f"Goal: hash-grid keys no larger than the small preset's (median bytes/px): {bytes_ratio:.2f}×: "
                  f"**{verdict(bytes_ratio, 1.0, True)}**."]
    covered = [row for row in rows if row["row"] == "coverage"]
    if covered:
        exact, pixels = sum(row["exact_pixels"] for row in covered), sum(row["pixels"] for row in covered)
        lines.append(f"Goal: every hard secret ({config.coverage_size}² each, side by side) exact at every one of the "
                     f"hash-grid fit's {len(covered)} cameras: {exact:,} of {pixels:,} pixels: "
                     f"**{verdict(exact, pixels, False)}**.")
    hides = [row for row in rows if row["row"] == "hide"]
    everywhere = sum(row["exact"] and row["api_exact"] and row["browser_exact"] is True for row in hides)
    lines.append(f"Goal: every photo exact through onnxruntime, the Python API and the page: "
                 f"{sum(row['exact'] for row in hides)}, {sum(row['api_exact'] for row in hides)}, "
                 f"{sum(row['browser_exact'] is True for row in hides)} of {len(hides)}: "
                 f"**{verdict(everywhere, len(hides), False)}**.")
    return lines


def plot_fields(rows: list[dict], path: Path) -> None:
    curves_plot([row for row in rows if row["row"] == "curve"], path, "preset", "seconds", "psnr",
                ("training seconds", "test PSNR (dB, held-out pixel subset)"), marker="o")
