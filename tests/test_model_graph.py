"""A model is what its fingerprint says, graph included (runtime/graph.py).

The exported graph is rebuilt from the architecture in the model's metadata and compared node for node
before onnxruntime sees the bytes: a model with genuine weights and metadata but an added, removed or
changed node, a changed attribute, constant, opset or port is refused with one line, exit code 2, fast,
and without a session ever being created.
"""

from __future__ import annotations

import time

import numpy as np
import onnx
import pytest
from onnx import helper, numpy_helper

from helpers import assert_refused, make_tiny_scene, run_reveal
from noisenerf.export.onnx_export import export_scene
from noisenerf.runtime import session as session_module
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields import field_graph
from noisenerf.runtime.model import load_model
from noisenerf.train.scene.random_scene import SMALL_HASHGRID

REFUSAL = "the model's graph is not the one its scene exports"
HASHGRID = SMALL_HASHGRID.to_dict()


@pytest.fixture(scope="module", params=[{}, {"fine": True}, {"kind": "hashgrid"}],
                ids=["coarse", "coarse+fine", "hashgrid"])
def exported(request, tmp_path_factory):
    """(the exported model file, its ModelProto) of a tiny scene: an MLP with and without a fine network, a
    hash grid."""
    folder = tmp_path_factory.mktemp("graph")
    make_tiny_scene(seed=3, **request.param).save(folder / "scene")
    export_scene(folder / "scene", folder / "model.onnx")
    return folder / "model.onnx", onnx.load(str(folder / "model.onnx"))


def copy_of(model: onnx.ModelProto) -> onnx.ModelProto:
    clone = onnx.ModelProto()
    clone.CopyFrom(model)
    return clone


def offset_colours(model):
    """The attack of issue 25: the genuine rgb output, plus a constant-shaped zero sum (allocating on
    demand) and a small constant, under the same output name."""
    model = copy_of(model)
    rgb = next(node for node in model.graph.node if "rgb" in node.output)
    rgb.output[0] = "rgb_genuine"
    model.graph.node.extend([
        helper.make_node("Constant", [], ["shape"], value=numpy_helper.from_array(np.array([4], np.int64))),
        helper.make_node("ConstantOfShape", ["shape"], ["zeros"]),
        helper.make_node("ReduceSum", ["zeros"], ["zero"], keepdims=0),
        helper.make_node("Add", ["rgb_genuine", "zero"], ["rgb"])])
    return model


def appended_node(model):
    """An extra node computing something no output uses."""
    model = copy_of(model)
    model.graph.node.append(helper.make_node("Identity", ["rgb"], ["unused"]))
    return model


def removed_node(model):
    model = copy_of(model)
    relu = next(i for i, node in enumerate(model.graph.node) if node.op_type == "Relu")
    relu_output, relu_input = model.graph.node[relu].output[0], model.graph.node[relu].input[0]
    del model.graph.node[relu]
    for node in model.graph.node:
        node.input[:] = [relu_input if name == relu_output else name for name in node.input]
    return model


def changed_attribute(model):
    model = copy_of(model)
    gemm = next(node for node in model.graph.node if node.op_type == "Gemm")
    next(attribute for attribute in gemm.attribute if attribute.name == "transB").i = 0
    return model


def swapped_activation(model):
    model = copy_of(model)
    next(node for node in model.graph.node if node.op_type == "Relu").op_type = "Sigmoid"
    return model


def changed_opset(model):
    model = copy_of(model)
    model.opset_import[0].version += 1
    return model


def changed_constant(model):
    """The encoding's frequencies (the hash grid's primes) doubled: the same weights see other inputs."""
    model = copy_of(model)
    index = next(i for i, t in enumerate(model.graph.initializer) if t.name.startswith(("freqs.", "grid.primes")))
    values = numpy_helper.to_array(model.graph.initializer[index]) * 2
    model.graph.initializer[index].CopyFrom(numpy_helper.from_array(values, model.graph.initializer[index].name))
    return model


def changed_port(model):
    model = copy_of(model)
    model.graph.output[0].type.tensor_type.shape.dim[1].dim_value = 4
    return model


