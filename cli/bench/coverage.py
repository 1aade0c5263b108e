"""Coverage: the exact method on secrets built to be hard, at every camera the scene knows.

The bench's photos and views are where the solver was tuned; exactness holds only if it also holds on
colours a sigmoid reaches last (0 and 255 in every channel, the background and its neighbours, fully
saturated primaries), on one-pixel 0/255 checkerboards and random bytes (no neighbour warm-starts
another), and on photos with blown highlights and crushed shadows, at every camera, revealed through
onnxruntime. The test suite runs a small version of the same sweep (tests/test_coverage.py).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret, to_uint8
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, resized
from noisenerf.cli.bench.report import verdict

PRIMARIES = np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 0], [0, 255, 255], [255, 0, 255],
                      [0, 0, 0], [255, 255, 255]], np.uint8)  # fully saturated primaries and secondaries, black, white


def clipped(photo: np.ndarray, gain: float = 3.0) -> np.ndarray:
    """A photo with blown highlights and crushed shadows: contrast × gain about mid-grey, clipped.
    (h, w, 3) uint8 -> (h, w, 3) uint8."""
    return np.clip((photo.astype(np.float32) - 127.5) * gain + 127.5, 0, 255).round().astype(np.uint8)


def smooth_photo(size: int, seed: int) -> np.ndarray:
    """A photo-like stand-in where no photo is given: smooth colour gradients and a few soft blobs."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / max(1, size - 1)
    image = np.stack([x, y, 1 - x * y], -1)
    for cx, cy, colour in zip(rng.random(4), rng.random(4), rng.random((4, 3))):
        image += colour * np.exp(-((x - cx) ** 2 + (y - cy) ** 2) * 20)[..., None]
    return to_uint8(image / image.max())


def hard_secrets(size: int, background: tuple[float, float, float], photo: np.ndarray | None = None,
                 seed: int = 0) -> dict[str, np.ndarray]:
    """Secrets (size, size, 3) uint8 built to be hard for the exact method: pure black and white, the
    scene's background colour and ±1 of it, saturated primaries in stripes, near-white and near-saturated
    noise, a one-pixel 0/255 checkerboard, uniform random bytes, and a clipped photo (`photo`, resized, or
    a smooth stand-in)."""
    rng = np.random.default_rng(seed)
    shape = (size, size, 3)
    back = to_uint8(np.asarray(background, np.float32))
    checker = ((np.add.outer(np.arange(size), np.arange(size)) % 2) * 255).astype(np.uint8)
    extremes = np.concatenate([np.arange(0, 6), np.arange(250, 256)]).astype(np.uint8)
    source = smooth_photo(size, seed) if photo is None else resized(photo, size, size)
    return {
        "black": np.zeros(shape, np.uint8),
        "white": np.full(shape, 255, np.uint8),
        "background": np.broadcast_to(back, shape).copy(),
        "background±1": np.clip(back.astype(np.int16) + rng.integers(-1, 2, shape), 0, 255).astype(np.uint8),
        "primaries": PRIMARIES[np.arange(size) * len(PRIMARIES) // size][None].repeat(size, 0),
        "near white": rng.integers(245, 256, shape, dtype=np.uint8),
        "near saturated": rng.choice(extremes, shape),
        "checkerboard": np.repeat(checker[..., None], 3, -1),
        "random bytes": rng.integers(0, 256, shape, dtype=np.uint8),
        "clipped photo": clipped(source),
    }


@dataclass(frozen=True)
class CoverageRow:
    """One secret hidden at one camera, revealed through onnxruntime."""

    scene: str
    secret: str
    view: int
    pixels: int
    exact_pixels: int  # pixels whose every 8-bit value the reveal recovered
    escaped: int
    worst_iterations: int
    hide_us_per_pixel: float


def sweep(context: BenchContext, secrets: dict[str, np.ndarray], views: range, scene_name: str) -> list[dict]:
    """Every secret hidden at every view (allowing inexact bundles, so that a miss is counted, not raised)
    and revealed with the bench's onnxruntime model."""
    rows = []
    for view in views:
        for name, secret in secrets.items():
            started = time.perf_counter()
            report = context.hide(secret, "coverage", HideConfig(view=view, seed=context.config.seed))
            seconds = time.perf_counter() - started
            revealed = reveal_tiles(load_bundle(context.work / "coverage.bundle", context.model.mask_secret), context.model.render_config,
                              context.model.fields())
            exact = int((revealed.pixels == secret).all(-1).sum())
            rows.append(vars(CoverageRow(
                scene_name, name, view, secret.shape[0] * secret.shape[1], exact,
                sum(t.get("escaped", 0) for t in report["tiles"]), max(t["iterations"] for t in report["tiles"]),
                seconds * 1e6 / secret[..., 0].size)))
    return rows


def measure_coverage(context: BenchContext) -> Measured:
    """The hard secrets at every camera of the bench scene."""
    photo = load_secret(context.config.photos[0])[0] if context.config.photos else None
    secrets = hard_secrets(context.config.coverage_size, context.scene.config.render.background, photo,
                           context.config.seed)
    return Measured(sweep(context, secrets, range(len(context.scene.config.cameras)), context.config.scene))


def describe_coverage(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    by_secret: dict[str, list[dict]] = {}
    for row in rows:
        by_secret.setdefault(row["secret"], []).append(row)
    size = context.config.coverage_size
    lines = [f"Each secret is {size}×{size} px, hidden at every one of the scene's {len(context.scene.config.cameras)} "
             "cameras with the defaults and revealed through onnxruntime.", "",
             "| secret | views | exact pixels | views not exact | escaped | worst iterations | hide µs/px median |",
             "|---|---|---|---|---|---|---|"]
    for name, group in by_secret.items():
        exact, pixels = sum(r["exact_pixels"] for r in group), sum(r["pixels"] for r in group)
        lines.append(f"| {name} | {len(group)} | {exact:,} / {pixels:,} | "
                     f"{sum(r['exact_pixels'] < r['pixels'] for r in group)} | {sum(r['escaped'] for r in group):,} | "
                     f"{max(r['worst_iterations'] for r in group)} | "
                     f"{np.median([r['hide_us_per_pixel'] for r in group]):.0f} |")
    missed = [r for r in rows if r["exact_pixels"] < r["pixels"]]
    total, exact = sum(r["pixels"] for r in rows), sum(r["exact_pixels"] for r in rows)
    places = ", ".join(f"{r['secret']} at view {r['view']}" for r in missed[:5])
    where = f" (missed: {places})" if missed else ""
    lines += ["", f"Goal: every pixel exact at every camera: {exact:,} of {total:,}{where}: "
                  f"**{verdict(exact, total, lower_is_better=False)}**."]
    return lines
