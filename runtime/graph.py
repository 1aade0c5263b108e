"""The graph a noisenerf model file holds, as a pure function of its architecture.

A model is trusted only as far as its fingerprint reaches. The fingerprint covers the weights and the
architecture (runtime.fingerprint); this module extends it to the graph: `field_graph` derives, from the
architecture in the model's metadata, every node, attribute, constant, port and opset the export writes
(export.onnx_export builds the ONNX graph from this same description), and `check_graph` compares a
model file's graph with it, field by field. Any extra, missing or changed node, attribute, constant,
opset, initializer or port shape is refused before a session exists, so a model whose weights and
metadata are genuine cannot compute anything but the scene's fields.

The rule, for any implementation (the browser reveal implements the same): read the architecture from
the metadata (it is in the fingerprint), rebuild this node list, and require the file's graph to be
exactly it — nodes in order with their op types, default domain, input and output names and integer
attributes; initializers exactly the weights (name, shape; values checked by the fingerprint) and the
constants (name, dtype, shape, values); inputs and outputs with their element types and shapes, the
batch axis symbolic; one opset import, the default domain at OPSET. Node names and doc strings are not
compared (they compute nothing).

Layout, per distinct encoding (shared by coarse and fine networks when their frequencies agree):
γ(v) = [v, sin(2⁰v), cos(2⁰v), …] by Unsqueeze → Mul → Sin, Cos → Unsqueeze → Concat → Reshape → Concat
(paper eq. 4, nerf-pytorch's order); noise is added to [γ(x) ‖ γ(d)] and split again (eq. 4–5); each
network is nn.Linear's layers as Gemm(transB=1) with ReLU and its skip Concat, then sigmoid colour and
ReLU density (σ squeezed to (n,)).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from noisenerf.runtime.encoding import encoding_dims
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_FREQUENCIES, checked_int, checked_list

if TYPE_CHECKING:
    from noisenerf.runtime.onnx_file import ModelFile

OPSET = 17
IR_VERSION = 8  # the ONNX IR of opset 17, readable by every onnxruntime this package supports
FLOAT, INT64 = 1, 7  # TensorProto.DataType
INPUT_NAMES = ("points", "viewdirs", "noise")
OUTPUT_NAMES = ("rgb", "sigma")  # the render network: the fine one where the model has both
COARSE_OUTPUT_NAMES = ("rgb_coarse", "sigma_coarse")  # the coarse network, present only beside a fine one
BATCH = "n"  # the symbolic batch axis of every port


@dataclass(frozen=True)
class Node:
    """One graph node: op type (default domain), input and output value names, integer attributes."""

    op: str
    inputs: tuple[str, ...]
    outputs: tuple[str, ...]
    attributes: tuple[tuple[str, int], ...] = ()


@dataclass(frozen=True)
class Port:
    """A graph input or output: name, element type, shape (BATCH for the free batch axis)."""

    name: str
    shape: tuple[int | str, ...]
    elem_type: int = FLOAT


@dataclass(frozen=True, eq=False)
class FieldGraph:
    """Everything a model's graph must be: nodes in order, constants (name -> array), weights (name ->
    shape, nn.Linear's (out, in) and (out,)), ports."""

    nodes: tuple[Node, ...]
    constants: dict[str, np.ndarray]
    weights: dict[str, tuple[int, ...]]
    inputs: tuple[Port, ...]
    outputs: tuple[Port, ...]


