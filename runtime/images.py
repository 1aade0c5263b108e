"""Image files in and out (OpenImageIO), secret loading rules, and exact area-averaging resize.

Pixels are (H, W, C) arrays. Alpha is always STRAIGHT (unassociated) in memory: files that store straight
alpha (PNG, unassociated TIFF) are read with OpenImageIO's `oiio:UnassociatedAlpha` hint so it does not
premultiply them; files that store associated alpha (EXR, associated TIFF) are divided by alpha on read.
"""

from __future__ import annotations

import contextlib
import errno
import os
import sys
from pathlib import Path
from typing import NamedTuple

import numpy as np
import OpenImageIO as oiio

from noisenerf.runtime.errors import UserError, one_line
from noisenerf.runtime.files import atomic_output
from noisenerf.runtime.limits import checked_image_size

# extension -> (OpenImageIO format name, pixel type written)
WRITE_FORMATS = {
    ".png": ("png", "uint8"), ".jpg": ("jpeg", "uint8"), ".jpeg": ("jpeg", "uint8"),
    ".tif": ("tiff", "uint16"), ".tiff": ("tiff", "uint16"), ".exr": ("openexr", "float"),
}
JPEG_QUALITY = 95
SECRET_CHANNELS = {1: "grey", 2: "grey+alpha", 3: "RGB", 4: "RGBA"}
MAX_CHANNELS = 16  # channels decoded from any image (RGBA needs 4; more are refused before decoding)
# Formats whose alpha is straight by their own specification but whose OpenImageIO reader hands the stored values
# over without saying so (no oiio:UnassociatedAlpha): taken as stored. Others that say nothing (OpenEXR, Maya
# IFF, RLA, Softimage PIC, an associated TIFF) store associated alpha, which is made straight.
STRAIGHT_ALPHA_FORMATS = {"bmp", "ico", "sgi", "dpx", "gif", "webp", "jpegxl", "jpeg2000", "psd", "fits", "pnm",
                          "png", "targa"}


@contextlib.contextmanager
def c_stderr_silenced():
    """The C libraries under OpenImageIO (libpng, libjpeg, libtiff) print their own warnings and errors
    straight to file descriptor 2; OpenImageIO also hands us each error through geterror(), which we report
    as one line. So descriptor 2 points at /dev/null for the length of an OpenImageIO call."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def _open(path: str | os.PathLike) -> oiio.ImageInput:
    """An open ImageInput that leaves straight alpha straight, or one UserError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"image not found: {path}", code="image.not_found")
    if path.stat().st_size == 0:
        raise UserError(f"image file is empty: {path}", code="image.empty")
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    image = oiio.ImageInput.open(str(path), config)
    if image is None:
        raise UserError(f"cannot read image {path}: {one_line(oiio.geterror()) or 'unknown format'}",
                        code="image.unreadable")
    return image


@c_stderr_silenced()
def image_shape(path: str | os.PathLike) -> tuple[int, int, int]:
    """(height, width, channels) from the file header, without decoding pixels."""
    image = _open(path)
    spec = image.spec()
    image.close()
    if spec.width < 1 or spec.height < 1 or spec.nchannels < 1:
        raise UserError(f"image has no pixels: {path}", code="image.no_pixels")
    return spec.height, spec.width, spec.nchannels


def read_native(path: str | os.PathLike) -> np.ndarray:
    """Pixels as stored, (H, W, C): integers in their stored type, floats as float32; alpha straight and last.

    Associated alpha (EXR, an associated TIFF, IFF, RLA: see STRAIGHT_ALPHA_FORMATS) is converted to straight,
    which needs floats: such files come back as float32 in [0, 1] for integer storage.
    """
    return read_stored(path)[0]


