"""The exported ONNX fields are self-contained, carry their metadata and weights, and render what torch renders."""

import json

import numpy as np
import onnx
import pytest

from helpers import make_tiny_scene
from noisenerf.export import onnx_export
from noisenerf.export.onnx_export import export_scene, probe_parity
from noisenerf.runtime.bundle import Tile
from noisenerf.runtime.layouts import VectorNoise
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fingerprint import weights_fingerprint
from noisenerf.runtime.fields import field_graph
from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.model import grid_from_dict, grid_to_dict, load_model
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.render import MarchingSampler, render_view
from noisenerf.runtime.reveal import render_tile
from noisenerf.runtime.session import OnnxField, read_model_file
from noisenerf.train.scene.render import numpy_field

KINDS = {"plain": {}, "ndc": {"ndc": True}, "fine": {"fine": True}}


def partial_grid(scene, seed: int = 0) -> OccupancyGrid:
    """About half the cells occupied, so that skipping and the bit packing are both exercised."""
    occupied = np.random.default_rng(seed).random((scene.config.grid_resolution,) * 3) < 0.5
    return OccupancyGrid(scene.config.aabb, occupied)


@pytest.fixture(scope="module", params=list(KINDS))
def exported(request, tmp_path_factory):
    """(scene, model path, export report) for a tiny plain, NDC and fine-net scene."""
    scene = make_tiny_scene(seed=1, **KINDS[request.param])
    scene.grid = partial_grid(scene)
    directory = tmp_path_factory.mktemp(request.param)
    scene.save(directory / "scene")
    report = export_scene(directory / "scene", directory / "model.onnx")
    return scene, directory / "model.onnx", report


def test_model_is_checked_and_self_contained(exported):
    _, path, report = exported
    model = onnx.load(str(path), load_external_data=False)
    onnx.checker.check_model(model, full_check=True)
    tensors = list(model.graph.initializer) + [attr.t for node in model.graph.node for attr in node.attribute
                                                if attr.type == onnx.AttributeProto.TENSOR]
    assert tensors and not any(onnx.external_data_helper.uses_external_data(t) for t in tensors)
    assert report["bytes"] == path.stat().st_size and report["opset"] == 17
    assert [p.name for p in model.graph.input] == ["points", "viewdirs", "noise"]
    outputs = ["rgb", "sigma"] + (["rgb_coarse", "sigma_coarse"] if report["networks"] == ["coarse", "fine"] else [])
    assert [p.name for p in model.graph.output] == outputs


def test_initializers_are_the_scene_weights(exported):
    """Named and laid out as in the scene directory, so the runtime can recompute the fingerprint; the
    only other initializers are the graph's constants (runtime.graph)."""
    scene, path, _ = exported
    model = onnx.load(str(path))
    initializers = {t.name: onnx.numpy_helper.to_array(t) for t in model.graph.initializer}
    weights = scene.weight_arrays()
    constants = field_graph(scene.config.architecture(), scene.render_field.config.noise_dims).constants
    assert sorted(initializers) == sorted([*weights, *constants])
    for name, value in {**weights, **constants}.items():
        np.testing.assert_array_equal(initializers[name], value)
    assert weights_fingerprint({name: initializers[name] for name in weights},
                               scene.config.architecture()) == scene.fingerprint()


def test_equal_coarse_and_fine_weights_keep_both_initializers(tmp_path):
    """A fine net equal to the coarse one exports with both networks' weights under their own names (a
    tracing exporter merged equal tensors and dropped a name)."""
    scene = make_tiny_scene(seed=3, fine=True)
    scene.fine.load_state_dict(scene.coarse.state_dict())
    scene.save(tmp_path / "scene")
    export_scene(tmp_path / "scene", tmp_path / "model.onnx")
    names = [t.name for t in onnx.load(str(tmp_path / "model.onnx")).graph.initializer]
    assert set(scene.weight_arrays()) <= set(names) and len(names) == len(set(names))
    assert load_model(tmp_path / "model.onnx", threads=1).fingerprint == scene.fingerprint()


def test_metadata_round_trips(exported):
    scene, path, _ = exported
    model = load_model(path, threads=1)
    assert model.fingerprint == scene.fingerprint()
    assert model.render_config == scene.config.render
    assert model.cameras == scene.config.cameras
    assert model.noise_dims == scene.render_field.config.noise_dims
    assert json.dumps(model.metadata.architecture, sort_keys=True) == json.dumps(scene.config.architecture(),
                                                                                 sort_keys=True)
    assert model.sampler().hierarchical == (scene.fine is not None) and list(model.fields()) == list(scene.fields())
    np.testing.assert_array_equal(model.grid.occupied, scene.grid.occupied)
    np.testing.assert_array_equal(model.grid.aabb, scene.grid.aabb)


def test_grid_bits_round_trip_for_any_resolution():
    occupied = np.random.default_rng(3).random((5, 5, 5)) < 0.3  # 125 bits: not a whole number of bytes
    grid = grid_from_dict(grid_to_dict(OccupancyGrid((-1, -2, -3, 1, 2, 3), occupied)))
    np.testing.assert_array_equal(grid.occupied, occupied)


