"""The paper's method: its quality at the paper's scale, its run time against the exact method's, and the
paper's Table 3 ablation."""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.images import load_secret, resize_image, to_uint8
from noisenerf.train.hide.settings import NO_SKIP, PaperSettings, pass_samples_for, recipe
from noisenerf.train.scene.field_kinds import Field
from noisenerf.train.scene.scene import Scene, load_scene

from noisenerf.cli.bench.config import BenchConfig
from noisenerf.cli.bench.context import BenchContext, Measured, peak_rss_gib, size_of, small_secret
from noisenerf.cli.bench.curves import PaperNoise, PaperRun, exact_curve, paper_curve
from noisenerf.cli.bench.exact_cost import field_flops, linear_flops
from noisenerf.cli.bench.report import curves_plot, save_figure, verdict

PAPER_TABLE1_SSIM = {"NeRF-Synthetic": 0.9913, "LLFF": 0.9847}  # the paper's mean SSIM after 300 iterations (Table 1)
PAPER_PHOTO_SSIM_FLOOR = 0.98  # no photo's SSIM (data_range 1, 11×11 Gaussian) below this after 300 iterations
PAPER_GPU_MEMORY_GOAL_GIB = 8.0  # peak GPU memory of a run at twice the secret width (CUDA only)
SKIP_SPEEDUP_GOAL = 5.0  # paper_speed: time without skipping ÷ time with it, the same secrets in one run
SKIP_SSIM_BOUND = 0.002  # paper_speed: |mean SSIM with skipping − without|
EXACT_OVER_PAPER_GOAL = 0.05  # exact-mode time ÷ paper-mode time, whole runs, with strictly better quality
CURVE_POINTS = (1, 5, 10, 25, 50, 75, 100, 150, 200, 250, 300)

ABLATION = {  # the paper's Table 3 on the paper's recipe as the paper ran it (no revival), then revival
    "none": ("paper", False, False, "off"), "no APS": ("paper", True, False, "off"),
    "no PP": ("paper", False, True, "off"), "full": ("paper", True, True, "off"),
    "full + revival (dead)": ("paper", True, True, "dead"), "full + revival (all)": ("paper", True, True, "all"),
    "authors": ("authors", False, False, "off"), "authors + revival (dead)": ("authors", False, False, "dead"),
    "authors + revival (all)": ("authors", False, False, "all"), "noisenerf (the default)": ("noisenerf", False, False, "all"),
}

PAPER_CHANGES = {  # our changes to the authors' method, each by the settings that switch it off alone
    "the authors' weight decay (0.8·0.3^(t/T))": {"weight_decay": 0.8},
    "the authors' step to lr 0.01 at 50": {"lr_step_at": 50},
    "finished pixels not retired": {"finish_within": None},
    "raw colours free to saturate": {"saturation_bound": float("inf")},
}


@dataclass(frozen=True)
class PaperTarget:
    """A scene the paper-quality experiments hide their photos in, at one of its views."""

    name: str  # its folder's name
    scene: Scene
    view: int

    @property
    def family(self) -> str:
        """The paper's dataset family (Table 1): LLFF for a forward-facing scene, rendered in NDC, else NeRF-Synthetic."""
        return "LLFF" if self.scene.config.render.ndc is not None else "NeRF-Synthetic"


def paper_targets(context: BenchContext) -> list[PaperTarget]:
    """paper_scenes, each loaded; without them, the bench's scene at its view."""
    config = context.config
    if not config.paper_scenes:
        return [PaperTarget(Path(config.scene).name, context.scene, config.view)]
    return [PaperTarget(Path(folder).name, load_scene(folder), view) for folder, view in config.paper_scenes]


def paper_secret_paths(config: BenchConfig) -> tuple[str, ...]:
    """The photos paper_quality and paper_changes hide."""
    return config.paper_secrets or config.photos[:config.paper_photos] or (config.secret,)


def paper_width(context: BenchContext) -> int:
    """paper_quality's square secrets: the paper's 400 on CUDA, small on a CPU, unless --paper-width says."""
    return context.config.paper_width or (400 if context.device.type == "cuda" else context.config.small_width)


def quality_settings(context: BenchContext) -> PaperSettings:
    """The default recipe at the bench's iterations, recording the curve's points."""
    config = context.config
    return recipe(config.paper_recipe, iters=config.paper_iters, pass_samples=pass_samples_for(context.device.type),
                  record_at=tuple(t for t in CURVE_POINTS if t < config.paper_iters) + (config.paper_iters,))