@c_stderr_silenced()
def read_stored(path: str | os.PathLike) -> tuple[np.ndarray, np.dtype]:
    """read_native's pixels and the type the file stores them in (uint8, uint16, float16, float32, …)."""
    image = _open(path)
    spec = image.spec()
    try:
        # the header's claim, before decoding
        checked_image_size(spec.width, spec.height, f"image {path}", code="image.size")
        if not 1 <= spec.nchannels <= MAX_CHANNELS:
            raise UserError(f"image {path} has {spec.nchannels} channels; at most {MAX_CHANNELS} are read",
                            code="image.too_many_channels", channels=spec.nchannels, most=MAX_CHANNELS)
    except UserError:
        image.close()
        raise
    pixels = image.read_image(oiio.UNKNOWN)
    error, format_name = image.geterror(), image.format_name()
    image.close()
    if pixels is None or pixels.size == 0:
        raise UserError(f"cannot read image {path}: {one_line(error) or 'no pixels'}", code="image.unreadable")
    pixels, stored = pixels.reshape(spec.height, spec.width, spec.nchannels), pixels.dtype
    if pixels.dtype.kind == "f":
        pixels = pixels.astype(np.float32)
    alpha = alpha_channel(spec)
    if alpha is not None and alpha != spec.nchannels - 1:  # colour first, alpha last, as every reader here expects
        pixels = pixels[..., [*(c for c in range(spec.nchannels) if c != alpha), alpha]]
    straight = (alpha is None or spec.get_int_attribute("oiio:UnassociatedAlpha", 0) == 1
                or format_name in STRAIGHT_ALPHA_FORMATS)
    return (pixels if straight else unpremultiply(normalized(pixels), spec.nchannels - 1)), stored


def alpha_channel(spec: oiio.ImageSpec) -> int | None:
    """The index of an image's alpha channel, or None. OpenImageIO's `alpha_channel` where it names a channel of
    the image; its GIF reader states one past the last (4 of RGBA), so a channel named A or Alpha otherwise."""
    if 0 <= spec.alpha_channel < spec.nchannels:
        return spec.alpha_channel
    names = [name.lower() for name in spec.channelnames]
    return next((c for c, name in enumerate(names) if name in ("a", "alpha")), None)


def normalized(pixels: np.ndarray) -> np.ndarray:
    """Integer pixels to float32 in [0, 1] (value / max); float pixels unchanged. (H, W, C) -> (H, W, C)."""
    if np.issubdtype(pixels.dtype, np.integer):
        return pixels.astype(np.float32) / np.float32(np.iinfo(pixels.dtype).max)
    return pixels.astype(np.float32)


def unpremultiply(pixels: np.ndarray, alpha_channel: int) -> np.ndarray:
    """Associated to straight alpha; colour stays 0 where alpha is 0. (H, W, C) float32 -> same."""
    alpha = pixels[..., alpha_channel:alpha_channel + 1]
    scale = np.divide(1.0, alpha, out=np.zeros_like(alpha), where=alpha > 0)
    colour = np.arange(pixels.shape[-1]) != alpha_channel
    return np.where(colour, pixels * scale, pixels).astype(np.float32)


def read_image(path: str | os.PathLike) -> np.ndarray:
    """An image as (H, W, C) float32: [0, 1] for 8/16-bit files, raw values for float files; straight alpha."""
    return normalized(read_native(path))


def composite_over(pixels: np.ndarray, background) -> np.ndarray:
    """Straight-alpha colour over a constant background. (H, W, C+1) float -> (H, W, C) float32."""
    colour, alpha = pixels[..., :-1], pixels[..., -1:]
    return (colour * alpha + np.asarray(background, np.float32) * (1.0 - alpha)).astype(np.float32, copy=False)


class Secret(NamedTuple):
    """A secret image as hidden: its 8-bit pixels, warnings for the user, and the bits per channel its file held."""

    pixels: np.ndarray  # (H, W, 3) uint8
    warnings: list[str]
    bits: int  # 8, 16 or 32 (float): more than 8 means the hidden secret is the file's 8-bit quantisation


def precision_note(bits: int) -> str:
    """What a hide reports of the precision it kept, for a secret file of `bits` per channel."""
    return "8-bit" if bits == 8 else f"8-bit (secret had {bits})"


