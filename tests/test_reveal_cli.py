"""`noisenerf-reveal` end to end as a subprocess: reveals what the library reveals, refuses bad input cleanly."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import onnx
import pytest
from safetensors.numpy import save_file

from helpers import make_tiny_scene
from noisenerf.export.onnx_export import export_scene
from noisenerf.train.scene.render import numpy_fields
from noisenerf.runtime.bundle import METADATA_KEY, Bundle, Tile, load_bundle, secret_digest
from noisenerf.runtime.images import read_image, read_native
from noisenerf.runtime.model import load_model
from noisenerf.runtime.camera import camera_rays
from noisenerf.runtime.render import prepare_rays
from noisenerf.runtime.sampling import sample_along
from noisenerf.runtime.reveal import reveal
from noisenerf.runtime.sampling import sample_positions
from noisenerf.train.scene.scene import load_scene


def two_tile_bundle(scene, layout: str = "ray", seed: int = 0, network: str | None = None) -> Bundle:
    """Random noise in two views side by side, for `network` (None: no network field, as bundles made
    before it existed); the digest is that of torch's render of this very noise."""
    config, dims = scene.config.render, scene.render_field.config.noise_dims
    rng = np.random.default_rng(seed)
    tiles = []
    for i, camera in enumerate(scene.config.cameras[:2]):
        shape = (camera.height, camera.width) + ((config.sampling.n_samples,) if layout == "sample" else ())
        noise = rng.normal(size=shape + (dims,)).astype(np.float32)
        tiles.append(Tile((i * camera.width, 0, camera.width, camera.height), camera, config.sampling, noise, i,
                          network))
    width, height = sum(t.rect[2] for t in tiles), tiles[0].rect[3]
    bundle = Bundle(scene.fingerprint(), width, height, "0" * 64, layout, dims, "float32", tuple(tiles), {})
    pixels = reveal(bundle, config, numpy_fields(scene.fields())).pixels
    return dataclasses.replace(bundle, secret_sha256=secret_digest(pixels))


def write_reveal_inputs(directory: Path) -> tuple[Path, Path]:
    """A tiny exported model and a two-tile bundle for it, in `directory`."""
    scene = make_tiny_scene(seed=4)
    scene.save(directory / "scene")
    export_scene(directory / "scene", directory / "model.onnx")
    two_tile_bundle(scene).save(directory / "secret.bundle")
    return directory / "model.onnx", directory / "secret.bundle"


def run_reveal(*args, cwd: Path | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "noisenerf.cli.reveal", *map(str, args)],
                          capture_output=True, text=True, timeout=60, cwd=cwd)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    directory = tmp_path_factory.mktemp("reveal")
    model, bundle = write_reveal_inputs(directory)
    return directory, model, bundle


def test_reveal_writes_the_library_reveal_and_reports_exact(inputs, tmp_path):
    _, model, bundle = inputs
    result = run_reveal(model, bundle, "-o", tmp_path / "out.png", "--json", "--threads", 1)
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout)
    assert isinstance(report, dict) and report["exact"] is True
    assert (report["width"], report["height"], report["tiles"]) == (32, 12, 2)
    assert report["rays"] == 32 * 12 and report["samples"] == 32 * 12 * 24
    assert report["output"] == str(tmp_path / "out.png") and report["seconds"] > 0
    loaded = load_model(model)
    expected = reveal(load_bundle(bundle), loaded.render_config, loaded.fields())
    np.testing.assert_array_equal(read_native(tmp_path / "out.png"), expected.pixels)


