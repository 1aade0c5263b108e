"""The exact method's rounding margin as the reveal computes it, what arithmetic errors the bundles survive, and what
keeping the margin costs."""

from __future__ import annotations

import dataclasses
import time

import numpy as np

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret
from noisenerf.runtime.metrics import rounding_margins
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide import run as hide_run
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.settings import ExactSettings

from noisenerf.cli.bench.context import BenchContext, Measured, small_secret

RELATIVE_ERRORS = (1e-6, 1e-5, 1e-4, 1e-3)  # each field output scaled by 1 ± this, the sign drawn per value


def perturbed(field, relative: float, seed: int):
    """A field callback whose every output is scaled by 1 ± `relative`: arithmetic that differs by that much."""
    rng = np.random.default_rng(seed)

    def evaluate(*arrays):
        rgb, sigma = field(*arrays)
        return ((rgb * (1 + relative * rng.choice([-1.0, 1.0], rgb.shape))).astype(np.float32),
                (sigma * (1 + relative * rng.choice([-1.0, 1.0], sigma.shape))).astype(np.float32))

    return evaluate


def margin_views(context: BenchContext) -> list[int]:
    """margin_views cameras spread over the scene's, none the bench's own view."""
    cameras = len(context.model.cameras)
    spread = np.linspace(0, cameras, context.config.margin_views, endpoint=False).astype(int)
    return sorted({int(v) if v != context.config.view else (int(v) + 1) % cameras for v in spread})


def measure_margins(context: BenchContext) -> Measured:
    """Each photo (the first margin_photos of `photos`) at margin_width, hidden with the defaults at margin_views views
    and without the margin (the solver's margin_bins 0, no promise); the default's bundle revealed with onnxruntime
    (its smallest margin in levels) and with its field's outputs perturbed by each of RELATIVE_ERRORS."""
    config, model = context.config, context.model
    rows = []
    for photo in config.photos[:config.margin_photos]:
        secret = small_secret(load_secret(photo)[0], config.margin_width)
        for view in margin_views(context):
            started = time.perf_counter()
            report = context.hide(secret, "margin", HideConfig(view=view))
            seconds = time.perf_counter() - started
            bundle = load_bundle(context.work / "margin.bundle", model.mask_secret)
            revealed = reveal_tiles(bundle, model.render_config, model.fields(), keep_float=True)
            survived = {f"survives_{relative:g}": bool(np.array_equal(reveal_tiles(
                bundle, model.render_config, {name: perturbed(field, relative, seed=view)
                                              for name, field in model.fields().items()}).pixels, secret))
                for relative in RELATIVE_ERRORS}
            bare_started, margin_bins = time.perf_counter(), dataclasses.replace(ExactSettings(), margin_bins=0.0)
            promise, hide_run.EXACT_MARGIN_LEVELS = hide_run.EXACT_MARGIN_LEVELS, 0.0
            try:
                bare = context.hide(secret, "bare", HideConfig(view=view, settings=(margin_bins,)))
            finally:
                hide_run.EXACT_MARGIN_LEVELS = promise
            rows.append({"photo": photo.rsplit("/", 1)[-1], "view": view, "exact": revealed.exact,
                         "margin_levels": float(rounding_margins(revealed.image, secret).min()),
                         "hide_margin_levels": report["margin_levels"], **survived,
                         "bare_margin_levels": bare["margin_levels"],
                         "key_growth": report["bundle_bytes"] / bare["bundle_bytes"],
                         "hide_time_ratio": seconds / (time.perf_counter() - bare_started)})
    return Measured(rows)


def describe_margins(context: BenchContext, measured: Measured) -> list[str]:
    rows, config = measured.rows, context.config
    survived = {relative: sum(row[f"survives_{relative:g}"] for row in rows) for relative in RELATIVE_ERRORS}
    lines = [f"The first {config.margin_photos} photos at {config.margin_width} px wide, each hidden with the defaults at "
             f"views {', '.join(map(str, margin_views(context)))} (not the bench's {config.view}) and revealed with "
             "onnxruntime: the smallest distance of any value from its rounding boundary in 8-bit levels, and whether "
             "the bundle reveals the same pixels when every output of its field is scaled by 1 ± a relative error. "
             "*Bare*: the same hide without the margin (the solver's margin_bins 0 and no promise), for its cost.", "",
             "| relative error | " + " | ".join(f"{r:g}" for r in RELATIVE_ERRORS) + " |",
             "|---|" + "---|" * len(RELATIVE_ERRORS),
             f"| bundles that survive (of {len(rows)}) | " + " | ".join(str(survived[r]) for r in RELATIVE_ERRORS) + " |",
             "", "| photo | view | exact | margin (levels) | hide's margin | bare margin | key ÷ bare | hide ÷ bare |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['photo']} | {r['view']} | {r['exact']} | {r['margin_levels']:.4f} | {r['hide_margin_levels']:.4f} | "
              f"{r['bare_margin_levels']:.4f} | {r['key_growth']:.3f} | {r['hide_time_ratio']:.2f} |" for r in rows]
    return lines
