"""The exact method on real secrets at scale: photos at native size, views all around the scene, a busy
machine, and a 2K secret as tiles."""

from __future__ import annotations

import math
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.cores import available_cores
from noisenerf.runtime.images import load_secret
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, resized, size_of, small_secret
from noisenerf.cli.bench.exact_cost import HIDE_OVER_REVEAL_GOAL
from noisenerf.cli.bench.report import curves_plot, verdict

VIEW_SPREAD_GOAL = 3  # hide µs per pixel: the slowest view's median ÷ the median over views
CONTENTION_GOAL = 3  # hide time beside one busy process ÷ hide time alone
BYTES_PER_PIXEL_GOAL = 8  # exact (compact) bundle file bytes ÷ secret pixels, metadata included
TWOK_HIDE_GOAL_SECONDS = 1800  # a 2048² secret hidden, extrapolated from the rows measured
TWOK_REVEAL_GOAL_SECONDS = 30  # and revealed with onnxruntime


def measure_photos(context: BenchContext) -> Measured:
    """Each photo at native size: exact in torch and in onnxruntime, and time."""
    rows = []
    for path in context.config.photos:
        photo, _, _ = load_secret(path)
        report, revealed, reveal_seconds = context.hide_and_reveal(photo, "photo", HideConfig(view=context.config.view))
        rows.append({"secret": Path(path).name, "width": photo.shape[1], "height": photo.shape[0],
                     "tiles": len(report["tiles"]), "hide_seconds": report["seconds"],
                     "reveal_seconds": reveal_seconds, "torch_exact_fraction": report["exact_fraction"],
                     "onnx_exact": revealed.exact, "bytes_per_pixel": report["bytes_per_pixel"],
                     "hide_over_reveal": report["seconds"] / reveal_seconds,
                     "max_iterations": max(t["iterations"] for t in report["tiles"]),
                     "restarts": sum(t["restarts"] for t in report["tiles"]),
                     "escaped": sum(t.get("escaped", 0) for t in report["tiles"]),
                     **{f"{count}_per_pixel": sum(t[count] for t in report["tiles"]) / photo[..., 0].size
                        for count in ("jacobians", "renders")}})
    return Measured(rows)