@dataclass(frozen=True, kw_only=True)
class PaperCurves(Measured):
    settings: PaperSettings  # the recipe the rows ran (the report names it)


@dataclass(frozen=True, kw_only=True)
class PaperQuality(PaperCurves):
    runs: list[tuple[PaperTarget, str, PaperRun]]  # (where, photo name, its run)
    probe_gib: float | None  # peak GPU memory at twice the width (CUDA only)


@dataclass(frozen=True, kw_only=True)
class ErrorVsTime(PaperCurves):
    paper_noise: PaperNoise  # the paper's noise it found: bundle_size stores it as float32 and float16


def square_secret(photo: np.ndarray, width: int) -> np.ndarray:
    """The photo's central square resized to width × width (the paper's views are square)."""
    height, full_width = photo.shape[:2]
    side = min(height, full_width)
    top, left = (height - side) // 2, (full_width - side) // 2
    crop = photo[top:top + side, left:left + side].astype(np.float32) / 255.0
    return to_uint8(resize_image(crop, width, width))


def ablation_secret(context: BenchContext) -> np.ndarray:
    """The secret the run-time and ablation curves hide: the authors' 100 px wide on CUDA, small on a CPU."""
    config = context.config
    cuda = context.device.type == "cuda"
    return small_secret(context.secret, config.ablation_width or (100 if cuda else config.small_width))


def measure_paper_quality(context: BenchContext) -> PaperQuality:
    """The paper's method at the paper's scale: photos as square secrets at each target's view, 64 samples,
    300 iterations, the default recipe; SSIM both ways, PSNR, time and peak memory. On a CPU the secrets
    are downscaled (the report says so); on CUDA a last run at twice the width measures memory only."""
    config, device, width = context.config, context.device, paper_width(context)
    settings = quality_settings(context)
    rows, runs = [], []
    for target in paper_targets(context):
        for path in paper_secret_paths(config):
            photo = square_secret(load_secret(path)[0], width)
            run = paper_curve(target.scene, photo, target.view, config.paper_samples, settings, device,
                              label=Path(path).name)
            rows += [{**row, "scene": target.name, "view": target.view, "width": width, "peak_gib": run.peak_gib,
                      "dead_fraction": run.dead_fraction} for row in run.rows]
            print(f"paper_quality: {target.name} view {target.view}, {Path(path).name} {width}²: SSIM "
                  f"{run.rows[-1]['ssim']:.4f}, authors' SSIM {run.rows[-1]['ssim_authors']:.4f}, PSNR "
                  f"{run.rows[-1]['psnr']:.2f} dB, {run.seconds:.1f} s, peak GPU {run.peak_gib} GiB",
                  file=sys.stderr, flush=True)  # seen even if a long run is cut
            runs.append((target, Path(path).name, run))
    probe_gib = None
    if device.type == "cuda":
        big = square_secret(context.secret, 2 * width)
        probe_gib = paper_curve(context.scene, big, config.view, config.paper_samples,
                                dataclasses.replace(settings, iters=2, record_at=(2,)), device,
                                label="memory probe").peak_gib
    return PaperQuality(rows, (width, width), settings=settings, runs=runs, probe_gib=probe_gib)


def paper_goal_line(name: str, family: str, finals: list[dict], iters: int) -> str:
    """One scene's verdict: its mean SSIM against the paper's figure for its family, no photo under the floor."""
    mean_ssim, lowest = float(np.mean([f["ssim"] for f in finals])), min(f["ssim"] for f in finals)
    goal = PAPER_TABLE1_SSIM[family]
    met = verdict(mean_ssim, goal, lower_is_better=False, also=lowest >= PAPER_PHOTO_SSIM_FLOOR)
    return (f"- {name} ({family}): mean SSIM after {iters} iterations over {len(finals)} photos **{mean_ssim:.4f}**, "
            f"lowest {lowest:.4f}, authors' SSIM {float(np.mean([f['ssim_authors'] for f in finals])):.4f}, "
            f"{float(np.mean([f['seconds'] for f in finals])):.1f} s a secret (goal: ≥ {goal}, the paper's Table 1 "
            f"for {family}, none under {PAPER_PHOTO_SSIM_FLOOR}: {met}).")


