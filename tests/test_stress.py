"""Numerical stress: every output finite and torch and onnxruntime agreeing at the extremes.

A fast subset runs with the suite; `NOISENERF_STRESS=full` (what `noisenerf bench --stress` sets) runs every
case: noise up to ±1e4, densities near float32 overflow, near/far at 1e-4 and 1e4, grazing and
axis-aligned rays, denormal noise, float16 bundles, and 1-pixel to many-tile secrets.
"""

from __future__ import annotations

import copy
import dataclasses
import os

import numpy as np
import pytest
import torch

from conftest import make_tiny_scene
from noisenerf.export.onnx_export import FLOAT32_SLACK, PROBE_TOLERANCE, export_scene, scaled_error
from noisenerf.runtime import compositing
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.camera import normalize_directions
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.field_callbacks import plain
from noisenerf.runtime.model import load_model
from noisenerf.runtime.rays import RayBatch
from noisenerf.runtime.render import RenderConfig, render_rays
from noisenerf.runtime.reveal import reveal
from noisenerf.runtime.sampling import LAST_DELTA, SamplingConfig
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene import render as rendering
from noisenerf.train.scene.render import numpy_field

FULL = os.environ.get("NOISENERF_STRESS") == "full"
CPU = torch.device("cpu")


def cases(fast: list, full: list) -> list:
    return full if FULL else fast


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    """A tiny scene, its float64 twin and its onnxruntime model."""
    scene = make_tiny_scene(seed=7)
    folder = tmp_path_factory.mktemp("stress")
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return scene, copy.deepcopy(scene.render_field).double(), load_model(folder / "model.onnx", threads=1), folder


def field_inputs(n: int, seed: int, noise_scale: float, dims: int):
    rng = np.random.default_rng(seed)
    points = rng.uniform(-1.5, 1.5, (n, 3)).astype(np.float32)
    viewdirs = normalize_directions(rng.normal(size=(n, 3)))
    noise = (noise_scale * rng.choice([-1.0, 1.0], (n, dims)) * rng.random((n, dims))).astype(np.float32)
    return points, viewdirs, noise


@pytest.mark.parametrize("noise_scale", cases([0.0, 1e2, 1e4], [0.0, 1e-3, 1.0, 1e1, 1e2, 1e3, 3e3, 1e4]))
def test_noisy_field_is_finite_and_onnxruntime_is_as_exact_as_torch(exported, noise_scale):
    scene, reference, model, _ = exported
    points, viewdirs, noise = field_inputs(512, 1, noise_scale, model.noise_dims)
    exact = numpy_field(reference)(points, viewdirs, noise)
    ours, theirs = numpy_field(scene.render_field)(points, viewdirs, noise), model.field(points, viewdirs, noise)
    for exact_part, torch_part, onnx_part in zip(exact, ours, theirs):
        assert np.isfinite(torch_part).all() and np.isfinite(onnx_part).all()
        assert scaled_error(exact_part, onnx_part) <= PROBE_TOLERANCE + FLOAT32_SLACK * scaled_error(exact_part, torch_part)


@pytest.mark.parametrize("sigma", cases([1e30, np.finfo(np.float32).max], [1e10, 1e20, 1e30, 1e37,
                                                                          np.finfo(np.float32).max]))
def test_compositing_near_float32_overflow_is_finite_in_both_backends(sigma):
    rng = np.random.default_rng(2)
    sigmas = (rng.random((64, 16)) * sigma).astype(np.float32)
    deltas = np.concatenate([rng.random((64, 15)) * 10, np.full((64, 1), LAST_DELTA)], axis=1).astype(np.float32)
    rgbs = rng.random((64, 16, 3)).astype(np.float32)
    background = np.ones(3, np.float32)
    expected = compositing.composite(compositing.render_weights(sigmas, deltas), rgbs, background)
    weights = rendering.render_weights(torch.from_numpy(sigmas), torch.from_numpy(deltas))
    got = rendering.composite(weights, torch.from_numpy(rgbs), torch.from_numpy(background)).numpy()
    assert np.isfinite(expected).all() and np.isfinite(got).all()
    assert float(weights.sum(1).max()) <= 1.0 + 1e-6
    assert np.abs(expected - got).max() <= 1e-6