def test_field_outputs_match_torch(exported):
    scene, path, _ = exported
    onnx_field = OnnxField(read_model_file(path), threads=1)
    for name, field in scene.fields().items():
        cases = {case.name: case for case in probe_parity(field, onnx_field.network(name), scene.config.aabb, 7)}
        assert cases["zero"].max_abs_diff <= 1e-5 and cases["normal"].max_abs_diff <= 1e-5
        # ±1e3 noise: float32 itself errs by ~1e-5 there, so the export's float64-anchored criterion applies
        assert all(case.passed for case in cases.values())
        assert cases["huge"].max_abs_diff <= 1e-3
    # the render outputs are the render network
    points = np.zeros((4, 3), np.float32)
    for a, b in zip(onnx_field(points, points), onnx_field.network("fine" if scene.fine else "coarse")(points, points)):
        np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("layout", ["ray", "sample"])
def test_noisy_renders_match_torch(exported, layout):
    scene, path, _ = exported
    config, camera = scene.config.render, scene.config.cameras[1]
    shape = (camera.height, camera.width) + ((config.sampling.n_samples,) if layout == "sample" else ())
    noise = np.random.default_rng(2).normal(size=shape + (scene.render_field.config.noise_dims,))
    tile = Tile((0, 0, camera.width, camera.height), camera, config.sampling, VectorNoise(noise.astype(np.float32)))
    reference = render_tile(tile, config, numpy_field(scene.render_field))
    image = render_tile(tile, config, OnnxField(read_model_file(path), threads=1))
    assert np.abs(image - reference).max() <= 1e-5
    np.testing.assert_array_equal(to_uint8(image), to_uint8(reference))


def test_skipping_render_evaluates_the_same_samples(exported):
    scene, path, _ = exported
    model = load_model(path, threads=1)
    camera = scene.config.cameras[2]
    reference, reference_stats = render_view(camera, scene.config.render, numpy_field(scene.render_field),
                                             MarchingSampler(scene.config.render, scene.grid))
    image, stats = render_view(camera, model.render_config, model.field, MarchingSampler(model.render_config, model.grid))
    assert stats == reference_stats and stats.n_samples_evaluated < stats.n_samples_dense
    assert np.abs(image - reference).max() <= 1e-5


def test_batched_and_noise_free_calls_agree(exported):
    _, path, _ = exported
    field, small = OnnxField(read_model_file(path), threads=1), OnnxField(read_model_file(path), threads=1, batch=7)
    rng = np.random.default_rng(4)
    points, viewdirs = rng.normal(size=(50, 3)).astype(np.float32), rng.normal(size=(50, 3)).astype(np.float32)
    zeros = np.zeros((50, field.noise_dims), np.float32)
    for a, b in zip(field(points, viewdirs), field(points, viewdirs, zeros)):
        np.testing.assert_array_equal(a, b)
    # onnxruntime's GEMM kernels depend on the batch size, so batching may move the last bit
    for a, b in zip(field(points, viewdirs), small(points, viewdirs)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_export_is_deterministic(exported, tmp_path):
    scene, path, _ = exported
    scene.save(tmp_path / "scene")
    export_scene(tmp_path / "scene", tmp_path / "again.onnx")
    assert (tmp_path / "again.onnx").read_bytes() == path.read_bytes()


def test_export_refuses_a_graph_that_disagrees_with_torch(tmp_path, monkeypatch):
    make_tiny_scene(seed=1).save(tmp_path / "scene")
    other = make_tiny_scene(seed=2)  # same architecture, other weights: a faulty export
    real_export = onnx_export.fields_to_onnx
    monkeypatch.setattr(onnx_export, "fields_to_onnx", lambda scene, metadata: real_export(other, metadata))
    with pytest.raises(UserError, match="export refused"):
        export_scene(tmp_path / "scene", tmp_path / "model.onnx")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["scene"]


def test_export_refuses_an_existing_output_without_force(tmp_path):
    make_tiny_scene().save(tmp_path / "scene")
    (tmp_path / "model.onnx").write_bytes(b"keep")
    with pytest.raises(UserError, match="output exists"):
        export_scene(tmp_path / "scene", tmp_path / "model.onnx", force=False)
    assert (tmp_path / "model.onnx").read_bytes() == b"keep"


def test_cuda_without_its_provider_is_refused(exported):
    import onnxruntime

    if "CUDAExecutionProvider" in onnxruntime.get_available_providers():
        pytest.skip("this onnxruntime has CUDA")
    with pytest.raises(UserError, match="cuda"):
        load_model(exported[1], device="cuda")


def test_probe_cases_are_reported(exported):
    scene, _, report = exported
    assert report["networks"] == list(scene.fields())
    assert [(case["network"], case["name"]) for case in report["probe"]] == [
        (network, name) for network in scene.fields() for name in onnx_export.PROBE_NOISE_SCALES]
    assert all(case["passed"] for case in report["probe"])