def load_secret(path: str | os.PathLike) -> Secret:
    """The secret image as (H, W, 3) uint8, plus human-readable warnings and the file's bits per channel.

    Rules:
    - PNG, JPEG, TIFF or EXR (anything OpenImageIO reads), 8-bit, 16-bit or float.
    - grey -> RGB by repeating the channel; grey+alpha and RGBA are composited over white (straight alpha).
    - 8-bit grey/RGB pass through bit-exactly; other values are quantised with `to_uint8` (round half up),
      16-bit as value / 65535. A file of more than 8 bits per channel is hidden as its 8-bit quantisation,
      with a warning that says so (the low bits are not kept: `exact` is about the 8-bit values).
    - float values outside [0, 1] are clipped, with a warning; NaN is refused.
    - a missing, empty or unreadable file, or a channel count other than 1–4, is a UserError naming the file.
    """
    pixels, stored = read_stored(path)
    channels = pixels.shape[-1]
    if channels not in SECRET_CHANNELS:
        raise UserError(f"secret image {path} has {channels} channels; expected {', '.join(SECRET_CHANNELS.values())}",
                        code="image.secret_channels", channels=channels)
    if pixels.dtype == np.uint8 and channels in (1, 3):
        return Secret(np.ascontiguousarray(np.broadcast_to(pixels, pixels.shape[:2] + (3,))), [], 8)
    values = normalized(pixels)
    if np.isnan(values).any():
        raise UserError(f"secret image {path} contains NaN values", code="image.nan")
    bits = 8 * stored.itemsize
    kind = "float" if stored.kind == "f" else f"{bits}-bit"
    warnings = [] if bits == 8 else [f"{path} has {kind} channels; it is hidden as 8 bits per channel (the "
                                     f"finer values are not kept, and `exact` is about the 8-bit values)"]
    outside = np.count_nonzero((values < 0) | (values > 1))
    if outside:
        warnings.append(f"{path}: {outside} values outside [0, 1] clipped")
        values = np.clip(values, 0.0, 1.0)
    if channels in (2, 4):
        values = composite_over(values, 1.0)
    return Secret(to_uint8(np.broadcast_to(values, values.shape[:2] + (3,))), warnings, bits)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """[0, 1] floats to 8-bit by rounding half up: value k covers [(k − ½)/255, (k + ½)/255)."""
    return np.clip(np.floor(np.asarray(image, np.float32) * 255.0 + 0.5), 0, 255).astype(np.uint8)


def encoded(image: np.ndarray, pixel_type: str) -> np.ndarray:
    """(H, W, C) uint8 or float in [0, 1] -> pixels of the written type: uint8, uint16 or float32."""
    if image.dtype == np.uint8 and pixel_type == "uint8":
        return image
    values = normalized(image)
    if pixel_type == "uint8":
        return to_uint8(values)
    if pixel_type == "uint16":
        return np.floor(np.clip(values, 0.0, 1.0) * 65535.0 + 0.5).astype(np.uint16)
    return values


def written_format(path: Path) -> tuple[str, str]:
    """(OpenImageIO format, pixel type) an image path is written in, by its extension (none: PNG)."""
    suffix = path.suffix.lower() or ".png"
    if suffix not in WRITE_FORMATS:
        raise UserError(f"unknown image extension {path.suffix!r} for {path}; use one of {', '.join(WRITE_FORMATS)}",
                        code="image.unknown_extension")
    return WRITE_FORMATS[suffix]