def describe_photos(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    lines = ["| secret | size | tiles | hide s | reveal s | hide ÷ reveal | torch exact | onnxruntime exact | "
             "bytes/pixel | escaped | restarts | Jacobians/pixel | renders/pixel |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['secret']} | {r['width']}×{r['height']} | {r['tiles']} | {r['hide_seconds']:.1f} | "
              f"{r['reveal_seconds']:.2f} | {r['hide_over_reveal']:.1f} | {r['torch_exact_fraction']:.6f} | "
              f"{str(r['onnx_exact']).lower()} | {r['bytes_per_pixel']:.2f} | {r['escaped']:,} | {r['restarts']:,} | "
              f"{r['jacobians_per_pixel']:.1f} | {r['renders_per_pixel']:.1f} |"
              for r in rows]
    if rows:
        pixels = sum(r["width"] * r["height"] for r in rows)
        seconds = sum(r["hide_seconds"] for r in rows)
        worst = max(r["bytes_per_pixel"] for r in rows)
        ratio = float(np.median([r["hide_over_reveal"] for r in rows]))
        lines += ["", f"All exact: **{all(r['onnx_exact'] for r in rows)}**; {pixels / seconds:,.0f} pixels per "
                  f"second of hiding ({seconds / len(rows):.1f} s per photo on average); bytes per pixel at most "
                  f"**{worst:.2f}** (goal ≤ {BYTES_PER_PIXEL_GOAL}: "
                  f"{verdict(worst, BYTES_PER_PIXEL_GOAL, lower_is_better=True)}); "
                  f"median hide ÷ reveal **{ratio:.1f}** (goal ≤ {HIDE_OVER_REVEAL_GOAL}: "
                  f"{verdict(ratio, HIDE_OVER_REVEAL_GOAL, lower_is_better=True)})."]
    return lines


def spread_views(n_cameras: int, count: int) -> list[int]:
    """`count` camera indices evenly spread over a scene's n_cameras (all of them if fewer)."""
    return sorted({round(i * n_cameras / count) % n_cameras for i in range(count)})


def view_photo_paths(context: BenchContext) -> tuple[str, ...]:
    """The photos the views experiment hides at each view (the bench secret without --photos)."""
    config = context.config
    return (config.photos or (config.secret,))[:config.view_photos]


def measure_views(context: BenchContext) -> Measured:
    """Exact hide and onnxruntime reveal of `view_photos` photos at `views` cameras around the scene."""
    config = context.config
    photos = [load_secret(path)[0] for path in view_photo_paths(context)]
    if config.view_width is not None:
        photos = [small_secret(photo, config.view_width) for photo in photos]
    names = [Path(path).name for path in view_photo_paths(context)]
    rows = []
    for view in spread_views(len(context.scene.config.cameras), config.views):
        for name, photo in zip(names, photos):
            report, revealed, reveal_seconds = context.hide_and_reveal(photo, "view", HideConfig(view=view))
            pixels = photo.shape[0] * photo.shape[1]
            rows.append({"view": view, "secret": name, "pixels": pixels, "hide_seconds": report["seconds"],
                         "hide_us_per_pixel": report["seconds"] / pixels * 1e6, "reveal_seconds": reveal_seconds,
                         "hide_over_reveal": report["seconds"] / reveal_seconds, "onnx_exact": revealed.exact,
                         "bytes_per_pixel": report["bytes_per_pixel"],
                         "escaped": sum(tile.get("escaped", 0) for tile in report["tiles"])})
    return Measured(rows)


def describe_views(context: BenchContext, measured: Measured) -> list[str]:
    config, rows = context.config, measured.rows
    per_pixel = np.array([r["hide_us_per_pixel"] for r in rows])
    by_view = {view: float(np.median([r["hide_us_per_pixel"] for r in rows if r["view"] == view]))
               for view in dict.fromkeys(r["view"] for r in rows)}
    spread = max(by_view.values()) / float(np.median(list(by_view.values())))
    hide_over_reveal = np.median([r["hide_over_reveal"] for r in rows])
    worst_bytes = max(r["bytes_per_pixel"] for r in rows)
    lines = [f"{len(view_photo_paths(context))} photos "
             f"({'native size' if config.view_width is None else f'{config.view_width} px wide'}) "
             f"hidden (compact layout) at each of {len(by_view)} views spread around the scene and revealed with "
             "onnxruntime.", "",
             "| view | median hide µs/pixel | worst hide µs/pixel | median hide ÷ reveal | bytes/pixel | all exact |",
             "|---|---|---|---|---|---|"]
    for view in by_view:
        mine = [r for r in rows if r["view"] == view]
        lines.append(f"| {view} | {by_view[view]:,.0f} | {max(r['hide_us_per_pixel'] for r in mine):,.0f} | "
                     f"{np.median([r['hide_over_reveal'] for r in mine]):.1f} | "
                     f"{np.median([r['bytes_per_pixel'] for r in mine]):.2f} | "
                     f"{str(all(r['onnx_exact'] for r in mine)).lower()} |")
    lines += ["", f"Hide time per pixel: median **{np.median(per_pixel):,.0f} µs**, worst "
              f"**{per_pixel.max():,.0f} µs**; slowest view ÷ median view **{spread:.1f}** (goal ≤ {VIEW_SPREAD_GOAL}: "
              f"{verdict(spread, VIEW_SPREAD_GOAL, lower_is_better=True)}); median hide ÷ reveal "
              f"**{hide_over_reveal:.1f}** (goal ≤ {HIDE_OVER_REVEAL_GOAL}: "
              f"{verdict(hide_over_reveal, HIDE_OVER_REVEAL_GOAL, lower_is_better=True)}); bytes per pixel "
              f"median {np.median([r['bytes_per_pixel'] for r in rows]):.2f}, worst "
              f"**{worst_bytes:.2f}** (goal ≤ {BYTES_PER_PIXEL_GOAL}: "
              f"{verdict(worst_bytes, BYTES_PER_PIXEL_GOAL, lower_is_better=True)}); all exact: "
              f"**{str(all(r['onnx_exact'] for r in rows)).lower()}**."]
    return lines


def plot_views(rows: list[dict], path: Path) -> None:
    curves_plot(rows, path, "secret", "view", "hide_us_per_pixel", ("scene camera (view)", "hide µs per pixel"),
                marker="o", size=(6, 3.6))


def measure_contention(context: BenchContext) -> Measured:
    """The exact hide of the secret at contention_width alone, then with one CPU-bound process beside it."""
    small = small_secret(context.secret, context.config.contention_width)
    rows = []
    for busy in (0, 1, 0, 1):
        loops = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(busy)]
        try:
            report = context.hide(small, "busy", HideConfig(view=context.config.view))
        finally:
            for loop in loops:
                loop.kill()
                loop.wait()
        rows.append({"busy_processes": busy, "hide_seconds": report["seconds"], "exact": report["exact"]})
    return Measured(rows, size_of(small))


