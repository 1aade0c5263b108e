"""Caps on every number a file may dictate, and the checks that enforce them before anything is allocated.

A bundle or model arrives from someone else: a size it claims must never decide how much memory or time a
reveal spends beyond what the file itself holds. So every count read from JSON metadata must be a true
integer (not a bool, not 2.5, not 1e300, not Infinity) inside one of these documented caps, and every
real number must be finite. The caps are far above anything noisenerf writes itself.
"""

from __future__ import annotations

import math

from noisenerf.runtime.errors import UserError

MAX_IMAGE_SIDE = 16384  # px: width or height of a secret, tile or camera
MAX_IMAGE_PIXELS = 8192 * 8192  # px: width × height of a secret or rendered camera (8K; a reveal holds it as 8-bit RGB, 192 MiB)
MAX_PAYLOAD_PIXELS = 4096 * 4096  # px: a payload's secret (48 MiB; its bytes are held several times over: record, cipher, pixels)
MAX_SAMPLES_PER_RAY = 1024  # samples per ray of any render (nerf-pytorch uses 64 + 128)
MAX_RAY_LAYOUT_SAMPLES = 256  # ray layout: one stored vector serves this many samples at most
MAX_COMPACT_COEFFICIENTS = 8  # compact layout: coefficients per pixel (int16: 16 bytes a pixel decompressed)
MAX_XZ_MEMORY = 80 << 20  # bytes an xz decoder may use: a preset-9 stream's 64 MiB dictionary, not the next size a
#   stream can state (96 MiB), which the browser's decoder (64 MiB at most) refuses too
MAX_XZ_RATIO = 64  # bytes an xz coefficient stream may state per byte it is: solved noise coefficients are nearly
#   random and compress a few times at most, a crafted stream of zeros thousands of times (docs/usage.md: the measured ratios)
FREE_XZ_BYTES = 1 << 20  # bytes any bundle may decompress, whatever its streams' size
MAX_TILES = MAX_IMAGE_PIXELS // 16 ** 2  # tiles in one bundle: the largest secret in the smallest (16 px) tiles
MAX_NOISE_DIMS = 4096  # width of the noise input (positional encodings use 90)
MAX_FIELD_DEPTH = 64  # layers of a model's trunk (NeRF's is 8)
MAX_FIELD_WIDTH = 4096  # units a layer (NeRF's 256)
MAX_FREQUENCIES = 32  # positional-encoding frequencies (NeRF's 10 and 4); 2^31 is float32's last exact doubling
MAX_HASH_LEVELS = 32  # levels of a hash-grid field (Instant-NGP's 16)
MAX_HASH_FEATURES = 8  # features per level (Instant-NGP's 2)
MAX_LOG2_TABLE = 24  # rows of one level's table, log2 (Instant-NGP's 19)
MAX_TABLE_VALUES = 1 << 28  # float32 values in one hash grid's tables together (1 GiB)
MAX_PROPOSAL_NETWORKS = 4  # density networks placing an ordinary render's samples (nerfacto's 2)
MAX_HASH_RESOLUTION = 1 << 20  # vertices per side of a hash grid's finest level: corner × prime stays in int64
MAX_GRID_RESOLUTION = 512  # cells per side of a model's occupancy grid (128 Mi cells)
MAX_CAMERAS = 100_000  # dataset cameras listed in a model or scene
MAX_JSON_DEPTH = 32  # nesting of any JSON metadata (ours is at most 5 deep)
MAX_HEADER_BYTES = 100_000_000  # a bundle's safetensors header (the safetensors library's own cap; ours are KBs)
MAX_MODEL_FIELDS = 1 << 18  # protobuf fields a model's parse walks in all (a nerfacto model has about 1300)


def is_finite(number) -> bool:
    """Whether an int or float is a finite float (an integer of hundreds of digits is not)."""
    try:
        return math.isfinite(number)
    except OverflowError:
        return False


def finite_params(**numbers) -> dict:
    """These numbers as a refusal's params, those that are not finite floats left out (JSON has no Infinity)."""
    return {name: number for name, number in numbers.items() if is_finite(number)}


