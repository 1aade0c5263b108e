"""Keys against the secret's own coding: an exact (compact) bundle's bytes beside the same pixels saved as a
PNG by the project's image writer and as lossless WebP (a strong lossless coder), for photos at the bench's
view and at the cameras farthest from it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.images import load_secret, write_image
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, small_secret
from noisenerf.cli.bench.report import verdict

KEY_OVER_PNG_GOAL = 1.0  # median bundle bytes ÷ the secret's own PNG bytes
WORST_KEY_OVER_PNG_GOAL = 1.5  # and the worst photo and view
FAR_VIEWS = 2  # cameras besides the bench's, those whose viewing directions turn farthest from it


def far_views(cameras: tuple[Camera, ...], view: int, count: int) -> list[int]:
    """The `count` cameras whose viewing directions make the largest angles with camera `view`'s."""
    forward = np.array([camera.matrix()[:3, 2] for camera in cameras], dtype=np.float64)
    forward /= np.linalg.norm(forward, axis=1, keepdims=True)
    cosine = forward @ forward[view]
    return [int(i) for i in np.argsort(cosine, kind="stable")[:count] if i != view]


def lossless_webp_bytes(image: np.ndarray, path: Path) -> int | None:
    """The size of (h, w, 3) uint8 pixels as lossless WebP, None where this OpenImageIO writes none that reads
    back to the same pixels."""
    output = oiio.ImageOutput.create(str(path))
    if output is None:
        return None
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], 3, "uint8")
    spec.attribute("compression", "lossless")
    written = output.open(str(path), spec) and output.write_image(np.ascontiguousarray(image))
    output.close()
    source = oiio.ImageInput.open(str(path)) if written else None
    if source is None:
        return None
    back = source.read_image("uint8")
    source.close()
    return path.stat().st_size if back is not None and np.array_equal(back.reshape(image.shape), image) else None


def measure_keys(context: BenchContext) -> Measured:
    """Each photo (the bench secret without --photos), `view_width` wide, hidden at the bench's view and the
    FAR_VIEWS cameras farthest from it, and revealed with onnxruntime; its PNG and lossless WebP sizes."""
    config = context.config
    views = [config.view, *far_views(context.scene.config.cameras, config.view, FAR_VIEWS)]
    rows = []
    for path in config.photos or (config.secret,):
        photo = load_secret(path)[0]
        if config.view_width is not None:
            photo = small_secret(photo, config.view_width)
        pixels = photo.shape[0] * photo.shape[1]
        write_image(context.work / "key.png", photo)
        png = (context.work / "key.png").stat().st_size
        webp = lossless_webp_bytes(photo, context.work / "key.webp")
        for view in views:
            report, revealed, reveal_seconds = context.hide_and_reveal(photo, "key", HideConfig(view=view))
            rows.append({"secret": Path(path).name, "view": view, "pixels": pixels,
                         "bytes_per_pixel": report["bundle_bytes"] / pixels, "png_bytes_per_pixel": png / pixels,
                         "webp_bytes_per_pixel": None if webp is None else webp / pixels,
                         "over_png": report["bundle_bytes"] / png,
                         "over_webp": None if webp is None else report["bundle_bytes"] / webp,
                         "escaped": sum(tile.get("escaped", 0) for tile in report["tiles"]),
                         "hide_seconds": report["seconds"], "reveal_seconds": reveal_seconds,
                         "onnx_exact": revealed.exact})
    return Measured(rows)


def optional(value: float | None) -> str:
    return "—" if value is None else f"{value:.2f}"


def describe_keys(context: BenchContext, measured: Measured) -> list[str]:
    config, rows = context.config, measured.rows
    over_png = np.array([r["over_png"] for r in rows])
    median, worst = float(np.median(over_png)), float(over_png.max())
    webp = [r["over_webp"] for r in rows if r["over_webp"] is not None]
    lines = [f"{len({r['secret'] for r in rows})} photo(s) "
             f"({'native size' if config.view_width is None else f'{config.view_width} px wide'}) hidden with the "
             f"defaults at view {config.view} and at the {FAR_VIEWS} cameras facing farthest from it, revealed with "
             "onnxruntime. A key's bytes are the whole bundle's; PNG is the project's image writer at its default "
             "compression, WebP OpenImageIO's lossless WebP of the same pixels.", "",
             "| secret | view | key bytes/pixel | PNG bytes/pixel | WebP bytes/pixel | key ÷ PNG | key ÷ WebP | "
             "escaped | hide s | reveal s | exact |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['secret']} | {r['view']} | {r['bytes_per_pixel']:.2f} | {r['png_bytes_per_pixel']:.2f} | "
              f"{optional(r['webp_bytes_per_pixel'])} | {r['over_png']:.2f} | {optional(r['over_webp'])} | "
              f"{r['escaped']:,} | {r['hide_seconds']:.2f} | {r['reveal_seconds']:.2f} | "
              f"{str(r['onnx_exact']).lower()} |" for r in rows]
    lines += ["", f"Key ÷ PNG: median **{median:.2f}** (goal ≤ {KEY_OVER_PNG_GOAL}: "
              f"{verdict(median, KEY_OVER_PNG_GOAL, lower_is_better=True)}), worst **{worst:.2f}** (goal ≤ "
              f"{WORST_KEY_OVER_PNG_GOAL}: {verdict(worst, WORST_KEY_OVER_PNG_GOAL, lower_is_better=True)})"
              + (f"; key ÷ lossless WebP median {np.median(webp):.2f}" if webp else "; no lossless WebP writer here")
              + f"; hide ÷ reveal median {np.median([r['hide_seconds'] / r['reveal_seconds'] for r in rows]):.1f}; "
              f"all exact: **{str(all(r['onnx_exact'] for r in rows)).lower()}**."]
    return lines
