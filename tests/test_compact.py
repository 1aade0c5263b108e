"""The compact layout end to end: exact through `noisenerf-reveal` (onnxruntime) on the demo scene,
tampering detected, format-1 bundles still revealed, newer formats refused in one line."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from helpers import as_older_compact_format, assert_refused, hidden_bundle, rewrite_bundle, run_reveal
from noisenerf.cli.demo import DEMO_VIEW
from noisenerf.runtime import interlaced
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.layouts import CompactBasis, expand_coefficients, pack_coefficients, unpack_coefficients
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import write_image
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide


@pytest.fixture(scope="module")
def demo(demo_scene, demo_model, tmp_path_factory):
    """A folder holding a 40×24 photo-like secret of the demo scene hidden as two compact tiles and as a ray
    bundle, the secret, the hides' reports, and the demo's model."""
    folder = tmp_path_factory.mktemp("compact")
    yy, xx = np.mgrid[0:24, 0:40]
    smooth = np.stack([xx * 6, yy * 10, (xx + yy) * 4], axis=-1)
    secret = np.clip(smooth + np.random.default_rng(0).integers(-8, 9, smooth.shape), 0, 255).astype(np.uint8)
    write_image(folder / "secret.png", secret)
    reports = {layout: hide(demo_scene, secret, folder / f"{layout}.bundle",
                            HideConfig(layout=layout, tile_size=24, view=DEMO_VIEW), torch.device("cpu")) for layout in ("compact", "ray")}
    return folder, secret, reports, demo_model


def test_compact_bundle_reveals_exactly_through_onnxruntime(demo):
    folder, secret, reports, model = demo
    assert reports["compact"]["exact"] and len(reports["compact"]["tiles"]) == 2
    assert reports["compact"]["bundle_bytes"] * 8 < reports["ray"]["bundle_bytes"]
    result = run_reveal(model, folder / "compact.bundle", "-o", folder / "out.png", "--json")
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["exact"] is True
    bundle = hidden_bundle(folder / "compact.bundle", model)
    assert bundle.layout == "compact" and bundle.dtype == "int16" and bundle.tiles[0].noise.coefficients().dtype == np.int16


def test_tiles_beyond_the_kept_budget_are_unpacked_again_when_rendered_with_the_same_pixels(demo, monkeypatch):
    from noisenerf.runtime import layouts as layouts_module
    from noisenerf.runtime.model import load_model
    from noisenerf.runtime.reveal import reveal_tiles

    folder, secret, _, model = demo
    kept = hidden_bundle(folder / "compact.bundle", model)
    tile_bytes = kept.tiles[0].noise.unpacked.nbytes  # two 24² tiles of k int16 coefficients a pixel
    monkeypatch.setattr(layouts_module, "KEPT_UNPACKED_BYTES", tile_bytes)
    partly = hidden_bundle(folder / "compact.bundle", model)
    assert [t.noise.unpacked is not None for t in kept.tiles] == [True, True]
    assert [t.noise.unpacked is not None for t in partly.tiles] == [True, False]
    loaded = load_model(model)
    for bundle in (kept, partly):
        revealed = reveal_tiles(bundle, loaded.render_config, loaded.fields())
        assert revealed.exact
        np.testing.assert_array_equal(revealed.pixels, secret)


def test_a_tampered_coefficient_is_not_exact_and_a_corrupt_stream_is_refused(demo):
    folder, _, _, model = demo
    bundle = hidden_bundle(folder / "compact.bundle", model)
    tile = bundle.tiles[0]
    coefficients = tile.noise.coefficients()
    coefficients[3, 5, 0] += 300  # one pixel moved ~9 noise units along the first basis direction

    def tamper(meta, tensors):
        tensors["tile_0000"] = pack_coefficients(coefficients)

    rewrite_bundle(folder / "compact.bundle", folder / "tampered.bundle", tamper, model)
    result = run_reveal(model, folder / "tampered.bundle", "-o", folder / "t.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is False

    def flip(meta, tensors):
        packed = tensors["tile_0001"].copy()
        packed[len(packed) // 2] ^= 0x10
        tensors["tile_0001"] = packed

    rewrite_bundle(folder / "compact.bundle", folder / "flipped.bundle", flip, model)
    result = run_reveal(model, folder / "flipped.bundle", "-o", folder / "f.png")
    assert_refused(result, folder / "f.png", "coefficients")


def test_format_1_ray_bundle_still_reveals_and_newer_formats_are_refused(demo):
    folder, _, _, model = demo

    def as_format(version):
        def edit(meta, tensors):
            meta.update(format_version=version)
            if version < 5:  # written unmasked
                meta.pop("mask")
        return edit

    rewrite_bundle(folder / "ray.bundle", folder / "v1.bundle", as_format(1), model)
    result = run_reveal(model, folder / "v1.bundle", "-o", folder / "v1.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True
    rewrite_bundle(folder / "compact.bundle", folder / "v1compact.bundle", as_format(1), model)
    with pytest.raises(UserError, match="unknown noise layout 'compact'"):
        load_bundle(folder / "v1compact.bundle")
    rewrite_bundle(folder / "compact.bundle", folder / "v6.bundle", as_format(6), model)
    result = run_reveal(model, folder / "v6.bundle", "-o", folder / "v6.png")
    assert_refused(result, folder / "v6.png", "bundle format 6")
    assert "a newer noisenerf is needed" in result.stderr


def test_a_format_2_compact_bundle_reveals_exactly_without_branch_escapes(demo):
    """Format 2 compact tiles (written before branch escapes) have no branch escape tensors and none is asked for;
    a format 3 bundle without them is refused."""
    folder, secret, reports, model = demo
    assert all(tile["branch_escaped"] == 0 for tile in reports["compact"]["tiles"])  # as a format 2 writer left it

    rewrite_bundle(folder / "compact.bundle", folder / "v2.bundle", as_older_compact_format(2), model)
    result = run_reveal(model, folder / "v2.bundle", "-o", folder / "v2.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True
    rewrite_bundle(folder / "compact.bundle", folder / "v3_missing.bundle",
                   lambda meta, tensors: tensors.pop("tile_0000_branch_escapes"), model)
    with pytest.raises(UserError, match="tensor 'tile_0000_branch_escapes' is missing"):
        hidden_bundle(folder / "v3_missing.bundle", model)


def test_a_format_3_compact_bundle_reveals_the_same_pixels_from_its_plain_planes(demo):
    """Format 3 stored the coefficients themselves (xz-byte-planes); the same coefficients so stored reveal the
    same exact pixels, and either codec stated under the other format is refused."""
    folder, secret, _, model = demo
    rewrite_bundle(folder / "compact.bundle", folder / "v3.bundle", as_older_compact_format(3), model)
    now, before = hidden_bundle(folder / "compact.bundle", model), load_bundle(folder / "v3.bundle")
    for tile_now, tile_before in zip(now.tiles, before.tiles):
        assert np.array_equal(tile_now.noise.coefficients(), tile_before.noise.coefficients())
        assert not np.array_equal(tile_now.noise.packed, tile_before.noise.packed)
    result = run_reveal(model, folder / "v3.bundle", "-o", folder / "v3.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True
    for version, source in ((3, "compact.bundle"), (4, "v3.bundle")):
        rewrite_bundle(folder / source, folder / "mixed.bundle",
                       lambda meta, tensors: meta.update(format_version=version) or meta.pop("mask", None), model)
        with pytest.raises(UserError, match="unknown coefficient codec"):
            load_bundle(folder / "mixed.bundle")


def test_coefficients_chosen_near_their_predictions_make_a_smaller_exact_key(demo_scene, demo_model, shared_data,
                                                                             tmp_path, monkeypatch):
    """A photo the bench never uses, at a camera it never uses: with each part's coefficients moved to those
    nearest their interlaced predictions (predicted_choice) the key's coefficients take at least 8 % fewer bytes than with the
    solver's own solutions coded the same way (the coefficient streams; the basis and metadata are alike), and both
    reveal exactly."""
    from noisenerf.cli.bench.context import small_secret
    from noisenerf.runtime.images import load_secret
    from noisenerf.train.hide import exact_solver

    photo = small_secret(load_secret(shared_data / "secrets" / "celeba_hq" / "male_006930.jpg")[0], 128)
    sizes = {}
    for name in ("chosen", "as_solved"):
        if name == "as_solved":
            monkeypatch.setattr(exact_solver, "predicted_choice", lambda view, space, pixels, shape, params, *_: params)
        report = hide(demo_scene, photo, tmp_path / f"{name}.bundle", HideConfig(view=33), torch.device("cpu"))
        result = run_reveal(demo_model, tmp_path / f"{name}.bundle", "-o", tmp_path / f"{name}.png", "--json")
        assert report["exact"] and json.loads(result.stdout)["exact"] is True
        sizes[name] = sum(len(tile.noise.packed) for tile in hidden_bundle(tmp_path / f"{name}.bundle", demo_scene).tiles)
    assert sizes["chosen"] < 0.92 * sizes["as_solved"], sizes


@pytest.mark.parametrize("dtype", [np.int16, np.int8])
def test_interlaced_differences_round_trip_every_integer_and_shrink_smooth_planes(dtype):
    """Any coefficients, the storage range's ends and odd sizes included, come back exactly; a smooth plane's
    differences are small, a 1×1 tile's is the value itself."""
    rng = np.random.default_rng(3)
    limit = np.iinfo(dtype).max
    for height, width in ((1, 1), (1, 9), (9, 1), (7, 13), (33, 70)):
        anything = rng.integers(-limit - 1, limit + 1, (height, width, 5)).astype(dtype)
        anything.flat[:4] = [-limit - 1, limit, -limit - 1, limit]
        for band_rows in (1, 3, 8, 40):
            assert np.array_equal(interlaced.decode(interlaced.encode(anything, band_rows), band_rows), anything)
    smooth = np.cumsum(np.cumsum(rng.integers(-1, 2, (40, 40, 3)), 0), 1).astype(dtype)
    codes = interlaced.encode(smooth, 16)
    assert np.array_equal(interlaced.decode(codes, 16), smooth)
    assert np.abs(interlaced.unzigzag(codes)).mean() < 0.5 * np.abs(smooth.astype(np.int64)).mean()
    assert interlaced.unzigzag(interlaced.encode(np.array([[[-7, 5]]], dtype), 1))[0, 0].tolist() == [-7, 5]