def rays_through_box(directions: np.ndarray, origin_distance: float) -> RayBatch:
    directions = np.asarray(directions, dtype=np.float32)
    unit = normalize_directions(directions)
    return RayBatch((-origin_distance * unit).astype(np.float32), directions, unit)


GRAZING = [[1, 0, 0], [0, 1, 0], [0, 0, -1], [-1, 0, 0], [1, 1e-7, 0], [1, 0, 1e-30], [1, 1, 1], [3e-8, 1, 0]]


@pytest.mark.parametrize("near, far", cases([(1e-4, 1e4)], [(1e-4, 1e4), (1e-4, 4.0), (2.0, 1e4), (0.0, 1e-4)]))
def test_extreme_near_far_grazing_and_axis_aligned_rays_render_alike(exported, near, far):
    scene, _, model, _ = exported
    config = dataclasses.replace(scene.config.render, sampling=SamplingConfig(near, far, 64))
    rays = rays_through_box(GRAZING, origin_distance=3.0)
    ours, _ = render_rays(config, rays, plain(numpy_field(scene.render_field)), scene.grid)
    theirs, _ = render_rays(config, rays, plain(model.field), model.grid)
    assert np.isfinite(ours).all() and np.isfinite(theirs).all()
    assert np.abs(ours - theirs).max() <= 1e-5


def test_zero_length_direction_is_refused_clearly():
    with pytest.raises(UserError, match="zero-length direction"):
        normalize_directions(np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 0.0]], dtype=np.float32))


@pytest.mark.parametrize("tiny", cases([1e-40], [1e-45, 1e-40, 1e-38, 6e-8]))
def test_denormal_noise_renders_like_no_noise(exported, tiny):
    scene, _, model, _ = exported
    points, viewdirs, _ = field_inputs(256, 3, 0.0, model.noise_dims)
    noise = np.full((256, model.noise_dims), tiny, dtype=np.float32)
    for field_fn in (numpy_field(scene.render_field), model.field):
        clean, noisy = field_fn(points, viewdirs, None), field_fn(points, viewdirs, noise)
        for a, b in zip(clean, noisy):
            assert np.isfinite(b).all()
            assert np.abs(a - b).max() <= 1e-6


@pytest.mark.parametrize("height, width, tile", cases([(1, 1, 16), (20, 300, 16)],
                                                      [(1, 1, 16), (1, 700, 16), (700, 1, 16), (20, 300, 16),
                                                       (64, 64, 64)]))
@pytest.mark.parametrize("layout, dtype", [("compact", "int16"), ("ray", "float16"), ("ray", "float32")])
def test_tiny_and_many_tile_secrets_hide_and_reveal_exactly(exported, tmp_path, height, width, tile, layout, dtype):
    scene, _, model, _ = exported
    secret = np.random.default_rng(height * width).integers(0, 256, (height, width, 3), dtype=np.uint8)
    report = hide(scene, secret, tmp_path / "s.bundle", HideConfig(tile_size=tile, layout=layout, dtype=dtype), CPU,
                  show_progress=False)
    assert report["exact"]
    bundle = load_bundle(tmp_path / "s.bundle")
    assert all(np.isfinite(t.noise.stored.astype(np.float32)).all() for t in bundle.tiles)
    revealed = reveal(bundle, model.render_config, model.fields())
    assert revealed.exact
    np.testing.assert_array_equal(revealed.pixels, secret)


@pytest.mark.parametrize("method, layout", [("exact", "compact"), ("exact", "ray"), ("paper", "sample")])
def test_same_seed_same_bundle_bytes(exported, tmp_path, method, layout):
    from noisenerf.train.hide.paper import PaperSettings

    scene = exported[0]
    secret = np.random.default_rng(5).integers(0, 256, (12, 20, 3), dtype=np.uint8)
    config = HideConfig(method=method, tile_size=16, seed=3, n_samples=None if method == "exact" else 4,
                        layout=layout, settings=(PaperSettings(iters=5, record_at=()),))
    for name in ("a", "b"):
        hide(scene, secret, tmp_path / f"{name}.bundle", config, CPU, show_progress=False)
    assert (tmp_path / "a.bundle").read_bytes() == (tmp_path / "b.bundle").read_bytes()
