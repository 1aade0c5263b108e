"""Interlaced prediction of a compact tile's coefficient planes (bundle format 4): each pixel's k coefficients
are stored as their difference from a prediction made of coefficients decoded before them, so a tile whose
neighbouring pixels' noise is alike stores small numbers, which xz codes in few bits.

Order, as Adam7 and multi-resolution coders go: first the roots, every ROOT_SPACING-th pixel of every
ROOT_SPACING-th row, each predicted by the root to its left (the first root of a row by the one above it, the very
first by 0); then for spacings s = 8, 4, 2 with d = s/2, a horizontal pass (rows y ≡ 0 mod s, columns x ≡ d mod
s: the floored mean of the two decoded pixels d to the left and right, or the left one alone at the right edge)
and a vertical pass (rows y ≡ d mod s, columns x ≡ 0 mod d: the floored mean of those d above and below, or the
one above at the bottom edge). Every pixel of a pass is predicted from earlier passes only, so a pass decodes
(and the hide solves it, train/hide/compact.predicted_choice) all at once.

A tile is coded in bands of `band_rows` whole rows (the last band what is left), each on its own as if it were
the whole image: a band is what one of the hide's parts solves, so each part chooses its coefficients
against predictions from its own pixels, in parallel with the others.

Differences wrap around the storage integer (int16 or int8), so every coefficient round-trips whatever its
prediction, and are zigzag-mapped (0, −1, 1, −2, … → 0, 1, 2, 3, …) so small differences of either sign have zero
high bytes. All integer arithmetic; web/src/interlaced.js computes the same numbers.
"""

from __future__ import annotations

from typing import Iterator

import numpy as np

ROOT_SPACING = 8
BITS = {np.dtype(np.int8): 8, np.dtype(np.int16): 16}


def passes(height: int, width: int) -> Iterator[tuple[np.ndarray, np.ndarray, str, int]]:
    """The passes of a (height, width) tile in decoding order: (rows (p,), columns (p,), kind, distance), kind
    "root", "across" or "down"; every pixel is in exactly one pass."""
    ys, xs = np.mgrid[0:height:ROOT_SPACING, 0:width:ROOT_SPACING]
    yield ys.ravel(), xs.ravel(), "root", ROOT_SPACING
    spacing = ROOT_SPACING
    while spacing > 1:
        d = spacing // 2
        ys, xs = np.mgrid[0:height:spacing, d:width:spacing]
        yield ys.ravel(), xs.ravel(), "across", d
        ys, xs = np.mgrid[d:height:spacing, 0:width:d]
        yield ys.ravel(), xs.ravel(), "down", d
        spacing = d


def predictions(decoded: np.ndarray, ys: np.ndarray, xs: np.ndarray, kind: str, d: int) -> np.ndarray:
    """The prediction of the pixels (ys, xs) of an "across" or "down" pass from `decoded` (h, w, k) int64, whose
    earlier passes are filled in. -> (p, k) int64."""
    height, width = decoded.shape[:2]
    if kind == "across":
        before = decoded[ys, xs - d]
        after = np.where((xs + d < width)[:, None], decoded[ys, np.minimum(xs + d, width - 1)], before)
    else:
        before = decoded[ys - d, xs]
        after = np.where((ys + d < height)[:, None], decoded[np.minimum(ys + d, height - 1), xs], before)
    return (before + after) >> 1


def root_predictions(roots: np.ndarray) -> np.ndarray:
    """Each root's prediction from the roots grid (r, c, k) int64: the one to its left, the first of a row the
    one above, the first 0. -> (r, c, k)."""
    predicted = np.zeros_like(roots)
    predicted[:, 1:] = roots[:, :-1]
    predicted[1:, 0] = roots[:-1, 0]
    return predicted


def wrapped(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Integers (...) int64 taken modulo the storage integer's range, as that dtype's two's complement reads them."""
    half = 1 << (BITS[np.dtype(dtype)] - 1)
    return ((values + half) & (2 * half - 1)) - half


def zigzag(values: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """Signed wrapped differences -> their zigzag codes, as the same-width signed dtype holds them."""
    bits = BITS[np.dtype(dtype)]
    return wrapped((values << 1) ^ (values >> (bits - 1)), dtype).astype(dtype)


def unzigzag(codes: np.ndarray) -> np.ndarray:
    """Zigzag codes (stored as a signed dtype) -> the signed differences, int64."""
    unsigned = codes.astype(np.int64) & ((1 << BITS[codes.dtype]) - 1)
    return (unsigned >> 1) ^ -(unsigned & 1)


def encode_band(values: np.ndarray) -> np.ndarray:
    """One band's coefficients (h, w, k) int64 -> their differences from the interlaced predictions, int64."""
    difference = np.empty_like(values)
    for ys, xs, kind, d in passes(*values.shape[:2]):
        if kind == "root":
            roots = values[::ROOT_SPACING, ::ROOT_SPACING]
            difference[::ROOT_SPACING, ::ROOT_SPACING] = roots - root_predictions(roots)
        else:
            difference[ys, xs] = values[ys, xs] - predictions(values, ys, xs, kind, d)
    return difference


def decode_band(difference: np.ndarray, dtype: np.dtype) -> np.ndarray:
    """encode_band's inverse, wrapped to the storage dtype: differences (h, w, k) int64 -> coefficients, int64."""
    decoded = np.zeros_like(difference)
    for ys, xs, kind, d in passes(*difference.shape[:2]):
        if kind == "root":  # each root is the running sum along its row from the first, itself down the column
            roots = difference[::ROOT_SPACING, ::ROOT_SPACING].copy()
            roots[:, 0] = np.cumsum(roots[:, 0], axis=0)
            decoded[::ROOT_SPACING, ::ROOT_SPACING] = wrapped(np.cumsum(roots, axis=1), dtype)
        else:
            decoded[ys, xs] = wrapped(predictions(decoded, ys, xs, kind, d) + difference[ys, xs], dtype)
    return decoded


def encode(coefficients: np.ndarray, band_rows: int) -> np.ndarray:
    """Coefficients (h, w, k) int16/int8, in bands of band_rows rows -> the zigzag codes of their differences from
    the interlaced predictions, same shape and dtype."""
    values = coefficients.astype(np.int64)
    difference = np.concatenate([encode_band(values[y:y + band_rows]) for y in range(0, len(values), band_rows)])
    return zigzag(wrapped(difference, coefficients.dtype), coefficients.dtype)


def decode(codes: np.ndarray, band_rows: int) -> np.ndarray:
    """encode's inverse: zigzag codes (h, w, k) int16/int8 in bands of band_rows rows -> the coefficients, same
    shape and dtype."""
    difference = unzigzag(codes)
    return np.concatenate([decode_band(difference[y:y + band_rows], codes.dtype)
                           for y in range(0, len(codes), band_rows)]).astype(codes.dtype)