def describe_paper_quality(context: BenchContext, measured: PaperQuality) -> list[str]:
    config, settings, (width, _) = context.config, measured.settings, measured.secret_size
    memory_lines = [] if measured.probe_gib is None else [
        f"- peak GPU memory at {2 * width}² (2 iterations, memory only): **{measured.probe_gib:.2f} GiB** "
        f"(goal ≤ {PAPER_GPU_MEMORY_GOAL_GIB:g} GiB: "
        f"{verdict(measured.probe_gib, PAPER_GPU_MEMORY_GOAL_GIB, lower_is_better=True)})."]
    scale = (f"the paper's scale ({width}×{width})" if width >= 400
             else f"secrets **downscaled to {width}×{width}** (the paper's 400² costs hours on a CPU; run the bench "
                  "with `--device cuda` for it)")
    lines = [f"Recipe `{settings.recipe}`, revival `{settings.revival}`, {config.paper_samples} samples per ray, "
             f"{settings.iters} iterations, blocks of {settings.block_pixels} pixels, coarse network, on "
             f"{context.device.type.upper()}; {scale}. SSIM: data_range 1, 11×11 Gaussian; authors' SSIM: "
             "data_range 2, 7×7 uniform (their code's).", "",
             "| scene | view | secret | SSIM | authors' SSIM | PSNR dB | exact fraction | seconds | dead rays | peak GPU GiB |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    finals: dict[tuple[str, str], list[dict]] = {}  # (scene, family) -> its photos' final rows
    for target, name, run in measured.runs:
        final = run.rows[-1]
        finals.setdefault((target.name, target.family), []).append({**final, "seconds": run.seconds})
        lines.append(f"| {target.name} | {target.view} | {name} | {final['ssim']:.4f} | {final['ssim_authors']:.4f} | "
                     f"{final['psnr']:.2f} | {final['exact_fraction']:.3f} | {run.seconds:.1f} | {run.dead_fraction:.1%} | "
                     f"{'—' if run.peak_gib is None else format(run.peak_gib, '.2f')} |")
    lines += ["", *(paper_goal_line(name, family, rows, settings.iters) for (name, family), rows in finals.items()),
              *memory_lines, f"- peak resident memory of the bench process so far: {peak_rss_gib():.2f} GiB."]
    return lines


def plot_paper_quality(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 2, figsize=(10, 3.6))
    for scene, photo in dict.fromkeys((r["scene"], r["method"]) for r in rows):
        curve = [r for r in rows if (r["scene"], r["method"]) == (scene, photo)]
        for axis, key in zip(axes, ("ssim", "psnr")):
            axis.plot([r["iteration"] for r in curve], [r[key] for r in curve], marker=".", label=f"{scene}: {photo}")
            axis.set_xlabel("iteration")
            axis.set_title({"ssim": "SSIM (data_range 1)", "psnr": "PSNR dB"}[key])
    axes[0].axhline(PAPER_PHOTO_SSIM_FLOOR, color="grey", linestyle=":")
    axes[0].legend(fontsize=7)
    figure.tight_layout()
    save_figure(figure, path)


def paper_changes_secret_paths(config: BenchConfig) -> tuple[str, ...]:
    """The photos paper_changes switches each change off on: the first paper_changes_secrets of paper_quality's."""
    return paper_secret_paths(config)[:config.paper_changes_secrets]


def measure_paper_changes(context: BenchContext) -> Measured:
    """Our changes to the default recipe, each switched off alone (PAPER_CHANGES), on paper_quality's scenes and
    views at its width, on its photos or the first paper_changes_secrets of them; paper_quality's runs of those
    photos are the row with every change on."""
    config, device = context.config, context.device
    quality: PaperQuality = context.needed["paper_quality"]
    names = {Path(path).name for path in paper_changes_secret_paths(config)}
    rows = [{"variant": "all changes", "scene": target.name, "photo": name, **final_of(run)}
            for target, name, run in quality.runs if name in names]
    for variant, off in PAPER_CHANGES.items():
        settings = dataclasses.replace(quality.settings, record_at=(config.paper_iters,), **off)
        for target in paper_targets(context):
            for path in paper_changes_secret_paths(config):
                photo = square_secret(load_secret(path)[0], quality.secret_size[0])
                run = paper_curve(target.scene, photo, target.view, config.paper_samples, settings, device,
                                  label=variant)
                rows.append({"variant": variant, "scene": target.name, "photo": Path(path).name, **final_of(run)})
                print(f"paper_changes: {variant}, {target.name}, {Path(path).name}: SSIM {rows[-1]['ssim']:.4f}, "
                      f"{run.seconds:.1f} s", file=sys.stderr, flush=True)
    return Measured(rows, quality.secret_size)


def final_of(run: PaperRun) -> dict:
    """A run's last record and its time."""
    final = run.rows[-1]
    return {"ssim": final["ssim"], "ssim_authors": final["ssim_authors"], "psnr": final["psnr"], "seconds": run.seconds}


def describe_paper_changes(context: BenchContext, measured: Measured) -> list[str]:
    width, _ = measured.secret_size
    photos = sorted({row["photo"] for row in measured.rows})
    lines = [f"Each of our changes to the recipe switched off alone, on paper_quality's scenes and views, on the "
             f"same {len(photos)} photos ({', '.join(photos)}; {width}×{width}); the first row is paper_quality's runs "
             "of them, with all of them on.", "",
             "| variant | scene | mean SSIM | lowest SSIM | mean authors' SSIM | mean PSNR dB | s a secret |",
             "|---|---|---|---|---|---|---|"]
    for variant, scene in dict.fromkeys((row["variant"], row["scene"]) for row in measured.rows):
        runs = [row for row in measured.rows if (row["variant"], row["scene"]) == (variant, scene)]
        lines.append(f"| {variant} | {scene} | {np.mean([r['ssim'] for r in runs]):.4f} | "
                     f"{min(r['ssim'] for r in runs):.4f} | {np.mean([r['ssim_authors'] for r in runs]):.4f} | "
                     f"{np.mean([r['psnr'] for r in runs]):.2f} | {np.mean([r['seconds'] for r in runs]):.1f} |")
    return lines


def pass_flops(field: Field) -> tuple[int, int]:
    """Floating-point operations per sample: of a forward and backward pass (the backward to the input only,
    the weights being frozen: one more product per layer), and of a density check (trunk and density layer)."""
    return 2 * field_flops(field), linear_flops(field.density_layers())


def measure_paper_speed(context: BenchContext) -> PaperCurves:
    """The default recipe on the same secrets with skipping (the default) and without (`--no-skip`), one
    after the other: time, SSIM, what skipping left out, and the arithmetic rate reached."""
    config, device = context.config, context.device
    settings = recipe(config.paper_recipe, iters=config.paper_iters, pass_samples=pass_samples_for(device.type),
                      record_at=(config.paper_iters,))
    full_flops, check_flops = pass_flops(context.scene.coarse)
    rows = []
    for path in config.photos[:config.paper_photos] or (config.secret,):
        photo = square_secret(load_secret(path)[0], config.speed_width)
        for label, run_settings in (("no skip", dataclasses.replace(settings, **NO_SKIP)), ("skip", settings)):
            run = paper_curve(context.scene, photo, config.view, config.paper_samples, run_settings, device, label=label)
            sample_iterations = photo.shape[0] * photo.shape[1] * config.paper_samples * config.paper_iters
            flops = sample_iterations * ((1 - run.skipping["skipped_samples"]) * full_flops
                                         + run.skipping["checked_samples"] * check_flops)
            final = run.rows[-1]
            rows.append({"photo": Path(path).name, "run": label, "seconds": run.seconds,
                         "seconds_per_pixel": run.seconds / (photo.shape[0] * photo.shape[1]), "ssim": final["ssim"],
                         "psnr": final["psnr"], **run.skipping, "gflops": flops / run.seconds / 1e9,
                         "peak_gib": run.peak_gib})
            print(f"paper_speed: {Path(path).name} {label}: {run.seconds:.1f} s, SSIM {final['ssim']:.4f}",
                  file=sys.stderr, flush=True)
    return PaperCurves(rows, (config.speed_width, config.speed_width), settings=settings)


def describe_paper_speed(context: BenchContext, measured: PaperCurves) -> list[str]:
    config, settings, (width, _) = context.config, measured.settings, measured.secret_size
    runs = {label: [row for row in measured.rows if row["run"] == label] for label in ("no skip", "skip")}
    speedup = sum(row["seconds"] for row in runs["no skip"]) / sum(row["seconds"] for row in runs["skip"])
    ssim_gap = abs(float(np.mean([r["ssim"] for r in runs["skip"]])) - float(np.mean([r["ssim"] for r in runs["no skip"]])))
    lines = [f"Recipe `{settings.recipe}` (revival `{settings.revival}`), {config.paper_samples} samples per ray, "
             f"{settings.iters} iterations, secrets {width}×{width} at scene view {config.view}, on "
             f"{context.device.type.upper()}; each secret without skipping (`--no-skip`, the method as written) "
             f"and then with the defaults (dead samples skipped, checked again every {settings.recheck_every} "
             f"iterations; pixels within {settings.finish_within} levels of their target retired). Skipped: "
             "sample-iterations left out of the forward and backward pass; checked: passes without gradients "
             "(density checks, retiring's renders) per sample-iteration; idle: pixel-iterations with nothing to "
             "evaluate.", "",
             "| secret | run | seconds | s/pixel | SSIM | PSNR dB | skipped | checked | idle | GFLOP/s |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for row in measured.rows:
        lines.append(f"| {row['photo']} | {row['run']} | {row['seconds']:.1f} | {row['seconds_per_pixel']:.4f} | "
                     f"{row['ssim']:.4f} | {row['psnr']:.2f} | {row['skipped_samples']:.1%} | "
                     f"{row['checked_samples']:.1%} | {row['idle_pixels']:.1%} | {row['gflops']:.1f} |")
    met = verdict(speedup, SKIP_SPEEDUP_GOAL, lower_is_better=False, also=ssim_gap <= SKIP_SSIM_BOUND)
    lines += ["", f"- time without skipping ÷ time with it (all secrets): **{speedup:.2f}×**, mean SSIM apart by "
              f"**{ssim_gap:.4f}** (goal ≥ {SKIP_SPEEDUP_GOAL:g}× within {SKIP_SSIM_BOUND} of SSIM: {met})."]
    return lines


def measure_error_vs_time(context: BenchContext) -> ErrorVsTime:
    """Both methods on the same small secret, quality against time; keeps the paper's noise for bundle_size."""
    config, device = context.config, context.device
    small = ablation_secret(context)
    exact_rows, _ = exact_curve(context.scene, small, config.view, device=device)
    record_at = tuple(t for t in sorted({1, 2, 5, 10, 20, *range(25, 301, 25), config.paper_iters})
                      if t <= config.paper_iters)
    settings = recipe(config.paper_recipe, iters=config.paper_iters, record_at=record_at,
                      pass_samples=pass_samples_for(device.type))
    run = paper_curve(context.scene, small, config.view, config.paper_samples, settings, device, keep_noise=True)
    return ErrorVsTime(exact_rows + run.rows, size_of(small), settings=settings, paper_noise=run.kept)


def first_reaching(rows: list[dict], key: str, value: float) -> dict | None:
    return next((row for row in rows if row[key] >= value), None)


def describe_error_vs_time(context: BenchContext, measured: ErrorVsTime) -> list[str]:
    config, settings, (width, height) = context.config, measured.settings, measured.secret_size
    exact_rows = [row for row in measured.rows if row["method"] == "exact"]
    paper_rows = [row for row in measured.rows if row["method"] == "paper"]
    lines = [f"Secret: `{Path(config.secret).name}` downscaled to {width}×{height}, scene view {config.view}, both on "
             f"{context.device.type.upper()}. Paper: recipe `{settings.recipe}` with revival `{settings.revival}`, "
             f"{config.paper_samples} samples per ray, {config.paper_iters} iterations, coarse network; exact: one "
             "sample per ray, float16 noise.", "",
             "| target | exact: seconds | paper: seconds | exact ÷ paper |", "|---|---|---|---|"]
    paper_final_ssim = paper_rows[-1]["ssim"]
    targets = (("ssim", paper_final_ssim, f"SSIM ≥ {paper_final_ssim:.4f} (the paper method's final: same quality)"),
               ("ssim", 0.99, "SSIM ≥ 0.99"), ("exact_fraction", 1.0, "100 % exact 8-bit values"))
    for key, value, label in targets:
        hit_exact, hit_paper = first_reaching(exact_rows, key, value), first_reaching(paper_rows, key, value)
        paper_text = f"{hit_paper['seconds']:.1f}" if hit_paper else f"not reached in {config.paper_iters} iterations"
        ratio = (f"{hit_exact['seconds'] / hit_paper['seconds']:.4f}" if hit_exact and hit_paper
                 else f"< {exact_rows[-1]['seconds'] / paper_rows[-1]['seconds']:.4f}" if hit_exact else "—")
        lines.append(f"| {label} | {hit_exact['seconds']:.2f} | {paper_text} | {ratio} |" if hit_exact
                     else f"| {label} | not reached | {paper_text} | — |")
    final_exact, final_paper = exact_rows[-1], paper_rows[-1]
    lines += ["", "| method | seconds | PSNR dB | SSIM | exact fraction | max error |", "|---|---|---|---|---|---|"]
    for row in (final_exact, final_paper):
        lines.append(f"| {row['method']} | {row['seconds']:.1f} | {row['psnr']:.2f} | {row['ssim']:.4f} | "
                     f"{row['exact_fraction']:.4f} | {row['max_error']} |")
    ratio = final_exact["seconds"] / final_paper["seconds"]
    met = verdict(ratio, EXACT_OVER_PAPER_GOAL, lower_is_better=True, also=final_exact["psnr"] > final_paper["psnr"])
    lines += ["", f"Exact-mode time ÷ paper-mode time (whole runs): **{ratio:.4f}** (goal ≤ {EXACT_OVER_PAPER_GOAL:g}, "
              f"with strictly better quality: {met})."]
    return lines


def plot_error_vs_time(rows: list[dict], path: Path) -> None:
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    for method in ("exact", "paper"):
        curve = [r for r in rows if r["method"] == method]
        for axis, key in zip(axes, ("psnr", "ssim", "exact_fraction")):
            axis.plot([r["seconds"] for r in curve], [min(r[key], 100) for r in curve], marker=".", label=method)
            axis.set_xscale("log")
            axis.set_xlabel("seconds (log)")
            axis.set_title({"psnr": "PSNR dB (capped at 100)", "ssim": "SSIM", "exact_fraction": "exact fraction"}[key])
    axes[0].legend()
    figure.tight_layout()
    save_figure(figure, path)


def ablation_points(iters: int) -> tuple[int, ...]:
    """The Table 3 iterations (50, 200, 300) a run of `iters` reaches, and its last."""
    return tuple(sorted({t for t in (50, 200, 300) if t <= iters} | {iters}))


def measure_ablation(context: BenchContext) -> Measured:
    """The paper's Table 3: SSIM and loss at 50, 200, 300 iterations with each strategy switched off,
    and each recipe with and without revival."""
    config, device = context.config, context.device
    small = ablation_secret(context)
    rows = []
    for name, (recipe_name, perturbation, selection, revival) in ABLATION.items():
        settings = recipe(recipe_name, iters=config.paper_iters, pixel_perturbation=perturbation,
                          adaptive_selection=selection, revival=revival, record_at=ablation_points(config.paper_iters),
                          pass_samples=pass_samples_for(device.type))
        rows += paper_curve(context.scene, small, config.view, config.ablation_samples, settings, device,
                            label=name).rows
    return Measured(rows, size_of(small))


def describe_ablation(context: BenchContext, measured: Measured) -> list[str]:
    config, (width, height) = context.config, measured.secret_size
    points = ablation_points(config.paper_iters)
    lines = [f"Secret {width}×{height}, {config.ablation_samples} samples per ray, coarse network, on "
             f"{context.device.type.upper()}. SSIM uses data_range 1. Rows 1–4 are the paper's Table 3 (the paper's "
             "recipe as the paper describes it); revival is our addition.", "",
             "| variant | " + " | ".join(f"SSIM@{t}" for t in points) + " | " + " | ".join(f"loss@{t}" for t in points)
             + " |", "|---|" + "---|" * 2 * len(points)]
    for name in ABLATION:
        by_t = {row["iteration"]: row for row in measured.rows if row["method"] == name}
        lines.append(f"| {name} | " + " | ".join(f"{by_t[t]['ssim']:.4f}" for t in points) + " | "
                     + " | ".join(f"{by_t[t]['loss']:.5f}" for t in points) + " |")
    return lines


def plot_ablation(rows: list[dict], path: Path) -> None:
    curves_plot(rows, path, "method", "iteration", "ssim", ("iteration", "SSIM"))