def test_pixels_the_basis_misses_but_the_view_branch_reaches_are_stored_as_branch_escapes(demo_scene, demo_model,
                                                                                          tmp_path):
    """At camera 20 of the demo scene, a basis misses a few pixels of the all-white secret; the view branch
    alone brings them to their colours, so each stores its 27 γ(d) values (58 bytes with its index, not the
    184 of a full escape), and the bundle reveals exactly through onnxruntime."""
    from noisenerf.cli.bench.coverage import hard_secrets

    secret = hard_secrets(16, tuple(demo_scene.config.render.background))["white"]
    report = hide(demo_scene, secret, tmp_path / "b.bundle", HideConfig(view=20), torch.device("cpu"), workers=1)
    tile = report["tiles"][0]
    assert tile["branch_escaped"] == tile["escaped"] > 0
    basis = hidden_bundle(tmp_path / "b.bundle", demo_scene).tiles[0].noise.basis
    assert len(basis.escapes) == 0 and basis.branch_escape_noise.shape == (tile["branch_escaped"], 27)
    result = run_reveal(demo_model, tmp_path / "b.bundle", "-o", tmp_path / "b.png", "--json")
    assert result.returncode == 0 and json.loads(result.stdout)["exact"] is True


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
    branch_noise = rng.normal(size=(3, 27)).astype(np.float16)
    compact_basis = CompactBasis(basis, offset, space.scale, np.array([3, 40], np.int32), escape_noise,
                                 np.array([1, 7, 60], np.int32), branch_noise)
    expanded = expand_coefficients(space.integers(params).numpy()[2:50], compact_basis, start=2)
    solver = space.expand(params)[2:50, 0].numpy()
    np.testing.assert_allclose(np.delete(expanded, [1, 5, 38], axis=0), np.delete(solver, [1, 5, 38], axis=0),
                               atol=2e-5)
    np.testing.assert_array_equal(expanded[[1, 38]], escape_noise.astype(np.float32))
    # pixel 7 (row 5) is a branch escape: the offset's first 63 values, then its 27 stored ones; 1 and 60 lie outside
    np.testing.assert_array_equal(expanded[5], np.concatenate([offset[:63], branch_noise[1].astype(np.float32)]))


