"""What a bundle shows without its model, masked (format 5) and as format 4 wrote it, and what the mask costs."""

from __future__ import annotations

import dataclasses
import lzma

import numpy as np
from safetensors.numpy import load

from noisenerf.runtime.api import reveal
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import load_secret
from noisenerf.train.hide.plan import HideConfig

from noisenerf.cli.bench.context import BenchContext, Measured, small_secret, timed


REPEATS = 7


def byte_entropy(data: bytes) -> float:
    """Shannon entropy of the bytes' histogram, bits per byte (8 for uniform bytes, less by about
    255 / (2 n ln 2) for n of them: the plug-in estimator's bias)."""
    counts = np.bincount(np.frombuffer(data, np.uint8), minlength=256)
    p = counts[counts > 0] / len(data)
    return float(-(p * np.log2(p)).sum())


def explained_variance(planes: np.ndarray, colours: np.ndarray) -> np.ndarray:
    """R² of the least-squares affine fit of each plane from the pixels' colours: planes (n, k), colours (n, 3)
    -> (k,) in [0, 1] (a constant plane: 0)."""
    design = np.concatenate([colours.astype(np.float64), np.ones((len(colours), 1))], axis=1)
    fitted = design @ np.linalg.lstsq(design, planes.astype(np.float64), rcond=None)[0]
    total = ((planes - planes.mean(axis=0)) ** 2).sum(axis=0)
    return np.where(total > 0, 1 - ((planes - fitted) ** 2).sum(axis=0) / np.maximum(total, 1e-300), 0.0)


def stored_bytes(data: bytes) -> bytes:
    """Every tensor's bytes as a bundle file stores them, in name order."""
    tensors = load(data)
    return b"".join(np.ascontiguousarray(tensors[name]).tobytes() for name in sorted(tensors))


def masked_planes(data: bytes, tile: int, pixels: int, k: int) -> np.ndarray:
    """What a reader without the model makes of a masked compact tile's stream: its bytes laid over the tile's pixels
    as k planes, row-major (the stream cannot be decompressed: it is not xz without the mask), -> (pixels, k)."""
    stream = np.frombuffer(np.ascontiguousarray(load(data)[f"tile_{tile:04d}"]).tobytes(), np.uint8)
    return np.resize(stream, pixels * k).reshape(pixels, k)


def measure_masking(context: BenchContext) -> Measured:
    """Each of the first masking_photos photos at masking_width, hidden at two views (the bench's and the one after):
    the masked bundle's stored bytes (entropy, what xz gains on them, its tile streams as planes against the secret's
    colours) against the same bundle unmasked as format 4 (its decoded coefficient planes against the colours), and
    the masked bundle's size and reveal time (the best of REPEATS) over the unmasked one's."""
    config, model = context.config, context.model
    rows = []
    for photo in config.photos[:config.masking_photos]:
        secret = small_secret(load_secret(photo)[0], config.masking_width)
        for view in (config.view, (config.view + 1) % len(model.cameras)):
            context.hide(secret, "masked", HideConfig(view=view))
            masked_path, plain_path = context.work / "masked.bundle", context.work / "plain.bundle"
            bundle = load_bundle(masked_path, model.mask_secret)
            plain_path.write_bytes(dataclasses.replace(bundle, mask_salt=None).to_bytes())
            masked, plain = masked_path.read_bytes(), plain_path.read_bytes()
            stored = stored_bytes(masked)
            r2_plain, r2_masked = [], []
            for i, tile in enumerate(bundle.tiles):
                x0, y0, width, height = tile.rect
                colours = secret[y0:y0 + height, x0:x0 + width].reshape(-1, 3)
                coefficients = tile.noise.coefficients().reshape(width * height, -1)
                r2_plain += explained_variance(coefficients, colours).tolist()
                r2_masked += explained_variance(masked_planes(masked, i, width * height, coefficients.shape[1]),
                                                colours).tolist()
            seconds = {"masked": [], "plain": []}  # each the best of REPEATS, taken in turn: a reveal takes ~0.1 s
            for _ in range(REPEATS):
                masked_reveal, took = timed(reveal, model, masked_path)
                seconds["masked"].append(took)
                plain_reveal, took = timed(reveal, model, plain_path)
                seconds["plain"].append(took)
            masked_seconds, plain_seconds = min(seconds["masked"]), min(seconds["plain"])
            rows.append({"photo": photo.rsplit("/", 1)[-1], "view": view, "stored_bytes": len(stored),
                         "entropy": byte_entropy(stored), "xz_gain": 1 - len(lzma.compress(stored, preset=9)) / len(stored),
                         "plain_r2_median": float(np.median(r2_plain)), "plain_r2_max": float(np.max(r2_plain)),
                         "masked_r2_max": float(np.max(r2_masked)), "size_ratio": len(masked) / len(plain),
                         "reveal_ratio": masked_seconds / plain_seconds,
                         "exact": masked_reveal.exact and plain_reveal.exact})
    return Measured(rows)


def describe_masking(context: BenchContext, measured: Measured) -> list[str]:
    rows = measured.rows
    lines = [f"The first {context.config.masking_photos} photos at {context.config.masking_width} px wide, hidden with "
             "the defaults at two views. *Masked*: the bundle as written (format 5); *plain*: the same bundle written "
             "unmasked (format 4), whose compact streams anyone can decompress. R²: how much of a coefficient plane's "
             "variance an affine function of the pixels' colours explains (plain: the decompressed planes; masked: the "
             "stored stream laid over the pixels, since it no longer decompresses). Entropy over all the masked "
             "bundle's stored tensor bytes (the estimator's bias for n bytes is about 255 / (2 n ln 2) bits).", "",
             "| photo | view | stored bytes | entropy bits/byte | xz gain | plain R² median | plain R² max | "
             "masked R² max | size masked ÷ plain | reveal masked ÷ plain | exact |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['photo']} | {r['view']} | {r['stored_bytes']:,} | {r['entropy']:.4f} | {r['xz_gain']:+.2%} | "
              f"{r['plain_r2_median']:.1%} | {r['plain_r2_max']:.1%} | {r['masked_r2_max']:.2%} | {r['size_ratio']:.4f} | "
              f"{r['reveal_ratio']:.3f} | {r['exact']} |" for r in rows]
    return lines
