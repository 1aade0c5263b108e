"""The compact layout end to end: exact through `noisenerf-reveal` (onnxruntime) on the demo scene,
tampering detected, format-1 bundles still revealed, newer formats refused in one line."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import save_file

from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.bundle import (METADATA_KEY, CompactBasis, expand_coefficients, load_bundle, pack_coefficients,
                                     unpack_coefficients)
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import write_image
from noisenerf.cli.demo import DEMO_VIEW
from noisenerf.train.scene.procedural import DEMO_SCENE
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.scene import load_scene


def run_reveal(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "noisenerf.cli.reveal", *map(str, args)],
                          capture_output=True, text=True, timeout=120)


@pytest.fixture(scope="module")
def demo(tmp_path_factory):
    """The demo scene's model, a 40×24 photo-like secret hidden as two compact tiles, and a ray bundle."""
    folder = tmp_path_factory.mktemp("compact")
    export_scene(DEMO_SCENE, folder / "model.onnx")
    yy, xx = np.mgrid[0:24, 0:40]
    smooth = np.stack([xx * 6, yy * 10, (xx + yy) * 4], axis=-1)
    secret = np.clip(smooth + np.random.default_rng(0).integers(-8, 9, smooth.shape), 0, 255).astype(np.uint8)
    write_image(folder / "secret.png", secret)
    scene = load_scene(DEMO_SCENE)
    reports = {layout: hide(scene, secret, folder / f"{layout}.bundle",
                            HideConfig(layout=layout, tile_size=24, view=DEMO_VIEW), torch.device("cpu"),
                            show_progress=False) for layout in ("compact", "ray")}
    return folder, secret, reports


def rewrite(source, target, edit_meta=lambda meta: meta, edit_tensors=lambda tensors: tensors) -> None:
    """Copy a bundle file with its metadata and tensors edited (no validation: what an attacker can write)."""
    with safe_open(str(source), framework="numpy") as handle:
        meta = json.loads(handle.metadata()[METADATA_KEY])
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    save_file(edit_tensors(tensors), str(target), metadata={METADATA_KEY: json.dumps(edit_meta(meta))})