@c_stderr_silenced()
def write_image(path: str | os.PathLike, image: np.ndarray, replace: bool = True) -> None:
    """Write (H, W, 3) RGB or (H, W, 4) straight RGBA, uint8 or float in [0, 1], atomically; the file is read
    back before it is published (OpenImageIO does not always report a write the disk refused), so what
    lands at `path` holds exactly these pixels (JPEG: this size). replace: see files.atomic_output.

    By extension: .png (also for a path without extension) and .jpg/.jpeg (quality 95, alpha dropped)
    8-bit, floats via `to_uint8`; .tif/.tiff 16-bit (round half up of v·65535, 8-bit as v·257); .exr 32-bit
    float (exact values, alpha premultiplied as EXR requires). A missing folder or unknown extension is a
    UserError.
    """
    path = Path(path)
    format_name, pixel_type = written_format(path)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[-1] not in (3, 4) or not (image.dtype == np.uint8 or image.dtype.kind == "f"):
        raise ValueError(f"write_image needs (H, W, 3|4) uint8 or float pixels, got {image.shape} {image.dtype}")
    pixels = encoded(image, pixel_type)
    spec = oiio.ImageSpec(image.shape[1], image.shape[0], image.shape[2], pixel_type)
    if image.shape[-1] == 4 and format_name == "openexr":
        pixels = np.concatenate([pixels[..., :3] * pixels[..., 3:], pixels[..., 3:]], axis=-1)
    elif image.shape[-1] == 4:
        spec.attribute("oiio:UnassociatedAlpha", 1)  # else OpenImageIO would divide by alpha on write
    if format_name == "jpeg":
        spec.attribute("Compression", f"jpeg:{JPEG_QUALITY}")
    pixels = np.ascontiguousarray(pixels)
    with atomic_output(path, replace=replace) as tmp:
        output = oiio.ImageOutput.create(format_name)
        # write_image after a failed open crashes the interpreter, so check open first
        if not output.open(str(tmp), spec):
            raise written_failure(path, output.geterror())
        written = output.write_image(pixels)
        error = output.geterror()
        closed = output.close()
        if not written or not closed:
            raise written_failure(path, error or output.geterror())
        check_written(tmp, path, pixels, lossless=format_name != "jpeg")


def written_failure(path: Path, error: str) -> Exception:
    """What a failed OpenImageIO write is: a full file system (an OSError, which atomic_output words) when the
    folder has no room left, since the libraries' own messages do not say so; else their message."""
    if os.statvfs(path.parent).f_bavail == 0:
        return OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
    return UserError(f"cannot write image {path}: {one_line(error)}", code="image.write_failed")


def check_written(tmp: Path, path: Path, pixels: np.ndarray, lossless: bool) -> None:
    """Refuse a written image that does not read back as `pixels` (a lossy one: as their size). A disk that
    filled can leave a short file behind a write OpenImageIO reported as done."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # as written: straight alpha stays straight
    image = oiio.ImageInput.open(str(tmp), config)
    stored = None if image is None else image.read_image("float" if pixels.dtype.kind == "f" else str(pixels.dtype))
    error = oiio.geterror() if image is None else image.geterror()  # read, so none is left pending at exit
    if image is not None:
        image.close()
    intact = stored is not None and stored.size == pixels.size and (
        not lossless or np.array_equal(stored.reshape(pixels.shape), pixels))
    if not intact:
        raise written_failure(path, f"the file written does not read back as the image ({error or 'other pixels'})")


def area_weights(n_in: int, n_out: int) -> np.ndarray:
    """Row i averages input pixels over the footprint [i, i + 1)·n_in/n_out by overlap. -> (n_out, n_in)."""
    scale = n_in / n_out
    starts = np.arange(n_out)[:, None] * scale
    pixel = np.arange(n_in)[None, :]
    overlap = np.minimum(starts + scale, pixel + 1) - np.maximum(starts, pixel)
    return (np.clip(overlap, 0.0, None) / scale).astype(np.float32)


def resize_image(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """Area-averaging (box) resize: each output pixel is the mean of the input area it covers, weighted by
    overlap (exact block means for integer factors, like cv2's INTER_AREA). Numpy, separable.
    (H, W, C) float32 -> (height, width, C) float32.
    """
    if width < 1 or height < 1:
        raise ValueError(f"resize to {width}x{height}")
    rows = np.tensordot(area_weights(image.shape[0], height), image.astype(np.float32), axes=(1, 0))
    return np.tensordot(rows, area_weights(image.shape[1], width), axes=(1, 1)).transpose(0, 2, 1).copy()
