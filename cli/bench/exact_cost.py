"""What the exact method costs on the bench secret: hide against reveal, reveal throughput per backend,
the work that skipping saves, and bundle bytes per pixel."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable

import numpy as np
import torch

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.metrics import psnr
from noisenerf.runtime.networks import render_network
from noisenerf.runtime.render import MarchingSampler, render_view
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.runtime.session import OnnxField, read_model_file
from noisenerf.train.hide.settings import recipe
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.scene.datasets import load_dataset
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.render import numpy_field

from noisenerf.cli.bench.context import BenchContext, Measured, size_of, small_secret, timed
from noisenerf.cli.bench.curves import PaperNoise, exact_curve, secret_quality
from noisenerf.cli.bench.report import verdict

HIDE_OVER_REVEAL_GOAL = 25  # exact hide time ÷ onnxruntime reveal time (the views experiment checks it too)
ONNX_OVER_TORCH_GOAL = 1.0  # onnxruntime ÷ torch eager, reveal rays/s and field samples/s alike
PEAK_FRACTION_GOAL = 0.5  # onnxruntime's field FLOP/s ÷ this machine's float32 matmul peak
SKIPPED_WORK_GOAL = 5  # samples the dense render evaluates ÷ samples evaluated with the grid and early termination
SKIPPED_PSNR_GOAL_DB = 0.1  # how far skipping may move the test views' PSNR either way


def field_flops(field: Field) -> int:
    """Multiply-adds × 2 of one field evaluation (the linear layers; activations are noise)."""
    return linear_flops(field.modules())


def linear_flops(modules: Iterable[torch.nn.Module]) -> int:
    """Multiply-adds × 2 of the linear layers among modules."""
    return 2 * sum(m.in_features * m.out_features for m in modules if isinstance(m, torch.nn.Linear))


@dataclass(frozen=True, kw_only=True)
class Cost(Measured):
    bundle: Path  # the full-size secret's exact hide, which throughput reveals


def measure_cost(context: BenchContext) -> Cost:
    """Exact hide of the full-size secret against its onnxruntime reveal and an ordinary render."""
    model, secret = context.model, context.secret
    report = context.hide(secret, "full", HideConfig(view=context.config.view))
    bundle = load_bundle(context.work / "full.bundle", model.mask_secret)
    revealed, reveal_seconds = timed(reveal_tiles, bundle, model.render_config, model.fields())
    _, render_seconds = timed(render_view, bundle.tiles[0].camera, model.render_config, model.field,
                              MarchingSampler(model.render_config, None, skip=False))
    hide_seconds = report["seconds"]
    return Cost([{"secret": Path(context.config.secret).name, "width": secret.shape[1], "height": secret.shape[0],
                      "hide_seconds": hide_seconds, "reveal_seconds": reveal_seconds,
                      "ordinary_render_seconds": render_seconds, "exact": revealed.exact,
                      "hide_over_reveal": hide_seconds / reveal_seconds,
                      "hide_over_ordinary_render": hide_seconds / render_seconds}], bundle=context.work / "full.bundle")


def describe_cost(context: BenchContext, measured: Measured) -> list[str]:
    row = measured.rows[0]
    return [f"`{row['secret']}` at native size ({row['width']}×{row['height']}), view {context.config.view}: "
            f"exact hide {row['hide_seconds']:.1f} s; onnxruntime reveal of the bundle {row['reveal_seconds']:.2f} s "
            f"(exact: {str(row['exact']).lower()}); a dense ordinary render of the same camera at the scene's "
            f"{context.model.render_config.sampling.n_samples} samples per ray {row['ordinary_render_seconds']:.2f} s.",
            "",
            f"- hide ÷ reveal: **{row['hide_over_reveal']:.1f}** (goal ≤ {HIDE_OVER_REVEAL_GOAL}: "
            f"{verdict(row['hide_over_reveal'], HIDE_OVER_REVEAL_GOAL, lower_is_better=True)}). The reveal renders "
            "one sample per ray, so it is far cheaper than an ordinary render;",
            f"- hide ÷ ordinary render of the same view: **{row['hide_over_ordinary_render']:.1f}**."]


def matmul_peak(threads: int, size: int = 1024, repeats: int = 20) -> float:
    """This machine's float32 GEMM rate at a thread count, GFLOP/s (best of a few runs)."""
    torch.set_num_threads(threads)
    a, b = torch.randn(size, size), torch.randn(size, size)
    best = 0.0
    for _ in range(3):
        _, seconds = timed(lambda: [a @ b for _ in range(repeats)])
        best = max(best, 2 * size ** 3 * repeats / seconds / 1e9)
    return best