def edit_tile_meta(key, value):
    """A bundle edit setting the first tile's `key` to `value`."""
    return lambda meta, tensors: meta["tiles"][0].__setitem__(key, value)


def edit_noise_meta(key, value):
    """A bundle edit setting the noise metadata's `key` to `value`."""
    return lambda meta, tensors: meta["noise"].__setitem__(key, value)


def edit_tensor(name, make):
    """A bundle edit replacing tensor `name` with make(it), or removing it where that is None."""
    def edit(meta, tensors):
        tensors[name] = make(tensors[name])
        if tensors[name] is None:
            del tensors[name]
    return edit


HOSTILE = {
    "scale NaN": (edit_tile_meta("scale", float("nan")), "scale must be a finite number"),
    "scale 0": (edit_tile_meta("scale", 0), "scale must be a finite number"),
    "scale text": (edit_tile_meta("scale", "1"), "scale must be a number"),
    "9 coefficients": (edit_noise_meta("coefficients", 9), "between 1 and 8"),
    "coefficients 2.5": (edit_noise_meta("coefficients", 2.5), "must be an integer"),
    "coefficients missing": (edit_noise_meta("coefficients", None), "must be an integer"),
    "unknown codec": (edit_noise_meta("codec", "zip"), "unknown coefficient codec"),
    "band rows 0": (edit_tile_meta("band_rows", 0), "band rows must be between 1 and 24"),
    "band rows past the tile": (edit_tile_meta("band_rows", 25), "band rows must be between 1 and 24"),
    "band rows missing": (edit_tile_meta("band_rows", None), "band rows must be an integer"),
    "float dtype": (edit_noise_meta("dtype", "float16"), "unknown noise dtype"),
    "one coefficient fewer": (edit_noise_meta("coefficients", 4), "do not hold exactly"),
    "basis missing": (edit_tensor("tile_0000_basis", lambda t: None), "is missing"),
    "basis NaN": (edit_tensor("tile_0000_basis", lambda t: np.full_like(t, np.nan)), "basis holds NaN"),
    "basis float16": (edit_tensor("tile_0000_basis", lambda t: t.astype(np.float16)), "expected float32"),
    "offset short": (edit_tensor("tile_0000_offset", lambda t: t[:89]), "offset is"),
    "escapes outside": (edit_tensor("tile_0000_escapes", lambda t: np.array([10 ** 6], np.int32)), "inside the tile"),
    "escapes repeated": (edit_tensor("tile_0000_escapes", lambda t: np.array([0, 0], np.int32)), "strictly increasing"),
    "escape noise Inf": (lambda meta, tensors: tensors.update(
        tile_0000_escapes=np.array([0], np.int32), tile_0000_escape_noise=np.full((1, 90), np.inf, np.float16)),
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
    folder, _, _, model = demo
    edit, message = HOSTILE[case]
    rewrite_bundle(folder / "compact.bundle", folder / "bad.bundle", edit, model)
    with pytest.raises(UserError, match=message):
        hidden_bundle(folder / "bad.bundle", model)


def test_a_space_from_no_solved_pixel_is_zero_not_nan():
    """A sample none of whose pixels the solver reached (a barely fitted fog) gives the zero offset and basis: the
    tile's own solve then reports the pixels it cannot reach (exit 3), where a mean of nothing made the offset NaN
    and the hide stopped on its own bundle."""
    from noisenerf.train.hide.compact import principal_basis

    offset, basis = principal_basis(torch.zeros(0, 6), 3)
    assert torch.equal(offset, torch.zeros(6)) and torch.equal(basis, torch.zeros(6, 3))
    offset, basis = principal_basis(torch.tensor([[1.0, 2.0], [3.0, 2.0]]), 2)
    assert torch.equal(offset, torch.tensor([2.0, 2.0])) and torch.equal(basis[:, 0].abs(), torch.tensor([1.0, 0.0]))