def test_compact_bundle_reveals_exactly_through_onnxruntime(demo):
    folder, secret, reports = demo
    assert reports["compact"]["exact"] and len(reports["compact"]["tiles"]) == 2
    assert reports["compact"]["bundle_bytes"] * 8 < reports["ray"]["bundle_bytes"]
    result = run_reveal(folder / "model.onnx", folder / "compact.bundle", "-o", folder / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True
    bundle = load_bundle(folder / "compact.bundle")
    assert bundle.layout == "compact" and bundle.dtype == "int16" and bundle.tiles[0].noise.coefficients.dtype == np.int16


def test_a_tampered_coefficient_is_not_exact_and_a_corrupt_stream_is_refused(demo):
    folder, _, _ = demo
    bundle = load_bundle(folder / "compact.bundle")
    tile = bundle.tiles[0]
    coefficients = tile.noise.coefficients.copy()
    coefficients[3, 5, 0] += 300  # one pixel moved ~9 noise units along the first basis direction

    def tamper(tensors):
        return {**tensors, "tile_0000": pack_coefficients(coefficients)}

    rewrite(folder / "compact.bundle", folder / "tampered.bundle", edit_tensors=tamper)
    result = run_reveal(folder / "model.onnx", folder / "tampered.bundle", "-o", folder / "t.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is False

    def flip(tensors):
        packed = tensors["tile_0001"].copy()
        packed[len(packed) // 2] ^= 0x10
        return {**tensors, "tile_0001": packed}

    rewrite(folder / "compact.bundle", folder / "flipped.bundle", edit_tensors=flip)
    result = run_reveal(folder / "model.onnx", folder / "flipped.bundle", "-o", folder / "f.png")
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert len(result.stderr.splitlines()) == 1 and "coefficients" in result.stderr
    assert not (folder / "f.png").exists()


def test_format_1_ray_bundle_still_reveals_and_newer_formats_are_refused(demo):
    folder, _, _ = demo

    def as_format(version):
        return lambda meta: {**meta, "format_version": version}

    rewrite(folder / "ray.bundle", folder / "v1.bundle", as_format(1))
    result = run_reveal(folder / "model.onnx", folder / "v1.bundle", "-o", folder / "v1.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True
    rewrite(folder / "compact.bundle", folder / "v1compact.bundle", as_format(1))
    with pytest.raises(UserError, match="unknown noise layout 'compact'"):
        load_bundle(folder / "v1compact.bundle")
    rewrite(folder / "compact.bundle", folder / "v3.bundle", as_format(3))
    result = run_reveal(folder / "model.onnx", folder / "v3.bundle", "-o", folder / "v3.png")
    assert result.returncode == 2 and len(result.stderr.splitlines()) == 1
    assert "bundle format 3" in result.stderr and "a newer noisenerf is needed" in result.stderr


@pytest.mark.parametrize("dtype", ["int16", "int8"])
def test_coefficient_planes_round_trip_and_refuse_a_wrong_size(dtype):
    coefficients = np.random.default_rng(1).integers(-127, 128, (5, 7, 3)).astype(dtype)
    packed = pack_coefficients(coefficients)
    np.testing.assert_array_equal(unpack_coefficients(packed, (5, 7, 3), dtype, "t"), coefficients)
    with pytest.raises(UserError, match="do not hold exactly"):
        unpack_coefficients(packed, (5, 7, 2), dtype, "t")
    with pytest.raises(UserError, match="do not hold exactly"):
        unpack_coefficients(packed, (5, 7, 4), dtype, "t")


def test_expansion_matches_the_solver_and_puts_escapes_in_place():
    from noisenerf.train.hide.exact import NoiseSpace

    rng = np.random.default_rng(2)
    basis, offset = np.linalg.qr(rng.normal(size=(90, 5)))[0].astype(np.float32), rng.normal(size=90).astype(np.float32)
    space = NoiseSpace(torch.int16, torch.from_numpy(basis), torch.from_numpy(offset), float(np.float32(1 / 32)))
    params = space.store(torch.from_numpy(rng.normal(scale=50, size=(64, 5)).astype(np.float32)))
    escape_noise = rng.normal(size=(2, 90)).astype(np.float16)
    compact_basis = CompactBasis(basis, offset, space.scale, np.array([3, 40], np.int32), escape_noise)
    expanded = expand_coefficients(space.integers(params).numpy()[2:50], compact_basis, start=2)
    solver = space.expand(params)[2:50, 0].numpy()
    np.testing.assert_allclose(np.delete(expanded, [1, 38], axis=0), np.delete(solver, [1, 38], axis=0), atol=2e-5)
    np.testing.assert_array_equal(expanded[[1, 38]], escape_noise.astype(np.float32))


def edit_tile_meta(key, value):
    def edit(meta):
        meta["tiles"][0][key] = value
        return meta
    return edit


def edit_noise_meta(key, value):
    def edit(meta):
        meta["noise"][key] = value
        return meta
    return edit


def edit_tensor(name, make):
    return lambda meta: meta, lambda tensors: {**tensors, name: make(tensors[name])}


HOSTILE = {
    "scale NaN": ((edit_tile_meta("scale", float("nan")), None), "scale must be a finite number"),
    "scale 0": ((edit_tile_meta("scale", 0), None), "scale must be a finite number"),
    "scale text": ((edit_tile_meta("scale", "1"), None), "scale must be a number"),
    "9 coefficients": ((edit_noise_meta("coefficients", 9), None), "between 1 and 8"),
    "coefficients 2.5": ((edit_noise_meta("coefficients", 2.5), None), "must be an integer"),
    "coefficients missing": ((edit_noise_meta("coefficients", None), None), "must be an integer"),
    "unknown codec": ((edit_noise_meta("codec", "zip"), None), "unknown coefficient codec"),
    "float dtype": ((edit_noise_meta("dtype", "float16"), None), "unknown noise dtype"),
    "one coefficient fewer": ((edit_noise_meta("coefficients", 4), None), "do not hold exactly"),
    "basis missing": (edit_tensor("tile_0000_basis", lambda t: None), "is missing"),
    "basis NaN": (edit_tensor("tile_0000_basis", lambda t: np.full_like(t, np.nan)), "basis holds NaN"),
    "basis float16": (edit_tensor("tile_0000_basis", lambda t: t.astype(np.float16)), "expected float32"),
    "offset short": (edit_tensor("tile_0000_offset", lambda t: t[:89]), "offset is"),
    "escapes outside": (edit_tensor("tile_0000_escapes", lambda t: np.array([10 ** 6], np.int32)), "inside the tile"),
    "escapes repeated": (edit_tensor("tile_0000_escapes", lambda t: np.array([0, 0], np.int32)), "strictly increasing"),
    "escape noise Inf": ((lambda meta: meta, lambda tensors: {**tensors, "tile_0000_escapes": np.array([0], np.int32),
                                                              "tile_0000_escape_noise": np.full((1, 90), np.inf, np.float16)}),
                         "escape noise holds NaN"),
    "escape noise short": (edit_tensor("tile_0000_escapes", lambda t: np.arange(len(t) + 1, dtype=np.int32)),
                           "escape noise is"),
    "stream truncated": (edit_tensor("tile_0000", lambda t: t[:len(t) // 2]), "do not hold exactly"),
    "stream garbage": (edit_tensor("tile_0000", lambda t: np.arange(64, dtype=np.uint8)), "coefficients are corrupt"),
    "stream a bomb": (edit_tensor("tile_0000", lambda t: pack_coefficients(np.zeros((4096, 4096, 5), np.int16))),
                      "do not hold exactly"),
}


@pytest.mark.parametrize("case", list(HOSTILE))
def test_hostile_compact_bundle_is_one_line(demo, case):
    folder, _, _ = demo
    (edit_meta, edit_tensors), message = HOSTILE[case]

    def tensors_without_none(tensors):
        edited = edit_tensors(tensors) if edit_tensors else tensors
        return {name: value for name, value in edited.items() if value is not None}

    rewrite(folder / "compact.bundle", folder / "bad.bundle", edit_meta, tensors_without_none)
    with pytest.raises(UserError, match=message):
        load_bundle(folder / "bad.bundle")