def measure_throughput(context: BenchContext) -> Measured:
    """Reveal rays/s and field samples/s, onnxruntime against torch eager at each thread count; the reveal
    is of cost's bundle."""
    config, scene = context.config, context.scene
    bundle = load_bundle(context.needed["cost"].bundle, context.model.mask_secret)
    flops = field_flops(scene.render_field)
    rng = np.random.default_rng(config.seed)
    points = rng.uniform(-1, 1, (65536, 3)).astype(np.float32)
    viewdirs = rng.normal(size=(65536, 3)).astype(np.float32)
    viewdirs /= np.linalg.norm(viewdirs, axis=1, keepdims=True)
    noise = rng.normal(size=(65536, scene.render_field.config.noise_dims)).astype(np.float32)
    rows = []
    for threads in config.threads:
        peak = matmul_peak(threads)
        backends = {"onnxruntime": OnnxField(read_model_file(context.model_path), threads=threads),
                    "torch": numpy_field(scene.render_field)}
        for name, field_fn in backends.items():
            torch.set_num_threads(threads)
            field_fn(points[:1024], viewdirs[:1024], noise[:1024])  # warm-up
            _, field_seconds = timed(field_fn, points, viewdirs, noise)
            revealed, reveal_seconds = timed(reveal_tiles, bundle, scene.config.render,
                                             {render_network(scene.fields()): field_fn})
            samples_per_second = len(points) / field_seconds
            rows.append({"backend": name, "threads": threads, "reveal_rays_per_second": bundle.width * bundle.height
                         / reveal_seconds, "field_samples_per_second": samples_per_second,
                         "gflops": samples_per_second * flops / 1e9, "matmul_peak_gflops": peak,
                         "fraction_of_peak": samples_per_second * flops / 1e9 / peak, "exact": revealed.exact})
    torch.set_num_threads(max(config.threads))
    return Measured(rows, (bundle.width, bundle.height))


def describe_throughput(context: BenchContext, measured: Measured) -> list[str]:
    rows, (width, height) = measured.rows, measured.secret_size
    lines = [f"Field: {field_flops(context.scene.render_field) / 1e6:.2f} MFLOP per sample; batches of 65,536 samples "
             f"with noise; reveal of the {width}×{height} bundle from the cost experiment (one sample per ray).", "",
             "| backend | threads | reveal rays/s | field samples/s | GFLOP/s | matmul peak GFLOP/s | fraction of peak |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['backend']} | {r['threads']} | {r['reveal_rays_per_second']:,.0f} | "
              f"{r['field_samples_per_second']:,.0f} | {r['gflops']:.1f} | {r['matmul_peak_gflops']:.1f} | "
              f"{r['fraction_of_peak']:.0%} |" for r in rows]
    lines.append("")
    for threads in context.config.threads:
        ort_row, torch_row = (next(r for r in rows if r["backend"] == b and r["threads"] == threads)
                              for b in ("onnxruntime", "torch"))
        rays = ort_row["reveal_rays_per_second"] / torch_row["reveal_rays_per_second"]
        samples = ort_row["field_samples_per_second"] / torch_row["field_samples_per_second"]
        lines.append(f"- {threads} thread(s): onnxruntime ÷ torch eager, reveal rays/s **{rays:.2f}**, field "
                     f"samples/s **{samples:.2f}** (goal ≥ {ONNX_OVER_TORCH_GOAL:.1f}: "
                     f"{verdict(min(rays, samples), ONNX_OVER_TORCH_GOAL, lower_is_better=False)}); onnxruntime at "
                     f"{ort_row['fraction_of_peak']:.0%} of the matmul peak (goal ≥ {PEAK_FRACTION_GOAL * 100:g} %: "
                     f"{verdict(ort_row['fraction_of_peak'], PEAK_FRACTION_GOAL, lower_is_better=False)}).")
    return lines


@dataclass(frozen=True, kw_only=True)
class Skipping(Measured):
    test_views: int  # how many the ordinary renders cover (none without --data)


def measure_skipping(context: BenchContext) -> Skipping:
    """Ordinary renders of the dataset's test views with and without skipping; hiding with and without
    retiring finished pixels."""
    config, scene = context.config, context.scene
    rows, views = [], []
    if config.data:
        dataset = load_dataset(Path(config.data), resolution=scene.config.cameras[0].width)
        field_fn = numpy_field(scene.render_field)
        views = list(dataset.splits.get("test") or dataset.splits["train"])
        for name, skip in (("dense", False), ("skipping", True)):
            started, evaluated, dense, scores = time.perf_counter(), 0, 0, []
            for index in views:
                image, stats = render_view(dataset.cameras[index], scene.config.render, field_fn,
                                           MarchingSampler(scene.config.render, scene.grid, skip))
                scores.append(psnr(image, dataset.images[index]))
                evaluated, dense = evaluated + stats.n_samples_evaluated, dense + stats.n_samples_dense
            rows.append({"experiment": "ordinary render", "variant": name, "work": evaluated, "dense_work": dense,
                         "psnr": float(np.mean(scores)), "seconds": time.perf_counter() - started})
    small = small_secret(context.secret, 2 * config.small_width)
    for retiring in (True, False):
        curve, counts = exact_curve(scene, small, config.view, retiring)
        rows.append({"experiment": "exact hide", "variant": "retiring" if retiring else "no retiring",
                     "work": counts["jacobians"], "dense_work": counts["renders"], "psnr": curve[-1]["psnr"],
                     "seconds": counts["seconds"]})
    return Skipping(rows, size_of(small), test_views=len(views))


