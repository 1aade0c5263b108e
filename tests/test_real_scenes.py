"""Real data end to end (skipped where ../shared/data is absent): a lego scene briefly fitted with the
small preset is exported, hides real photos exactly, and onnxruntime agrees with torch within 1e-5."""

import dataclasses

import numpy as np
import pytest
import torch

from helpers import hidden_bundle
from noisenerf.export.onnx_export import export_scene, probe_parity
from noisenerf.runtime.images import load_secret, resize_image
from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.model import load_model
from noisenerf.runtime.render import render_view
from noisenerf.runtime.reveal import render_tile, reveal_tiles
from noisenerf.train.hide.plan import HideConfig
from noisenerf.train.hide.run import hide
from noisenerf.train.scene.datasets import load_dataset
from noisenerf.train.scene.fit import PRESETS, Budget, fit
from noisenerf.train.scene.render import numpy_field
from noisenerf.train.scene.scene import load_scene

CPU = torch.device("cpu")


@pytest.fixture(scope="module")
def lego(shared_data, tmp_path_factory):
    """A lego scene fitted for 150 steps at 40 px with the small preset, and its exported model."""
    folder = tmp_path_factory.mktemp("lego")
    dataset = load_dataset(shared_data / "scenes" / "blender" / "lego", resolution=40)
    config = dataclasses.replace(PRESETS["small"], batch_rays=512)
    fit(dataset, folder / "scene", config, Budget(iters=150), CPU, curve_seconds=0)
    export_scene(folder / "scene", folder / "model.onnx")
    return load_scene(folder / "scene"), load_model(folder / "model.onnx"), folder


def small_photo(shared_data, name_index=0, width=48):
    photo = sorted((shared_data / "secrets" / "imagenet").iterdir())[name_index]
    secret, _, _ = load_secret(photo)
    height = round(secret.shape[0] * width / secret.shape[1])
    return to_uint8(resize_image(secret.astype(np.float32) / 255.0, width, height))


def test_field_parity_on_fitted_lego(lego):
    scene, model, _ = lego
    cases = probe_parity(scene.render_field, model.field, scene.config.aabb, seed=3)
    assert all(case.passed for case in cases)
    assert max(c.max_abs_diff for c in cases if c.name in ("zero", "normal")) <= 1e-5


def test_ordinary_render_parity_on_fitted_lego(lego):
    scene, model, _ = lego
    camera = scene.config.cameras[110]
    ours, ours_stats = render_view(camera, scene.config.render, numpy_field(scene.render_field), scene.sampler())
    theirs, theirs_stats = render_view(camera, model.render_config, model.field, model.sampler())
    assert np.abs(ours - theirs).max() <= 1e-5
    assert (to_uint8(ours) == to_uint8(theirs)).all()
    assert ours_stats.n_samples_evaluated == theirs_stats.n_samples_evaluated


@pytest.mark.parametrize("layout, dtype", [("compact", "int16"), ("ray", "float16"), ("sample", "float32")])
def test_real_photo_hides_exactly_and_reveals_in_onnxruntime(lego, shared_data, layout, dtype):
    scene, model, folder = lego
    secret = small_photo(shared_data)
    report = hide(scene, secret, folder / f"{layout}.bundle", HideConfig(layout=layout, dtype=dtype, view=105),
                  CPU, force=True)
    assert report["exact"], report["tiles"]
    bundle = hidden_bundle(folder / f"{layout}.bundle", model)
    revealed = reveal_tiles(bundle, model.render_config, model.fields(), keep_float=True)
    assert revealed.exact
    np.testing.assert_array_equal(revealed.pixels, secret)
    torch_image = render_tile(bundle.tiles[0], scene.config.render, numpy_field(scene.render_field))
    assert np.abs(torch_image - revealed.image).max() <= 1e-5