def checked_int(value, what: str, low: int, high: int, code: str | None = None, **params) -> int:
    """`value` as an int in [low, high]: JSON integers only, so 2.5, 16.0, 1e300, true and Infinity are
    refused rather than truncated or overflowed. code (and params): the refusal's, the field's own (the
    runtime's callers name one; the sender's half refuses with a message only)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise UserError(f"{what} must be an integer, got {value!r:.40}", code=code, **finite_params(low=low, high=high),
                        **params)
    if not low <= value <= high:
        raise UserError(f"{what} must be between {low} and {high}, got {approximately(value)}", code=code,
                        **finite_params(value=value, low=low, high=high), **params)
    return value


def approximately(value: int) -> str:
    """An integer as format(value, ".6g") prints it, and one past a float's range (a JSON integer of hundreds
    of digits) in the same form from its digits, where .6g would overflow."""
    try:
        return f"{value:.6g}"
    except OverflowError:
        digits = str(abs(value))
        return f"{'-' if value < 0 else ''}{digits[0]}.{digits[1:6]}e+{len(digits) - 1}"


def checked_float(value, what: str, low: float = -math.inf, high: float = math.inf, code: str | None = None,
                  **params) -> float:
    """`value` as a finite float in [low, high]; NaN, Infinity, strings and bools are refused. code (and
    params): as checked_int's; a value or bound that is not finite is left out of the params."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{what} must be a number, got {value!r:.40}", code=code,
                        **finite_params(low=low, high=high), **params)
    if not is_finite(value) or not low <= float(value) <= high:
        raise UserError(f"{what} must be a finite number in [{low}, {high}], got {value!r:.40}", code=code,
                        **finite_params(value=value, low=low, high=high), **params)
    return float(value)


def checked_list(value, what: str, length: int | None = None, most: int = MAX_CAMERAS, code: str | None = None,
                 **params) -> list:
    """`value` as a JSON list of `length` items (or at most `most`). code (and params): as checked_int's."""
    if not isinstance(value, list):
        raise UserError(f"{what} must be a list, got {type(value).__name__}", code=code, **params)
    if (length is not None and len(value) != length) or len(value) > most:
        raise UserError(f"{what} must hold {length if length is not None else f'at most {most}'} items, "
                        f"got {len(value)}", code=code, count=len(value),
                        **({"length": length} if length is not None else {"most": most}), **params)
    return value


def checked_image_size(width, height, what: str, code: str | None = None, **params) -> tuple[int, int]:
    """(width, height) of an image or camera within MAX_IMAGE_SIDE and MAX_IMAGE_PIXELS. code (and params): as
    checked_int's, for each side (side: "width" or "height") and for the pixels together."""
    width = checked_int(width, f"{what} width", 1, MAX_IMAGE_SIDE, code, side="width", **params)
    height = checked_int(height, f"{what} height", 1, MAX_IMAGE_SIDE, code, side="height", **params)
    if width * height > MAX_IMAGE_PIXELS:
        raise UserError(f"{what} is {width}x{height}, more than the {MAX_IMAGE_PIXELS} pixels noisenerf renders",
                        code=code, width=width, height=height, most=MAX_IMAGE_PIXELS, **params)
    return width, height


def checked_expansion(packed: int, stated: int, what: str) -> None:
    """Refuse compressed streams of `packed` bytes stated to hold `stated` bytes beyond MAX_XZ_RATIO (and
    FREE_XZ_BYTES): a reveal's decoding and rendering then follow the size of the file, not what it claims."""
    if stated > max(FREE_XZ_BYTES, MAX_XZ_RATIO * packed):
        raise UserError(f"{what}: {packed} bytes of compressed coefficients cannot hold the {stated} bytes the tiles "
                        f"state (at most {MAX_XZ_RATIO} times their size)", code="compact.xz_ratio", packed=packed,
                        stated=stated, ratio=MAX_XZ_RATIO)


def json_depth(data) -> int:
    """Nesting depth of parsed JSON (a scalar is 0), walked iteratively so no input can overflow the stack."""
    deepest, stack = 0, [(data, 0)]
    while stack:
        item, depth = stack.pop()
        deepest = max(deepest, depth)
        children = item.values() if isinstance(item, dict) else item if isinstance(item, list) else ()
        stack.extend((child, depth + 1) for child in children)
    return deepest