def describe_skipping(context: BenchContext, measured: Skipping) -> list[str]:
    rows, (width, height) = measured.rows, measured.secret_size
    lines = ["| experiment | variant | work | other work | PSNR dB | seconds |", "|---|---|---|---|---|---|"]
    lines += [f"| {r['experiment']} | {r['variant']} | {r['work']:,} | {r['dense_work']:,} | {r['psnr']:.2f} | "
              f"{r['seconds']:.1f} |" for r in rows]
    lines.append("")
    renders = [r for r in rows if r["experiment"] == "ordinary render"]
    if renders:
        dense_row, skip_row = renders
        fewer, change = dense_row["work"] / skip_row["work"], skip_row["psnr"] - dense_row["psnr"]
        lines.append(f"- Ordinary renders of {measured.test_views} test views: {dense_row['dense_work']:,} samples "
                     f"along the rays, {dense_row['work']:,} of them inside the scene's box (the dense render: outside "
                     f"the box the scene is empty), {skip_row['work']:,} evaluated with the occupancy grid and early "
                     f"termination: **{dense_row['dense_work'] / skip_row['work']:.1f}× fewer** than all samples, "
                     f"{fewer:.1f}× fewer than the dense render (goal ≥ {SKIPPED_WORK_GOAL}×: "
                     f"{verdict(fewer, SKIPPED_WORK_GOAL, lower_is_better=False)}); PSNR change **{change:+.3f} dB** "
                     f"(goal within {SKIPPED_PSNR_GOAL_DB} dB: "
                     f"{verdict(abs(change), SKIPPED_PSNR_GOAL_DB, lower_is_better=True)}); time "
                     f"{dense_row['seconds'] / skip_row['seconds']:.1f}× less.")
    hides = [r for r in rows if r["experiment"] == "exact hide"]
    lines.append(f"- Exact hide of a {width}×{height} secret: pixel-Jacobians (work) "
                 f"{hides[1]['work']:,} without retiring vs {hides[0]['work']:,} with it "
                 f"(**{hides[1]['work'] / hides[0]['work']:.1f}×**; other work = forward passes), "
                 f"{hides[1]['seconds'] / hides[0]['seconds']:.1f}× the time.")
    return lines


def stored_quality(kept: PaperNoise, dtype: str) -> dict:
    """Exact fraction and PSNR of paper-mode noise once stored as `dtype` (float32 or float16)."""
    index = torch.arange(kept.secret_view.n_rays, device=kept.secret_view.device)
    with torch.no_grad():
        stored = kept.noise.to(getattr(torch, dtype)).float().to(index.device)
        quality = secret_quality(kept.secret_view.render(index, stored), kept.secret)
    return {"exact_fraction": quality["exact_fraction"], "psnr": quality["psnr"]}


def measure_bundle_size(context: BenchContext) -> Measured:
    """Bytes per hidden pixel of each noise layout and dtype, and what float16 storage does to each; the
    paper's quality is that of error_vs_time's noise (its one-iteration hides here give the bytes only)."""
    config = context.config
    small = small_secret(context.secret, config.small_width)
    n_pixels = small.shape[0] * small.shape[1]
    rows = []
    for method, layout, dtype, samples in (("exact", "compact", "int16", 1), ("exact", "ray", "float16", 1),
                                           ("exact", "ray", "float32", 1),
                                           ("paper", "sample", "float32", config.paper_samples),
                                           ("paper", "sample", "float16", config.paper_samples)):
        paper = recipe(config.paper_recipe, iters=1, record_at=())
        report = context.hide(small, "size", HideConfig(method=method, layout=layout, dtype=dtype, n_samples=samples,
                                                        view=config.view, settings=(paper,)))
        row = {"method": method, "layout": layout, "dtype": dtype, "samples": samples,
               "file_bytes_per_pixel": report["bundle_bytes"] / n_pixels, "hide_seconds": report["seconds"],
               "exact_fraction": report["exact_fraction"]}
        if method == "paper":
            row.update(stored_quality(context.needed["error_vs_time"].paper_noise, dtype))
        rows.append(row)
    return Measured(rows, size_of(small))


def describe_bundle_size(context: BenchContext, measured: Measured) -> list[str]:
    width, height = measured.secret_size
    lines = [f"The secret at {width}×{height}; bytes per pixel are the whole file's (metadata, "
             "bases and escapes included) ÷ the secret's pixels.", "",
             "| method | layout | dtype | samples/ray | file bytes/pixel | hide s | exact fraction |",
             "|---|---|---|---|---|---|---|"]
    lines += [f"| {r['method']} | {r['layout']} | {r['dtype']} | {r['samples']} | {r['file_bytes_per_pixel']:,.1f} | "
              f"{r['hide_seconds']:.2f} | "
              f"{r['exact_fraction']:.4f} |" for r in measured.rows]
    lines += ["", "Exact mode verifies every pixel after rounding to the storage dtype (the compact layout's "
              "integer lattice, the ray layout's float16), so its bundles are exact by construction; the paper's "
              "rows give the fraction its noise (from the run-time experiment) reaches before and after float16 "
              "rounding. Small secrets pay relatively more for a tile's basis and metadata (~2.5 KB)."]
    return lines
