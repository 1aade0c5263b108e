"""Image I/O: straight alpha, bit-exact 8-bit, 16-bit and float conversion, secret rules, atomic writes, resize."""

from __future__ import annotations

import itertools
import types

import numpy as np
import OpenImageIO as oiio
import pytest

from helpers import assert_refused, read_raw, run_main, run_reveal, write_raw
from noisenerf.cli.bench.reliability import indexed_png
from noisenerf.cli.main import main as noisenerf_main
from noisenerf.runtime import images
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import image_shape, load_secret, read_image, resize_image, write_image


# ---- reading -------------------------------------------------------------------------------------

@pytest.mark.parametrize("name, dtype", [("half.png", np.uint8), ("half.tif", np.uint16)])
def test_straight_alpha_reads_back_straight(tmp_path, name, dtype):
    top = np.iinfo(dtype).max
    pixels = np.array([[[top, top, top, top // 2 + 1]]], dtype)
    path = write_raw(tmp_path / name, pixels, dtype.__name__, unassociated=True)
    image = read_image(path)
    assert image.dtype == np.float32 and image.shape == (1, 1, 4)
    np.testing.assert_array_equal(image[0, 0], [1.0, 1.0, 1.0, np.float32(top // 2 + 1) / np.float32(top)])
    # OpenImageIO's default would have premultiplied: the pixel above does catch that
    default = oiio.ImageInput.open(str(path))
    assert default.read_image("float")[0, 0, 0] == pytest.approx(0.5, abs=0.01)
    default.close()


def test_exr_associated_alpha_is_made_straight(tmp_path):
    pixels = np.array([[[0.25, 0.1, 0.0, 0.5], [0.0, 0.0, 0.0, 0.0]]], np.float32)  # premultiplied, as EXR is
    image = read_image(write_raw(tmp_path / "a.exr", pixels, "float"))
    np.testing.assert_allclose(image[0, 0], [0.5, 0.2, 0.0, 0.5], rtol=1e-6)
    np.testing.assert_array_equal(image[0, 1], [0.0, 0.0, 0.0, 0.0])


def test_16_bit_reads_as_unit_range_and_float_raw(tmp_path):
    values = np.array([[[0], [32768], [65535]]], np.uint16)
    image = read_image(write_raw(tmp_path / "a.tif", values, "uint16"))
    np.testing.assert_allclose(image.ravel(), [0.0, 32768 / 65535, 1.0], rtol=1e-7)
    raw = read_image(write_raw(tmp_path / "b.exr", np.array([[[-2.0, 7.5, 0.25]]], np.float32), "float"))
    np.testing.assert_array_equal(raw.ravel(), [-2.0, 7.5, 0.25])
    assert image_shape(tmp_path / "a.tif") == (1, 3, 1)


# ---- secrets -------------------------------------------------------------------------------------

def test_8_bit_secret_passes_through_bit_exactly(tmp_path):
    pixels = np.random.default_rng(0).permutation(np.arange(256 * 3, dtype=np.int64) % 256).astype(np.uint8)
    pixels = pixels.reshape(16, 16, 3)
    secret, warnings, _ = load_secret(write_raw(tmp_path / "s.png", pixels, "uint8"))
    np.testing.assert_array_equal(secret, pixels)
    assert secret.dtype == np.uint8 and warnings == []
    grey, _, _ = load_secret(write_raw(tmp_path / "g.png", pixels[..., :1], "uint8"))
    np.testing.assert_array_equal(grey, np.repeat(pixels[..., :1], 3, axis=-1))


def test_16_bit_secret_rounds_half_up(tmp_path):
    values = np.array([[[0, 128 * 257, 32767, 32768, 65535]]], np.uint16).reshape(1, 5, 1)
    secret, _, _ = load_secret(write_raw(tmp_path / "s.tif", np.repeat(values, 3, axis=-1), "uint16"))
    # 32767 / 65535 · 255 = 127.498, 32768 / 65535 · 255 = 127.502
    np.testing.assert_array_equal(secret[0, :, 0], [0, 128, 127, 128, 255])


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_16_bit_secrets_say_their_low_bits_are_not_kept(tmp_path, channels):
    """RGB, grey and RGBA 16-bit PNGs: the 8-bit quantisation is hidden, and the warning and bits say so."""
    values = np.random.default_rng(channels).integers(0, 65536, (4, 5, channels), dtype=np.uint16)
    values[..., channels - 1] |= 1 if channels != 4 else 0xFFFF  # opaque alpha; odd values lose bits
    secret, warnings, bits = load_secret(write_raw(tmp_path / "s.png", values, "uint16", unassociated=True))
    assert bits == 16 and len(warnings) == 1
    assert warnings[0].endswith("has 16-bit channels; it is hidden as 8 bits per channel (the finer values are "
                                "not kept, and `exact` is about the 8-bit values)")
    colour = values[..., :3] if channels != 1 else np.repeat(values, 3, axis=-1)
    scaled = colour.astype(np.float32) / np.float32(65535) * np.float32(255) + np.float32(0.5)
    np.testing.assert_array_equal(secret, np.floor(scaled).astype(np.uint8))


def test_alpha_secrets_are_composited_over_white(tmp_path):
    rgba = np.array([[[255, 0, 0, 128], [10, 20, 30, 0], [10, 20, 30, 255]]], np.uint8)
    secret, _, _ = load_secret(write_raw(tmp_path / "rgba.png", rgba, "uint8", unassociated=True))
    np.testing.assert_array_equal(secret[0], [[255, 127, 127], [255, 255, 255], [10, 20, 30]])
    grey_alpha = np.array([[[0, 51]]], np.uint8)  # black at 20 % over white: 0.8 · 255
    secret, _, _ = load_secret(write_raw(tmp_path / "ya.png", grey_alpha, "uint8", unassociated=True))
    np.testing.assert_array_equal(secret[0, 0], [204, 204, 204])


def test_float_secret_is_clipped_with_a_warning(tmp_path):
    pixels = np.array([[[-0.5, 1.5, 0.5]]], np.float32)
    secret, warnings, _ = load_secret(write_raw(tmp_path / "s.exr", pixels, "float"))
    np.testing.assert_array_equal(secret[0, 0], [0, 255, 128])
    assert len(warnings) == 2 and "has float channels; it is hidden as 8 bits" in warnings[0]
    assert "2 values outside [0, 1] clipped" in warnings[1]


@pytest.mark.parametrize("name, content, message", [
    ("missing.png", None, "image not found: .*missing.png"),
    ("empty.png", b"", "image file is empty: .*empty.png"),
    ("garbage.png", b"not an image at all", "cannot read image .*garbage.png"),
])
def test_unreadable_secrets_are_user_errors(tmp_path, name, content, message):
    if content is not None:
        (tmp_path / name).write_bytes(content)
    with pytest.raises(UserError, match=message):
        load_secret(tmp_path / name)


def test_five_channel_secret_is_refused(tmp_path):
    path = write_raw(tmp_path / "five.tif", np.zeros((2, 2, 5), np.uint8), "uint8")
    with pytest.raises(UserError, match="five.tif has 5 channels"):
        load_secret(path)


# ---- writing -------------------------------------------------------------------------------------

def test_write_png_uint8_exact_and_float_rounded_half_up(tmp_path):
    pixels = np.arange(48, dtype=np.uint8).reshape(4, 4, 3) * 5
    write_image(tmp_path / "a.png", pixels)
    np.testing.assert_array_equal(read_raw(tmp_path / "a.png"), pixels)
    write_image(tmp_path / "b.png", np.array([[[0.5, 1.0 / 510.0, 1.2]]], np.float32))
    np.testing.assert_array_equal(read_raw(tmp_path / "b.png")[0, 0], [128, 1, 255])
    write_image(tmp_path / "no_extension", pixels)
    assert (tmp_path / "no_extension").read_bytes()[1:4] == b"PNG"


def test_write_tiff_16_bit_and_exr_float(tmp_path):
    write_image(tmp_path / "a.tif", np.array([[[0, 1, 255]]], np.uint8))
    np.testing.assert_array_equal(read_raw(tmp_path / "a.tif")[0, 0], [0, 257, 65535])
    write_image(tmp_path / "b.tiff", np.array([[[0.5, 0.25, 1.0]]], np.float32))
    np.testing.assert_array_equal(read_raw(tmp_path / "b.tiff")[0, 0], [32768, 16384, 65535])
    values = np.array([[[0.123456, 0.5, 0.987654]]], np.float32)
    write_image(tmp_path / "c.exr", values)
    stored = read_raw(tmp_path / "c.exr")
    assert stored.dtype == np.float32
    np.testing.assert_array_equal(stored, values)


def test_rgba_round_trips_with_straight_alpha(tmp_path):
    rgba = np.array([[[200, 100, 50, 64], [1, 2, 3, 255]]], np.uint8)
    write_image(tmp_path / "a.png", rgba)
    np.testing.assert_array_equal(read_raw(tmp_path / "a.png"), rgba)


def test_write_refuses_unknown_extension_and_missing_folder(tmp_path):
    image = np.zeros((2, 2, 3), np.uint8)
    with pytest.raises(UserError, match="unknown image extension '.bmpx'"):
        write_image(tmp_path / "a.bmpx", image)
    with pytest.raises(UserError, match="output folder does not exist"):
        write_image(tmp_path / "nowhere" / "a.png", image)


class FailingOutput:
    """An ImageOutput that starts the file, then fails mid-write as a full disk would."""

    def open(self, path, spec):
        with open(path, "wb") as file:
            file.write(b"partial")
        return True

    def write_image(self, pixels):
        return False

    def geterror(self):
        return "No space left on device"

    def close(self):
        pass


def test_failed_write_leaves_no_partial_file(tmp_path, monkeypatch):
    target = tmp_path / "keep.png"
    target.write_bytes(b"previous")
    fake = types.SimpleNamespace(ImageSpec=oiio.ImageSpec,
                                 ImageOutput=types.SimpleNamespace(create=lambda name: FailingOutput()))
    monkeypatch.setattr(images, "oiio", fake)
    with pytest.raises(UserError, match="cannot write image .*keep.png: No space left on device"):
        write_image(target, np.zeros((2, 2, 3), np.uint8))
    assert target.read_bytes() == b"previous"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.png"]


# ---- resize --------------------------------------------------------------------------------------

def test_resize_integer_factor_is_block_mean():
    image = np.random.default_rng(1).random((8, 12, 2), dtype=np.float32)
    small = resize_image(image, 3, 2)
    np.testing.assert_allclose(small, image.reshape(2, 4, 3, 4, 2).mean(axis=(1, 3)), rtol=1e-6)


def test_resize_fractional_factor_weights_by_overlap():
    row = np.arange(6, dtype=np.float32).reshape(1, 6, 1)
    # footprints of 1.5 px: [0, 1.5) -> (0 + 0.5·1) / 1.5, [1.5, 3) -> (0.5·1 + 2) / 1.5, ...
    np.testing.assert_allclose(resize_image(row, 4, 1).ravel(), [1 / 3, 5 / 3, 10 / 3, 14 / 3], rtol=1e-6)
    constant = np.full((7, 5, 3), 0.3, np.float32)
    np.testing.assert_allclose(resize_image(constant, 3, 4), 0.3, rtol=1e-6)


@pytest.mark.parametrize("name", ["ost/OST_013.png", "celeba_hq/female_039913.jpg"])
def test_real_secrets_load_as_stored(shared_data, name):
    path = shared_data / "secrets" / name
    secret, warnings, _ = load_secret(path)
    assert secret.dtype == np.uint8 and secret.shape[-1] == 3 and warnings == []
    np.testing.assert_array_equal(secret, read_raw(path)[..., :3])


def test_reports_are_strict_json_with_null_for_non_finite_values():
    from noisenerf.runtime.files import json_text

    text = json_text({"psnr": float("inf"), "tiles": [{"ssim": float("nan"), "max_error": 0}], "exact": True})
    assert text == '{"psnr": null, "tiles": [{"ssim": null, "max_error": 0}], "exact": true}'


# ---- every format OpenImageIO writes -------------------------------------------------------------

def writable_formats() -> list[tuple[str, str]]:
    """(OpenImageIO format name, extension) for every format this OpenImageIO build knows, but its terminal and
    null outputs."""
    listed = oiio.get_string_attribute("extension_list").split(";")
    return [(name, extensions.split(",")[0]) for name, extensions in (item.split(":") for item in listed)
            if name not in ("term", "null")]


def composited(pixels: np.ndarray, associated: bool) -> np.ndarray:
    """What a secret of these 8-bit stored pixels should hide as (the test's own arithmetic): grey repeated,
    alpha composited over white, straight or associated. (H, W, C) uint8 -> (H, W, 3) uint8."""
    values = pixels.astype(np.float64) / 255.0
    if values.shape[-1] in (2, 4):
        colour, alpha = values[..., :-1], values[..., -1:]
        values = (colour if associated else colour * alpha) + (1.0 - alpha)
    return images.to_uint8(np.broadcast_to(values, values.shape[:2] + (3,)).astype(np.float32))


@pytest.mark.parametrize("format_name, extension", writable_formats())
def test_every_format_openimageio_writes_hides_as_its_pixels_or_is_refused(tmp_path, format_name, extension):
    """An image of each pixel type and channel count OpenImageIO writes in this format: load_secret returns the
    (h, w, 3) 8-bit secret, or refuses with one coded line; never another exception. Where the file holds the
    8-bit values written, they are the secret: passed through, or composited over white as its alpha says."""
    written = 0
    for pixel_type, channels in itertools.product(("uint8", "uint16", "float"), (1, 2, 3, 4)):
        pixels = np.random.default_rng(channels).integers(0, 256, (6, 9, channels), dtype=np.uint8)
        pixels[0, :4, -1] = (0, 1, 128, 255)  # alpha's extremes, where it has one
        path = tmp_path / f"{pixel_type}_{channels}.{extension}"
        output = oiio.ImageOutput.create(str(path))
        spec = oiio.ImageSpec(9, 6, channels, pixel_type)
        associated_format = format_name in ("openexr", "iff", "rla", "softimage")  # by their specifications
        spec.attribute("oiio:UnassociatedAlpha", 0 if associated_format else 1)
        stored = {"uint8": pixels, "uint16": pixels.astype(np.uint16) * 257, "float": pixels.astype(np.float32) / 255}
        if output is None or not output.open(str(path), spec) or not output.write_image(stored[pixel_type]):
            oiio.geterror()
            continue
        output.close()
        written += 1
        try:
            secret = load_secret(path)
        except UserError as error:
            assert error.code is not None and "\n" not in str(error), (pixel_type, channels, str(error))
            continue
        assert secret.pixels.dtype == np.uint8 and secret.pixels.shape == (6, 9, 3)
        reader = oiio.ImageInput.open(str(path))
        kept, has_alpha = reader.read_image("uint8").reshape(6, 9, -1), reader.spec().alpha_channel >= 0
        reader.close()
        if kept.shape[-1] == channels and np.array_equal(kept, pixels):  # the file holds the values written
            np.testing.assert_array_equal(secret.pixels, composited(pixels, associated_format and has_alpha),
                                          err_msg=str(path.name))
    if not written:
        pytest.skip(f"OpenImageIO reads {format_name} but writes none")


def test_an_indexed_png_with_transparency_is_its_palette_over_white(tmp_path):
    rng = np.random.default_rng(3)
    palette, indices = rng.integers(0, 256, (16, 3)), rng.integers(0, 16, (6, 7))
    alpha = np.array([0, 128] + [255] * 14)
    secret = load_secret(indexed_png(tmp_path / "p.png", indices, palette, alpha))
    rgba = np.concatenate([palette, alpha[:, None]], 1)[indices].astype(np.uint8)
    np.testing.assert_array_equal(secret.pixels, composited(rgba, associated=False))
    assert (secret.bits, secret.warnings) == (8, [])
    opaque = load_secret(indexed_png(tmp_path / "o.png", indices, palette))
    np.testing.assert_array_equal(opaque.pixels, palette[indices])


@pytest.mark.parametrize("name", ["transparent.gif", "indexed.png"])
def test_a_gif_or_indexed_png_secret_hides_and_reveals_exactly_through_the_commands(reveal_inputs, tmp_path, capfd,
                                                                                     name):
    """The family that crashed the hide (OpenImageIO states a GIF's alpha as channel 4 of 4) end to end."""
    folder, model, _ = reveal_inputs
    rng = np.random.default_rng(5)
    if name.endswith(".gif"):
        pixels = rng.integers(0, 256, (6, 9, 4), dtype=np.uint8)
        pixels[..., 3] = np.where(pixels[..., 3] > 100, 255, 0)
        write_raw(tmp_path / name, pixels, unassociated=True)
    else:
        indexed_png(tmp_path / name, rng.integers(0, 16, (6, 9)), rng.integers(0, 256, (16, 3)),
                    np.array([0, 64] + [255] * 14))
    expected = load_secret(tmp_path / name).pixels
    result = run_main(noisenerf_main, ["hide", folder / "scene", tmp_path / name, "-o", tmp_path / "s.bundle",
                                       "--quiet"], capfd)
    assert result.code in (0, None) and result.err == "", result.err
    revealed = run_reveal(model, tmp_path / "s.bundle", "-o", tmp_path / "out.png")
    assert revealed.returncode == 0, revealed.stderr
    np.testing.assert_array_equal(images.read_native(tmp_path / "out.png"), expected)


def test_a_truncated_png_is_refused_in_one_line_with_libpngs_own_words_kept_off_stderr(reveal_inputs, tmp_path,
                                                                                        capfd):
    folder, _, _ = reveal_inputs
    write_image(tmp_path / "whole.png", np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8))
    (tmp_path / "cut.png").write_bytes((tmp_path / "whole.png").read_bytes()[:60])
    result = run_main(noisenerf_main, ["hide", folder / "scene", tmp_path / "cut.png", "-o", tmp_path / "s.bundle",
                                       "--quiet"], capfd)
    assert_refused(result, tmp_path / "s.bundle", f"cannot read image {tmp_path / 'cut.png'}: ")
