"""A model is its weights and one file; a bundle tile names the network it was hidden through.

On a tiny scene with coarse and fine networks: a model whose weights were changed after export is
refused even with its metadata intact, tensors stored outside the file are refused before onnxruntime
could read them from the recipient's folder, a tile hidden through the coarse network (the paper's
method) reveals through it, and a bundle without the field (made before it existed) still reveals
through the render network.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import onnx
import pytest
from onnx import numpy_helper

from helpers import assert_refused, make_tiny_scene, run_reveal, two_tile_bundle
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime.bundle import load_bundle
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.images import read_native
from noisenerf.runtime.model import load_model
from noisenerf.runtime.onnx_file import parse_model
from noisenerf.runtime.render import render_view
from noisenerf.runtime.reveal import render_tile, reveal_tiles
from noisenerf.train.hide.plan import HideConfig, plan
from noisenerf.train.scene.render import numpy_field, numpy_fields


@pytest.fixture(scope="module")
def fine_model(tmp_path_factory):
    """(scene with a fine network, its exported model, the folder)."""
    folder = tmp_path_factory.mktemp("fine")
    scene = make_tiny_scene(seed=6, fine=True)
    scene.save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return scene, folder / "model.onnx", folder


def tampered(model: onnx.ModelProto, name: str, edit) -> onnx.ModelProto:
    """The model with initializer `name` replaced by edit(its array), metadata untouched."""
    for index, tensor in enumerate(model.graph.initializer):
        if tensor.name == name:
            model.graph.initializer[index].CopyFrom(numpy_helper.from_array(edit(numpy_helper.to_array(tensor)), name))
    return model


def nudge(weights: np.ndarray) -> np.ndarray:
    """One value moved by 1e-3."""
    weights = weights.copy()
    weights.flat[7] += np.float32(1e-3)
    return weights


def test_a_model_with_one_weight_nudged_is_refused(fine_model, tmp_path):
    scene, model, _ = fine_model
    two_tile_bundle(scene).save(tmp_path / "s.bundle")
    onnx.save_model(tampered(onnx.load(str(model)), "fine.pts_linears.1.weight", nudge), str(tmp_path / "nudged.onnx"))
    for target in ([tmp_path / "s.bundle"], ["--view", 1]):
        result = run_reveal(tmp_path / "nudged.onnx", *target, "-o", tmp_path / "out.png")
        assert_refused(result, tmp_path / "out.png", "its weights do not match its fingerprint")


def test_an_external_initializer_is_refused_and_never_read(fine_model, tmp_path):
    """One tensor pointing at a file beside the recipient: refused before any session, whatever the folder."""
    scene, model, _ = fine_model
    two_tile_bundle(scene).save(tmp_path / "s.bundle")
    proto = onnx.load(str(model))
    tensor = next(t for t in proto.graph.initializer if t.name == "coarse.rgb_linear.bias")
    (tmp_path / "weights.bin").write_bytes(tensor.raw_data)
    onnx.external_data_helper.set_external_data(tensor, location="weights.bin")
    tensor.ClearField("raw_data")
    tensor.data_location = onnx.TensorProto.EXTERNAL
    onnx.save_model(proto, str(tmp_path / "external.onnx"))
    for cwd in (tmp_path, model.parent):
        result = run_reveal(tmp_path / "external.onnx", tmp_path / "s.bundle", "-o", tmp_path / "out.png", cwd=cwd)
        assert_refused(result, tmp_path / "out.png", "keeps tensor 'coarse.rgb_linear.bias' in external data")


def with_node(model: onnx.ModelProto, node: onnx.NodeProto) -> bytes:
    model.graph.node.insert(0, node)
    return model.SerializeToString()


def test_tensors_anywhere_outside_the_file_and_subgraphs_are_refused(fine_model):
    """A Constant's external tensor is as dangerous as an initializer's; subgraphs would hide more tensors."""
    model = fine_model[1]
    value = numpy_helper.from_array(np.zeros(3, np.float32), "c")
    onnx.external_data_helper.set_external_data(value, location="weights.bin")
    value.data_location = onnx.TensorProto.EXTERNAL
    constant = onnx.helper.make_node("Constant", [], ["c"], value=value)
    with pytest.raises(UserError, match="keeps tensor 'c' in external data"):
        parse_model(with_node(onnx.load(str(model)), constant), "m.onnx")
    branch = onnx.helper.make_graph([], "branch", [], [])
    subgraph = onnx.helper.make_node("If", ["cond"], [], then_branch=branch, else_branch=branch)
    with pytest.raises(UserError, match="holds subgraphs"):
        parse_model(with_node(onnx.load(str(model)), subgraph), "m.onnx")
    data = model.read_bytes()
    for garbage in (data[:len(data) // 3], b"\xff" * 64):
        with pytest.raises(UserError, match="not a loadable ONNX model"):
            parse_model(garbage, "m.onnx")


def test_paper_hides_through_the_coarse_network_and_exact_through_the_render_network(fine_model):
    scene = fine_model[0]
    secret = np.zeros((4, 5, 3), np.uint8)
    assert {tile.network for tile in plan(scene, secret, HideConfig(method="paper")).tiles} == {"coarse"}
    assert {tile.network for tile in plan(scene, secret, HideConfig(method="exact")).tiles} == {"fine"}
    assert plan(scene, secret, HideConfig(method="paper", network="fine")).tiles[0].network == "fine"


@pytest.mark.parametrize("network", ["coarse", "fine", None])
def test_tiles_reveal_through_their_network(fine_model, tmp_path, network):
    """onnxruntime reveals what torch renders through the tile's network (None: an old bundle, the fine one)."""
    scene, model, _ = fine_model
    bundle = two_tile_bundle(scene, layout="sample", network=network)
    bundle.save(tmp_path / "s.bundle")
    assert all(("network" in tile) == (network is not None) for tile in bundle.metadata()["tiles"])
    loaded, reread = load_model(model, threads=1), load_bundle(tmp_path / "s.bundle")
    assert [tile.network for tile in reread.tiles] == [network] * 2
    torch_field = numpy_field(scene.fields()[network or "fine"])
    other_field = numpy_field(scene.fields()["fine" if network == "coarse" else "coarse"])
    for tile in reread.tiles:
        ours = render_tile(tile, loaded.render_config, loaded.fields()[network or "fine"])
        assert np.abs(ours - render_tile(tile, scene.config.render, torch_field)).max() <= 1e-5
        assert np.abs(ours - render_tile(tile, scene.config.render, other_field)).max() > 1e-2
    result = run_reveal(model, tmp_path / "s.bundle", "-o", tmp_path / "out.png", "--threads", 1)
    assert result.returncode == 0 and result.stdout.startswith("exact: true"), result.stderr
    expected = reveal_tiles(reread, scene.config.render, numpy_fields(scene.fields())).pixels
    np.testing.assert_array_equal(read_native(tmp_path / "out.png"), expected)