def test_sample_layout_bundle_reveals_exactly(inputs, tmp_path):
    directory, model, _ = inputs
    two_tile_bundle(load_scene(directory / "scene"), layout="sample", seed=1).save(tmp_path / "s.bundle")
    result = run_reveal(model, tmp_path / "s.bundle", "-o", tmp_path / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True


def test_exr_output_holds_the_float_image(inputs, tmp_path):
    _, model, bundle = inputs
    result = run_reveal(model, bundle, "-o", tmp_path / "out.exr")
    assert result.returncode == 0, result.stderr
    loaded = load_model(model)
    expected = reveal(load_bundle(bundle), loaded.render_config, loaded.fields())
    np.testing.assert_array_equal(read_image(tmp_path / "out.exr"), expected.image)


def test_another_digest_is_reported_inexact(inputs, tmp_path):
    _, model, bundle = inputs
    dataclasses.replace(load_bundle(bundle), secret_sha256="0" * 64).save(tmp_path / "other.bundle")
    result = run_reveal(model, tmp_path / "other.bundle", "-o", tmp_path / "out.png")
    assert result.returncode == 0, result.stderr
    assert result.stdout.splitlines()[0] == "exact: false"
    assert (tmp_path / "out.png").is_file()


def test_view_render_skips_and_no_skip_does_not(inputs, tmp_path):
    _, model, _ = inputs
    reports = {}
    for flags in ([], ["--no-skip"]):
        result = run_reveal(model, "--view", 3, "-o", tmp_path / f"view{len(flags)}.png", "--json", *flags)
        assert result.returncode == 0, result.stderr
        reports[bool(flags)] = json.loads(result.stdout)
    # without skipping, every sample inside the scene's box is evaluated (outside it the scene is empty)
    loaded = load_model(model)
    rays = prepare_rays(loaded.render_config, *camera_rays(loaded.camera(3), loaded.render_config.pixel_center))
    points, _ = sample_along(rays.origins, rays.directions, sample_positions(loaded.render_config.sampling))
    assert reports[True]["samples_dense"] == 16 * 12 * 24
    assert reports[True]["samples"] == int(loaded.grid.contains(points).sum()) > 0
    assert reports[False]["samples"] <= reports[True]["samples"]
    assert (reports[False]["width"], reports[False]["height"]) == (16, 12)


def raw_bundle(path: Path, source: Path, edit) -> Path:
    """Write a bundle whose metadata and tensors `edit(meta, tensors)` has tampered with, bypassing validation."""
    bundle = load_bundle(source)
    meta = bundle.metadata()
    tensors = {f"tile_{i:04d}": tile.noise.copy() for i, tile in enumerate(bundle.tiles)}
    edit(meta, tensors)
    save_file(tensors, str(path), metadata={METADATA_KEY: json.dumps(meta)})
    return path


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
def test_malformed_bundles_are_refused(inputs, tmp_path, case):
    _, model, bundle = inputs
    edit, message = REFUSALS[case]
    bad = raw_bundle(tmp_path / "bad.bundle", bundle, edit)
    assert_refused(run_reveal(model, bad, "-o", tmp_path / "out.png"), tmp_path / "out.png", message)


def assert_refused(result: subprocess.CompletedProcess, output: Path | None, message: str) -> None:
    """Exit code 2, one stderr line carrying `message`, nothing on stdout, and no `output` written."""
    lines = result.stderr.splitlines()
    assert result.returncode == 2, result.stderr
    assert len(lines) == 1 and lines[0].startswith("noisenerf-reveal: error: "), result.stderr
    assert message in lines[0]
    assert result.stdout == ""
    assert output is None or not output.exists()


def test_truncated_and_foreign_bundles_are_refused(inputs, tmp_path):
    _, model, bundle = inputs
    data = bundle.read_bytes()
    (tmp_path / "truncated.bundle").write_bytes(data[:len(data) // 2])
    (tmp_path / "text.bundle").write_text("not a bundle at all\n")
    for name in ("truncated.bundle", "text.bundle"):
        assert_refused(run_reveal(model, tmp_path / name, "-o", tmp_path / "out.png"), tmp_path / "out.png",
                       "not a readable safetensors bundle")


def test_foreign_and_external_data_models_are_refused(inputs, tmp_path):
    _, model, bundle = inputs
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


def test_bad_view_and_outputs_are_refused(inputs, tmp_path):
    directory, model, bundle = inputs
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