def extra_value_info(model):
    model = copy_of(model)
    model.graph.value_info.append(helper.make_tensor_value_info("rgb", onnx.TensorProto.FLOAT, ["n", 3]))
    return model


TAMPERINGS = {"offset colours": (offset_colours, "-> rgb_genuine, expected"),
              "appended node": (appended_node, "1 more nodes"), "removed node": (removed_node, "node"),
              "transB": (changed_attribute, "transB=0"), "activation": (swapped_activation, "Sigmoid"),
              "opset": (changed_opset, "opsets"), "constant": (changed_constant, "constant '"),
              "port": (changed_port, "outputs"), "value_info": (extra_value_info, "graph field 13")}


@pytest.mark.parametrize("name", TAMPERINGS)
def test_a_tampered_graph_is_refused_fast_before_any_session(exported, name, tmp_path, monkeypatch):
    path, model = exported
    tamper, detail = TAMPERINGS[name]
    onnx.save_model(tamper(model), str(tmp_path / "tampered.onnx"))

    def no_session(*args, **kwargs):
        raise AssertionError("an onnxruntime session was created for a tampered model")

    monkeypatch.setattr(session_module.ort, "InferenceSession", no_session)
    started = time.perf_counter()
    with pytest.raises(UserError, match=REFUSAL) as refusal:
        load_model(tmp_path / "tampered.onnx")
    assert time.perf_counter() - started < 1.0
    assert detail in str(refusal.value) and "export the scene again" in str(refusal.value)


def test_the_attack_is_refused_by_the_cli_in_one_line(exported, tmp_path):
    path, model = exported
    onnx.save_model(offset_colours(model), str(tmp_path / "tampered.onnx"))
    result = run_reveal(tmp_path / "tampered.onnx", "--view", 0, "-o", tmp_path / "out.png")
    assert_refused(result, tmp_path / "out.png", REFUSAL)


def test_the_export_is_node_for_node_the_graph_the_runtime_derives(exported):
    path, model = exported
    metadata = load_model(path).metadata
    expected = field_graph(metadata.architecture, metadata.noise_dims)
    assert [(n.op_type, tuple(n.input), tuple(n.output)) for n in model.graph.node] == \
        [(n.op, n.inputs, n.outputs) for n in expected.nodes]
    assert {t.name for t in model.graph.initializer} == set(expected.weights) | set(expected.constants)


@pytest.mark.parametrize("architecture, message", [
    ({"coarse": {"depth": 10 ** 9, "width": 8, "skips": [], "xyz_freqs": 2, "dir_freqs": 1, "use_viewdirs": True},
      "fine": None}, "depth"),
    ({"coarse": {"depth": 2, "width": 8, "skips": [5], "xyz_freqs": 2, "dir_freqs": 1, "use_viewdirs": True},
      "fine": None}, "skip"),
    ({"coarse": {"depth": 2, "width": 8, "skips": [], "xyz_freqs": 2, "dir_freqs": 1}, "fine": None}, "exactly"),
    ({"coarse": {**HASHGRID, "levels": 33}, "fine": None}, "levels must be between 1 and 32"),
    ({"coarse": {**HASHGRID, "log2_table": 25}, "fine": None}, "log2_table must be between 3 and 24"),
    ({"coarse": {**HASHGRID, "levels": 16, "per_level_scale": 4.0}, "fine": None}, "finest level has"),
    ({"coarse": {**HASHGRID, "levels": 32, "features": 8, "log2_table": 24, "per_level_scale": 1.0, "base_resolution": 4096},
      "fine": None}, "tables hold"),
    ({"coarse": {**HASHGRID, "aabb": [0, 0, 0, 1, -1, 1]}, "fine": None}, "min < max"),
    ({"coarse": {**HASHGRID, "sh_degree": 5}, "fine": None}, "sh_degree must be between 1 and 4"),
    ({"coarse": {key: value for key, value in HASHGRID.items() if key != "aabb"}, "fine": None}, "exactly"),
    ({"coarse": {**HASHGRID, "kind": "triplane"}, "fine": None}, "of kind 'triplane'; this noisenerf knows"),
])
def test_an_architecture_out_of_the_caps_derives_no_graph(architecture, message):
    with pytest.raises(UserError, match=message):
        field_graph(architecture, 30)