def describe_contention(context: BenchContext, measured: Measured) -> list[str]:
    rows, (width, height) = measured.rows, measured.secret_size
    part_pixels = HideConfig().part_pixels
    alone = np.median([r["hide_seconds"] for r in rows if r["busy_processes"] == 0])
    busy = np.median([r["hide_seconds"] for r in rows if r["busy_processes"] == 1])
    lines = [f"`{Path(context.config.secret).name}` at {width}×{height}, view {context.config.view}, hidden twice "
             f"alone and twice beside one `python -c 'while True: pass'` on {available_cores()} cores: its "
             f"{math.ceil(width * height / part_pixels)} part(s) of {part_pixels:,} pixels spread over "
             f"{available_cores()} worker processes of one torch thread each (train/hide/executors.LocalExecutor, "
             "ExactSolver.threads).", "",
             f"- hide alone {alone:.2f} s, beside a busy process {busy:.2f} s: **{busy / alone:.1f}×** "
             f"(goal ≤ {CONTENTION_GOAL}: {verdict(busy / alone, CONTENTION_GOAL, lower_is_better=True)}).",
             "", "| busy processes | hide s | exact |", "|---|---|---|"]
    lines += [f"| {r['busy_processes']} | {r['hide_seconds']:.2f} | {str(r['exact']).lower()} |" for r in rows]
    return lines


@dataclass(frozen=True, kw_only=True)
class TiledSecret2K(Measured):
    """The 2048² secret hidden as tiles: one row, the part measured and its extrapolation to the whole."""

    bytes_per_pixel: float  # of the part hidden


def measure_twok(context: BenchContext) -> TiledSecret2K:
    """A 2048×2048 secret (twok_size) as 512-px tiles: the first `twok_rows` tile rows hidden and revealed."""
    config = context.config
    big = resized(context.secret, config.twok_size, config.twok_size)
    rows_total = config.twok_size // config.twok_tile
    part = big[:config.twok_rows * config.twok_tile]
    report, revealed, reveal_seconds = context.hide_and_reveal(part, "twok", HideConfig(view=config.view,
                                                                                       tile_size=config.twok_tile))
    scale = rows_total / config.twok_rows
    row = {"hidden_rows": config.twok_rows, "tile_rows": rows_total, "tiles": len(report["tiles"]),
           "hide_seconds": report["seconds"], "reveal_seconds": reveal_seconds, "exact": revealed.exact,
           "torch_exact_fraction": report["exact_fraction"], "hide_seconds_2k": report["seconds"] * scale,
           "reveal_seconds_2k": reveal_seconds * scale, "bundle_bytes_2k": report["bundle_bytes"] * scale}
    return TiledSecret2K([row], bytes_per_pixel=report["bytes_per_pixel"])


def describe_twok(context: BenchContext, measured: TiledSecret2K) -> list[str]:
    config, row = context.config, measured.rows[0]
    scale = row["tile_rows"] / row["hidden_rows"]
    part = "the whole secret" if scale == 1 else (f"the first {row['hidden_rows']} of {row['tile_rows']} tile rows "
                                                   f"({row['tiles']} tiles), extrapolated ×{scale:g}")
    return [f"`{Path(config.secret).name}` resized to {config.twok_size}×{config.twok_size}, tiles of "
            f"{config.twok_tile} px, each at its own camera. Measured: {part}.", "",
            f"- hide: {row['hide_seconds']:.0f} s measured → **{row['hide_seconds_2k'] / 60:.1f} min** for 2K "
            f"(goal ≤ {TWOK_HIDE_GOAL_SECONDS / 60:g} min: "
            f"{verdict(row['hide_seconds_2k'], TWOK_HIDE_GOAL_SECONDS, lower_is_better=True)});",
            f"- reveal (onnxruntime): {row['reveal_seconds']:.1f} s measured → **{row['reveal_seconds_2k']:.1f} s** "
            f"for 2K (goal ≤ {TWOK_REVEAL_GOAL_SECONDS} s: "
            f"{verdict(row['reveal_seconds_2k'], TWOK_REVEAL_GOAL_SECONDS, lower_is_better=True)}); exact: "
            f"{str(row['exact']).lower()}; bundle {row['bundle_bytes_2k'] / 2 ** 20:.1f} MiB for 2K "
            f"(**{measured.bytes_per_pixel:.2f}** bytes per pixel; goal ≤ {BYTES_PER_PIXEL_GOAL}: "
            f"{verdict(measured.bytes_per_pixel, BYTES_PER_PIXEL_GOAL, lower_is_better=True)})."]
