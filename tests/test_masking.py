"""The mask (bundle format 5, runtime.masking): a bundle reads only with its model; with it nothing changes."""

from __future__ import annotations

import dataclasses
import json
import lzma

import numpy as np
import pytest
import torch

import noisenerf
from helpers import bundle_contents, make_tiny_scene, mask_secret_of, rewrite_bundle, run_reveal
from noisenerf.cli.bench.masking import byte_entropy, explained_variance, stored_bytes
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.bundle import BUNDLE_FORMAT_VERSION, load_bundle
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fingerprint import weights_digests
from noisenerf.runtime.masking import mask_key, mask_metadata, xor_masked
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def hidden(tmp_path_factory):
    """A tiny scene's model, and a smooth 24² secret hidden in it as compact and as ray bundles."""
    folder = tmp_path_factory.mktemp("masking")
    scene = make_tiny_scene(seed=4)
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    yy, xx = np.mgrid[0:24, 0:24]
    secret = np.stack([xx * 10, yy * 10, 255 - xx * 5], -1).astype(np.uint8)
    for layout in ("compact", "ray"):
        hide(scene, secret, folder / f"{layout}.bundle", HideConfig(layout=layout, tile_size=24, view=1), CPU,
             workers=1)
    return folder, scene, secret


def test_the_mask_secret_is_not_the_fingerprint_and_follows_every_weight():
    scene = make_tiny_scene(seed=4)
    digests = scene.digests()
    assert digests.fingerprint == scene.fingerprint() and len(digests.mask_secret) == 32
    assert digests.mask_secret != bytes.fromhex(digests.fingerprint)
    weights = scene.weight_arrays()
    name = sorted(weights)[0]
    weights[name] = weights[name].copy()
    weights[name].flat[0] = np.nextafter(weights[name].flat[0], np.float32(np.inf))
    assert weights_digests(weights, scene.config.architecture()).mask_secret != digests.mask_secret


def test_a_bundle_without_its_model_is_refused_and_its_bytes_are_noise(hidden):
    folder, scene, secret = hidden
    for layout in ("compact", "ray"):
        path = folder / f"{layout}.bundle"
        meta, stored = bundle_contents(path)
        assert meta["format_version"] == BUNDLE_FORMAT_VERSION == 5 and set(meta["mask"]) == {"cipher", "kdf", "salt"}
        with pytest.raises(UserError, match="masked with its model") as refused:
            load_bundle(path)
        assert refused.value.code == "bundle.masked"
        _, unmasked = bundle_contents(path, scene)
        key = mask_key(scene.digests().mask_secret, bytes(16))
        assert all(np.array_equal(xor_masked(xor_masked(unmasked, key), key)[name], unmasked[name]) for name in stored)
        data = path.read_bytes()
        masked_bytes = stored_bytes(data)
        plain = dataclasses.replace(load_bundle(path, mask_secret_of(scene)), mask_salt=None).to_bytes()
        plain_bytes = stored_bytes(plain)
        assert len(masked_bytes) == len(plain_bytes) and masked_bytes != plain_bytes
        assert len(lzma.compress(masked_bytes, preset=9)) > len(masked_bytes)  # xz gains nothing on noise
        assert byte_entropy(masked_bytes) > 8 - 255 / (2 * len(masked_bytes) * np.log(2)) - 0.05
        if layout == "ray":  # float16 noise as written: far from uniform bytes
            assert byte_entropy(plain_bytes) < 7.5 and len(lzma.compress(plain_bytes)) < 0.9 * len(plain_bytes)


def test_the_compact_planes_follow_the_colours_only_unmasked(hidden):
    """The measurement behind the mask: unmasked, a linear function of the colours explains much of a coefficient
    plane; the masked stream, laid over the pixels, nothing beyond what chance fits."""
    folder, scene, secret = hidden
    bundle = load_bundle(folder / "compact.bundle", mask_secret_of(scene))
    coefficients = bundle.tiles[0].noise.coefficients().reshape(24 * 24, -1)
    colours = secret.reshape(-1, 3)
    assert explained_variance(coefficients, colours).max() > 0.2
    _, stored = bundle_contents(folder / "compact.bundle")
    stream = np.resize(np.frombuffer(stored["tile_0000"].tobytes(), np.uint8), coefficients.shape)
    assert explained_variance(stream, colours).max() < 0.05


def test_masked_bundles_reveal_exactly_and_the_same_seed_gives_the_same_bytes(hidden, tmp_path):
    folder, scene, secret = hidden
    for layout in ("compact", "ray"):
        result = noisenerf.reveal(folder / "model.onnx", folder / f"{layout}.bundle")
        assert result.exact and np.array_equal(result.pixels, secret)
    hide(scene, secret, tmp_path / "again.bundle", HideConfig(layout="compact", tile_size=24, view=1), CPU, workers=1)
    assert (tmp_path / "again.bundle").read_bytes() == (folder / "compact.bundle").read_bytes()
    hide(scene, secret, tmp_path / "seed.bundle", HideConfig(layout="compact", tile_size=24, view=1, seed=1), CPU,
         workers=1)
    assert bundle_contents(tmp_path / "seed.bundle")[0]["mask"] != bundle_contents(folder / "compact.bundle")[0]["mask"]


def test_a_format_4_bundle_still_reveals_and_a_stripped_or_foreign_mask_is_refused(hidden, tmp_path):
    folder, scene, secret = hidden
    model = folder / "model.onnx"

    def as_format_4(meta, tensors):
        meta.update(format_version=4)
        meta.pop("mask")

    rewrite_bundle(folder / "compact.bundle", tmp_path / "v4.bundle", as_format_4, scene)
    assert load_bundle(tmp_path / "v4.bundle").tiles[0].noise.coefficients().shape == (24, 24, 5)
    result = run_reveal(model, tmp_path / "v4.bundle", "-o", tmp_path / "v4.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True
    cases = {
        "stripped": (lambda meta, tensors: meta.pop("mask"), "format 5 bundles are masked"),
        "format 4 masked": (lambda meta, tensors: meta.update(format_version=4), "format 4 bundles are not masked"),
        "other salt": (lambda meta, tensors: meta.update(mask=mask_metadata(bytes(16))), "bundle: tile 0"),
        "salt text": (lambda meta, tensors: meta["mask"].update(salt="not base64!"), "the mask must be an object"),
    }
    for case, (edit, message) in cases.items():
        rewrite_bundle(folder / "compact.bundle", tmp_path / "bad.bundle", edit)  # tensors as stored, masked
        result = run_reveal(model, tmp_path / "bad.bundle", "-o", tmp_path / "bad.png")
        assert result.returncode == 2 and message in result.stderr and result.stderr.count("\n") == 1, (case, result.stderr)
        assert not (tmp_path / "bad.png").exists()


def test_another_models_bundle_is_refused_by_fingerprint_before_it_is_unmasked(hidden, tmp_path):
    folder, _, _ = hidden
    other = make_tiny_scene(seed=5)
    other.save(tmp_path / "scene")
    export_scene(tmp_path / "scene", tmp_path / "model.onnx")
    result = run_reveal(tmp_path / "model.onnx", folder / "compact.bundle", "-o", tmp_path / "out.png")
    assert result.returncode == 2 and "bundle was made for model" in result.stderr