def test_a_fine_tile_on_a_model_without_one_is_refused(tmp_path):
    coarse_only = make_tiny_scene(seed=7)
    coarse_only.save(tmp_path / "scene")
    export_scene(tmp_path / "scene", tmp_path / "model.onnx")
    two_tile_bundle(make_tiny_scene(seed=7, fine=True), network="fine").save(tmp_path / "s.bundle")
    dataclasses.replace(load_bundle(tmp_path / "s.bundle"), model_fingerprint=coarse_only.fingerprint()
                        ).save(tmp_path / "s.bundle", replace=True)
    assert_refused(run_reveal(tmp_path / "model.onnx", tmp_path / "s.bundle", "-o", tmp_path / "out.png"),
                   tmp_path / "out.png", "needs the fine network; this model has only coarse")


def test_hierarchical_view_renders_agree_between_torch_and_onnxruntime(fine_model):
    """The same numpy pipeline (coarse → sample_pdf → fine) on either backend, as fit's evaluation uses it.

    The fields agree to ~1e-7, but where a ray's coarse weights are nearly flat sample_pdf moves fine
    samples with those ulps (see test_import_nerf_pytorch.tame_field), and this fresh random net changes
    fast along a ray: a few pixels differ by ~1e-4, the mean by far less."""
    scene, model, _ = fine_model
    loaded = load_model(model, threads=1)
    camera = scene.config.cameras[2]
    ours, stats = render_view(camera, loaded.render_config, loaded.field, loaded.sampler())
    theirs, _ = render_view(camera, scene.config.render, numpy_field(scene.fine), scene.sampler())
    n_coarse, n_importance = scene.config.n_coarse, scene.config.n_importance
    assert stats.n_samples_evaluated == stats.n_samples_dense == stats.n_rays * (2 * n_coarse + n_importance)
    assert np.abs(ours - theirs).max() <= 1e-3 and np.abs(ours - theirs).mean() <= 1e-5