class GraphBuilder:
    """Collects nodes and constants; a value computed once (an encoding) is reused by name."""

    def __init__(self):
        self.nodes: list[Node] = []
        self.constants: dict[str, np.ndarray] = {}
        self.weights: dict[str, tuple[int, ...]] = {}

    def add(self, op: str, inputs: tuple[str, ...], output: str, **attributes: int) -> str:
        self.nodes.append(Node(op, tuple(inputs), (output,), tuple(sorted(attributes.items()))))
        return output

    def constant(self, name: str, values: np.ndarray) -> str:
        self.constants.setdefault(name, values)
        return name

    def linear(self, prefix: str, layer: str, x: str, fan_in: int, fan_out: int) -> str:
        """nn.Linear `prefix.layer` on x: Gemm(x, W (out, in), b, transB=1)."""
        weight, bias = f"{prefix}.{layer}.weight", f"{prefix}.{layer}.bias"
        self.weights[weight], self.weights[bias] = (fan_out, fan_in), (fan_out,)
        return self.add("Gemm", (x, weight, bias), f"{prefix}.{layer}", transB=1)

    def computed(self, name: str) -> bool:
        return any(name in node.outputs for node in self.nodes)

    def encoding(self, x: str, n_freqs: int) -> str:
        """γ(x) of an (n, 3) value -> (n, 3 + 6·n_freqs), computed once per (input, frequencies)."""
        name = f"gamma.{x}.{n_freqs}"
        if self.computed(name):
            return name
        axis1 = self.constant("axes.1", np.array([1], np.int64))
        axis2 = self.constant("axes.2", np.array([2], np.int64))
        freqs = self.constant(f"freqs.{n_freqs}", (2.0 ** np.arange(n_freqs, dtype=np.float32))[:, None])
        scaled = self.add("Mul", (self.add("Unsqueeze", (x, axis1), f"{name}.x"), freqs), f"{name}.scaled")
        sin = self.add("Unsqueeze", (self.add("Sin", (scaled,), f"{name}.sin"), axis2), f"{name}.sin4")
        cos = self.add("Unsqueeze", (self.add("Cos", (scaled,), f"{name}.cos"), axis2), f"{name}.cos4")
        bands = self.add("Concat", (sin, cos), f"{name}.bands4", axis=2)
        flat = self.add("Reshape", (bands, self.constant("shape.flat", np.array([0, -1], np.int64))), f"{name}.bands")
        return self.add("Concat", (x, flat), name, axis=1)

    def noisy_inputs(self, config: dict) -> tuple[str, str | None]:
        """γ(x) + noise, or [γ(x) ‖ γ(d)] + noise split back into its γ(x) and γ(d) parts (the latter None
        without view directions), computed once per frequencies."""
        xyz = self.encoding("points", config["xyz_freqs"])
        if not config["use_viewdirs"]:
            name = f"{xyz}+noise"
            return (name if self.computed(name) else self.add("Add", (xyz, "noise"), name)), None
        dirs = self.encoding("viewdirs", config["dir_freqs"])
        name = f"{xyz}|{dirs}+noise"
        if not self.computed(name):
            self.add("Add", (self.add("Concat", (xyz, dirs), f"{xyz}|{dirs}", axis=1), "noise"), name)
            sizes = self.constant(f"split.{config['xyz_freqs']}.{config['dir_freqs']}", np.array(
                [encoding_dims(config["xyz_freqs"]), encoding_dims(config["dir_freqs"])], np.int64))
            self.nodes.append(Node("Split", (name, sizes), (f"{name}.xyz", f"{name}.dirs"), (("axis", 1),)))
        return f"{name}.xyz", f"{name}.dirs"

    def network(self, prefix: str, config: dict, rgb: str, sigma: str) -> None:
        """One NeRF MLP (train.scene.field.NeRFField, layer for layer) -> outputs rgb (n, 3), sigma (n,)."""
        xyz, dirs = self.noisy_inputs(config)
        xyz_dims, width = encoding_dims(config["xyz_freqs"]), config["width"]
        h, fan_in = xyz, xyz_dims
        for i in range(config["depth"]):
            h = self.add("Relu", (self.linear(prefix, f"pts_linears.{i}", h, fan_in, width),), f"{prefix}.h{i}")
            fan_in = width
            if i in config["skips"]:
                h, fan_in = self.add("Concat", (xyz, h), f"{prefix}.skip{i}", axis=1), width + xyz_dims
        if config["use_viewdirs"]:
            density = self.linear(prefix, "alpha_linear", h, width, 1)
            feature = self.linear(prefix, "feature_linear", h, width, width)
            branch = self.add("Concat", (feature, dirs), f"{prefix}.branch", axis=1)
            hidden = self.linear(prefix, "views_linears.0", branch, width + encoding_dims(config["dir_freqs"]),
                                 width // 2)
            raw_rgb = self.linear(prefix, "rgb_linear", self.add("Relu", (hidden,), f"{prefix}.views"), width // 2, 3)
        else:
            raw = self.linear(prefix, "output_linear", h, width, 4)
            sizes = self.constant("split.rgb_density", np.array([3, 1], np.int64))
            raw_rgb, density = f"{prefix}.raw_rgb", f"{prefix}.raw_density"
            self.nodes.append(Node("Split", (raw, sizes), (raw_rgb, density), (("axis", 1),)))
        self.add("Sigmoid", (raw_rgb,), rgb)
        self.add("Squeeze", (self.add("Relu", (density,), f"{prefix}.sigma"), self.constant("axes.1", np.array(
            [1], np.int64))), sigma)


def checked_network(config, what: str) -> dict:
    """A network's architecture as metadata states it (train.scene.field.FieldConfig's fields), every number
    within the caps before a graph is derived from it."""
    if not isinstance(config, dict) or set(config) != {"depth", "width", "skips", "xyz_freqs", "dir_freqs",
                                                       "use_viewdirs"}:
        raise UserError(f"the {what} network's architecture must have exactly depth, width, skips, xyz_freqs, "
                        "dir_freqs and use_viewdirs")
    depth = checked_int(config["depth"], f"{what} depth", 1, MAX_FIELD_DEPTH)
    skips = [checked_int(skip, f"{what} skip", 0, depth - 1) for skip in checked_list(
        list(config["skips"]) if isinstance(config["skips"], tuple) else config["skips"], "skips", most=depth)]
    if not isinstance(config["use_viewdirs"], bool):
        raise UserError(f"the {what} network's use_viewdirs must be true or false")
    return {"depth": depth, "width": checked_int(config["width"], f"{what} width", 2, MAX_FIELD_WIDTH),
            "skips": sorted(set(skips)), "use_viewdirs": config["use_viewdirs"],
            **{key: checked_int(config[key], f"{what} {key}", 0, MAX_FREQUENCIES) for key in ("xyz_freqs", "dir_freqs")}}


def field_graph(architecture: dict, noise_dims: int) -> FieldGraph:
    """The graph of a model with this architecture ({"coarse": FieldConfig dict, "fine": … | None}) and
    noise width: outputs rgb, sigma of the render network (the fine one where there is one), then
    rgb_coarse, sigma_coarse beside a fine network. Refuses an architecture out of the caps (UserError)."""
    builder = GraphBuilder()
    architecture = {name: None if config is None else checked_network(config, name)
                    for name, config in architecture.items()}
    fine = architecture.get("fine")
    outputs = [Port("rgb", (BATCH, 3)), Port("sigma", (BATCH,))]
    if fine is None:
        builder.network("coarse", architecture["coarse"], *OUTPUT_NAMES)
    else:
        builder.network("fine", fine, *OUTPUT_NAMES)
        builder.network("coarse", architecture["coarse"], *COARSE_OUTPUT_NAMES)
        outputs += [Port("rgb_coarse", (BATCH, 3)), Port("sigma_coarse", (BATCH,))]
    inputs = (Port("points", (BATCH, 3)), Port("viewdirs", (BATCH, 3)), Port("noise", (BATCH, noise_dims)))
    return FieldGraph(tuple(builder.nodes), builder.constants, builder.weights, inputs, tuple(outputs))


def refuse(source: str, what: str) -> UserError:
    return UserError(f"{source}: the model's graph is not the one its scene exports: {what}; export the scene again")


def describe(node: Node) -> str:
    attributes = "".join(f", {name}={value}" for name, value in node.attributes)
    return f"{node.op}({', '.join(node.inputs)}{attributes}) -> {', '.join(node.outputs)}"


def check_graph(file: ModelFile, expected: FieldGraph, source: str) -> dict[str, np.ndarray]:
    """Refuse (UserError) a model file whose graph differs from `expected` in any node, attribute, constant,
    initializer, port or opset; return its weights (name -> float32 array) for the fingerprint check."""
    if file.unexpected:
        raise refuse(source, f"it holds {file.unexpected[0]}")
    for kind, got, want in (("inputs", file.inputs, expected.inputs), ("outputs", file.outputs, expected.outputs)):
        if got != want:
            raise refuse(source, f"its {kind} are {[port and (port.name, port.shape) for port in got]}, expected "
                                 f"{[(port.name, port.shape) for port in want]}")
    if file.opsets != (("", OPSET),):
        raise refuse(source, f"it imports opsets {list(file.opsets)}, not [('', {OPSET})]")
    for i, (got, want) in enumerate(zip(file.nodes, expected.nodes)):
        if got != want:
            raise refuse(source, f"node {i} is {describe(got)}, expected {describe(want)}")
    if len(file.nodes) != len(expected.nodes):
        more = len(file.nodes) - len(expected.nodes)
        raise refuse(source, f"it has {abs(more)} {'more' if more > 0 else 'fewer'} nodes than the "
                             f"{len(expected.nodes)} expected")
    records = {}
    for record in file.initializers:
        if record.name in records:
            raise refuse(source, f"initializer {record.name!r} appears twice")
        records[record.name] = record
    names, wanted = set(records), set(expected.weights) | set(expected.constants)
    if names != wanted:
        odd = sorted(names - wanted) or sorted(wanted - names)
        raise refuse(source, f"initializer {odd[0]!r} is {'extra' if names - wanted else 'missing'}")
    for name, values in expected.constants.items():
        got = records[name].array(source, INT64 if values.dtype == np.int64 else FLOAT)
        if got.shape != values.shape or not np.array_equal(got, values):
            raise refuse(source, f"constant {name!r} holds {got.ravel()[:4].tolist()}…, expected "
                                 f"{values.ravel()[:4].tolist()}…")
    weights = {}
    for name, shape in expected.weights.items():
        if records[name].dims != shape:
            raise refuse(source, f"weight {name!r} has shape {list(records[name].dims)}, expected {list(shape)}")
        weights[name] = records[name].array(source)
    return weights
