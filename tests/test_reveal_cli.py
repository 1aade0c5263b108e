"""`noisenerf-reveal` end to end as a subprocess: reveals what the library reveals, refuses bad input cleanly."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import onnx
import pytest

from helpers import assert_refused, hidden_bundle, mask_secret_of, rewrite_bundle, run_reveal, two_tile_bundle
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.images import read_native
from noisenerf.runtime.model import load_model
from noisenerf.runtime.rays import camera_ray_batch
from noisenerf.runtime.reveal import reveal_tiles
from noisenerf.runtime.sampling import sample_along
from noisenerf.runtime.sampling import sample_positions
from noisenerf.train.scene.scene import load_scene


def test_reveal_writes_the_library_reveal_and_reports_exact(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    result = run_reveal(model, bundle, "-o", tmp_path / "out.png", "--json", "--threads", 1)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert isinstance(report, dict) and report["exact"] is True
    assert (report["width"], report["height"], report["tiles"]) == (32, 12, 2)
    assert report["rays"] == 32 * 12 and report["samples"] == 32 * 12 * 24
    assert report["output"] == str(tmp_path / "out.png") and report["seconds"] > 0
    loaded = load_model(model)
    expected = reveal_tiles(hidden_bundle(bundle, loaded), loaded.render_config, loaded.fields())
    np.testing.assert_array_equal(read_native(tmp_path / "out.png"), expected.pixels)


def test_sample_layout_bundle_reveals_exactly(reveal_inputs, tmp_path):
    directory, model, _ = reveal_inputs
    two_tile_bundle(load_scene(directory / "scene"), layout="sample", seed=1).save(tmp_path / "s.bundle")
    result = run_reveal(model, tmp_path / "s.bundle", "-o", tmp_path / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True


WIDE = {"out.tif": (lambda v: v.astype(np.uint16) * np.uint16(257), "16 bits (v*257)"),
        "out.exr": (lambda v: v.astype(np.float32) / np.float32(255), "(v/255)")}


@pytest.mark.parametrize("name", WIDE)
def test_wide_outputs_hold_the_pixels_exact_judged(reveal_inputs, tmp_path, name):
    """A 16-bit or float file holds the 8-bit pixels the digest was checked on, scaled exactly, and says so,
    not the float render, whose values `exact` says nothing about."""
    _, model, bundle = reveal_inputs
    scaled, written = WIDE[name]
    result = run_reveal(model, bundle, "-o", tmp_path / name, "--json")
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert report["exact"] is True and report["written"].endswith(written)
    loaded = load_model(model)
    expected = reveal_tiles(hidden_bundle(bundle, loaded), loaded.render_config, loaded.fields(), keep_float=True)
    stored = read_native(tmp_path / name)
    np.testing.assert_array_equal(stored, scaled(expected.pixels))
    assert not np.array_equal(stored, scaled(expected.image * 255).astype(stored.dtype))  # not the float render


def test_another_digest_is_reported_inexact(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    secret = mask_secret_of(model)
    dataclasses.replace(load_bundle(bundle, secret), secret_sha256="0" * 64).save(tmp_path / "other.bundle",
                                                                                  mask_secret=secret)
    result = run_reveal(model, tmp_path / "other.bundle", "-o", tmp_path / "out.png")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == "exact: false"
    assert (tmp_path / "out.png").is_file()


def test_view_render_skips_and_no_skip_does_not(reveal_inputs, tmp_path):
    _, model, _ = reveal_inputs
    reports = {}
    for flags in ([], ["--no-skip"]):
        result = run_reveal(model, "--view", 3, "-o", tmp_path / f"view{len(flags)}.png", "--json", *flags)
        assert result.returncode == 0, result.stderr
        reports[bool(flags)] = json.loads(result.stdout)
    # without skipping, every sample inside the scene's box is evaluated (outside it the scene is empty)
    loaded = load_model(model)
    rays = camera_ray_batch(loaded.camera(3), loaded.render_config)
    points, _ = sample_along(rays.origins, rays.directions, sample_positions(loaded.render_config.sampling))
    assert reports[True]["samples_dense"] == 16 * 12 * 24
    assert reports[True]["samples"] == int(loaded.grid.contains(points).sum()) > 0
    assert reports[False]["samples"] <= reports[True]["samples"]
    assert (reports[False]["width"], reports[False]["height"]) == (16, 12)


def nan_noise(meta, tensors):
    tensors["tile_0001"][3, 4, 5] = np.nan


def wrong_shape(meta, tensors):
    tensors["tile_0000"] = tensors["tile_0000"][..., :-1].copy()


def overlapping(meta, tensors):
    meta["tiles"][1]["rect"][0] = 8


def outside(meta, tensors):
    meta["tiles"][1]["rect"][0] = 24


def unknown_network(meta, tensors):
    meta["tiles"][0]["network"] = "medium"


def other_model(meta, tensors):
    meta["model_fingerprint"] = "f" * 64


def strip_metadata(model: onnx.ModelProto) -> onnx.ModelProto:
    del model.metadata_props[:]
    return model


REFUSALS = {  # case: (tampering, expected message)
    "fingerprint mismatch": (other_model, "bundle was made for model ffffffffffff"),
    "NaN noise": (nan_noise, "NaN"),
    "wrong noise shape": (wrong_shape, "noise is"),
    "overlapping tiles": (overlapping, "overlap"),
    "tile outside the image": (outside, "outside"),
    "unknown network": (unknown_network, "names network 'medium'"),
}


@pytest.mark.parametrize("case", list(REFUSALS))
def test_malformed_bundles_are_refused(reveal_inputs, tmp_path, case):
    _, model, bundle = reveal_inputs
    edit, message = REFUSALS[case]
    bad = rewrite_bundle(bundle, tmp_path / "bad.bundle", edit)
    assert_refused(run_reveal(model, bad, "-o", tmp_path / "out.png"), tmp_path / "out.png", message)


def test_truncated_and_foreign_bundles_are_refused(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    data = bundle.read_bytes()
    (tmp_path / "truncated.bundle").write_bytes(data[:len(data) // 2])
    (tmp_path / "text.bundle").write_text("not a bundle at all\n")
    for name in ("truncated.bundle", "text.bundle"):
        assert_refused(run_reveal(model, tmp_path / name, "-o", tmp_path / "out.png"), tmp_path / "out.png",
                       "not a readable safetensors bundle")


def test_foreign_and_external_data_models_are_refused(reveal_inputs, tmp_path):
    _, model, bundle = reveal_inputs
    onnx.save_model(strip_metadata(onnx.load(str(model))), str(tmp_path / "plain.onnx"))
    onnx.save_model(onnx.load(str(model)), str(tmp_path / "external.onnx"), save_as_external_data=True,
                    location="external.onnx.data", size_threshold=0)
    data = model.read_bytes()
    (tmp_path / "truncated.onnx").write_bytes(data[:len(data) // 2])
    cases = {"plain.onnx": "not a noisenerf model", "external.onnx": "external data",
             "truncated.onnx": "not a loadable ONNX model", "missing.onnx": "model not found"}
    for name, message in cases.items():
        assert_refused(run_reveal(tmp_path / name, bundle, "-o", tmp_path / "out.png"), tmp_path / "out.png",
                       message)


def test_bad_view_and_outputs_are_refused(reveal_inputs, tmp_path):
    directory, model, bundle = reveal_inputs
    out = tmp_path / "out.png"
    assert_refused(run_reveal(model, "--view", 6, "-o", out), out, "view 6 is out of range")
    assert_refused(run_reveal(model, "--view", -1, "-o", out), out, "out of range")
    assert_refused(run_reveal(model, bundle, "-o", tmp_path / "nowhere" / "out.png"),
                   tmp_path / "nowhere" / "out.png", "output folder does not exist")
    assert_refused(run_reveal(model, directory / "missing.bundle", "-o", out), out, "bundle not found")
    assert_refused(run_reveal(model, bundle, "-o", tmp_path / "out.bmp"), tmp_path / "out.bmp", "unknown image")
    out.write_bytes(b"keep")
    assert_refused(run_reveal(model, bundle, "-o", out), None, "pass --force to overwrite")
    assert out.read_bytes() == b"keep"
    assert run_reveal(model, bundle, "-o", out, "--force").returncode == 0
    assert read_native(out).shape == (12, 32, 3)
