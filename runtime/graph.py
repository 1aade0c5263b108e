"""The graph a noisenerf model file holds, and the rule that binds a model file to it.

A model is trusted only as far as its fingerprint reaches. The fingerprint covers the weights and the
architecture (runtime.fingerprint); the graph extends it: `runtime.fields.field_graph` derives, from the
architecture in the model's metadata, every node, attribute, constant, port and opset the export writes
(export.onnx_export builds the ONNX graph from this same description; each network's part is written by
its field kind, runtime.fields), and `check_graph` here compares a model file's graph with it, field by
field. Any extra, missing or changed node, attribute, constant, opset, initializer or port shape is
refused before a session exists, so a model whose weights and metadata are genuine cannot compute
anything but the scene's fields.

The rule, for any implementation (the browser reveal implements the same): read the architecture from
the metadata (it is in the fingerprint), rebuild the node list, and require the file's graph to be
exactly it — nodes in order with their op types, default domain, input and output names and integer
attributes; initializers exactly the weights (name, shape; values checked by the fingerprint) and the
constants (name, dtype, shape, values); inputs and outputs with their element types and shapes, the
batch axis symbolic; one opset import, the default domain at the graph's opset (the highest its field
kinds need). Node names and doc strings are not compared (they compute nothing).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from noisenerf.runtime.errors import UserError

if TYPE_CHECKING:
    from noisenerf.runtime.onnx_file import ModelFile

IR_VERSION = 8  # the ONNX IR of opsets 17 and 18, readable by every onnxruntime this package supports
FLOAT, INT64 = 1, 7  # TensorProto.DataType
INPUT_NAMES = ("points", "viewdirs", "noise")
OUTPUT_NAMES = ("rgb", "sigma")  # the render network: the fine one where the model has both
COARSE_OUTPUT_NAMES = ("rgb_coarse", "sigma_coarse")  # the coarse network, present only beside a fine one
BATCH = "n"  # the symbolic batch axis of every port


def proposal_output(index: int) -> str:
    """The output of a scene's proposal network `index` (density only; runtime.fields.nerfacto)."""
    return f"sigma_proposal{index}"


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
    shape, nn.Linear's (out, in) and (out,), tables), ports, the default domain's opset."""

    nodes: tuple[Node, ...]
    constants: dict[str, np.ndarray]
    weights: dict[str, tuple[int, ...]]
    inputs: tuple[Port, ...]
    outputs: tuple[Port, ...]
    opset: int


class GraphBuilder:
    """Collects nodes, constants and weights; a value computed once (an encoding) is reused by name. The
    field kinds (runtime.fields) write their networks with it."""

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

    def split(self, x: str, sizes: str, outputs: tuple[str, ...], axis: int = 1) -> tuple[str, ...]:
        """Split x along `axis` into `outputs` of the sizes held by the constant `sizes`."""
        self.nodes.append(Node("Split", (x, sizes), outputs, (("axis", axis),)))
        return outputs

    def computed(self, name: str) -> bool:
        return any(name in node.outputs for node in self.nodes)

    def noisy_pair(self, position: str, direction: str, add_sizes) -> tuple[str, str]:
        """[position ‖ direction] + noise split back into its two segments, computed once per pair of
        encodings (paper eq. 4–5); `add_sizes()` adds the constant holding their widths, after the Add
        (the constants' order is the file's), and returns its name."""
        name = f"{position}|{direction}+noise"
        if not self.computed(name):
            self.add("Add", (self.add("Concat", (position, direction), f"{position}|{direction}", axis=1), "noise"),
                     name)
            self.split(name, add_sizes(), (f"{name}.xyz", f"{name}.dirs"))
        return f"{name}.xyz", f"{name}.dirs"

def refuse(source: str, what: str, code: str, **params) -> UserError:
    return UserError(f"{source}: the model's graph is not the one its scene exports: {what}; export the scene again",
                     code=code, **params)


def describe(node: Node) -> str:
    attributes = "".join(f", {name}={value}" for name, value in node.attributes)
    return f"{node.op}({', '.join(node.inputs)}{attributes}) -> {', '.join(node.outputs)}"


def check_graph(file: ModelFile, expected: FieldGraph, source: str) -> dict[str, np.ndarray]:
    """Refuse (UserError) a model file whose graph differs from `expected` in any node, attribute, constant,
    initializer, port or opset; return its weights (name -> float32 array) for the fingerprint check."""
    if file.unexpected:
        raise refuse(source, f"it holds {file.unexpected[0]}", "graph.unexpected_field", field=file.unexpected[0])
    for kind, got, want in (("inputs", file.inputs, expected.inputs), ("outputs", file.outputs, expected.outputs)):
        if got != want:
            raise refuse(source, f"its {kind} are {[port and (port.name, port.shape) for port in got]}, expected "
                                 f"{[(port.name, port.shape) for port in want]}", "graph.ports", ports=kind,
                         names=[port and port.name[:60] for port in got[:16]], expected=[port.name for port in want])
    if file.opsets != (("", expected.opset),):
        raise refuse(source, f"it imports opsets {list(file.opsets)}, not [('', {expected.opset})]", "graph.opsets",
                     opsets=[[domain[:60], version] for domain, version in file.opsets[:16]], expected=expected.opset)
    for i, (got, want) in enumerate(zip(file.nodes, expected.nodes)):
        if got != want:
            raise refuse(source, f"node {i} is {describe(got)}, expected {describe(want)}", "graph.node", index=i,
                         op=got.op[:60], expected=want.op)
    if len(file.nodes) != len(expected.nodes):
        more = len(file.nodes) - len(expected.nodes)
        raise refuse(source, f"it has {abs(more)} {'more' if more > 0 else 'fewer'} nodes than the "
                             f"{len(expected.nodes)} expected", "graph.node_count", nodes=len(file.nodes),
                     expected=len(expected.nodes))
    records = {}
    for record in file.initializers:
        if record.name in records:
            raise refuse(source, f"initializer {record.name!r} appears twice", "graph.initializer_twice",
                         name=record.name[:60])
        records[record.name] = record
    names, wanted = set(records), set(expected.weights) | set(expected.constants)
    if names != wanted:
        odd = sorted(names - wanted) or sorted(wanted - names)
        if names - wanted:
            raise refuse(source, f"initializer {odd[0]!r} is extra", "graph.initializer_extra", name=odd[0][:60])
        raise refuse(source, f"initializer {odd[0]!r} is missing", "graph.initializer_missing", name=odd[0])
    for name, values in expected.constants.items():
        got = records[name].array(source, INT64 if values.dtype == np.int64 else FLOAT)
        if got.shape != values.shape or not np.array_equal(got, values):
            raise refuse(source, f"constant {name!r} holds {got.ravel()[:4].tolist()}…, expected "
                                 f"{values.ravel()[:4].tolist()}…", "graph.constant", name=name)
    weights = {}
    for name, shape in expected.weights.items():
        if records[name].dims != shape:
            raise refuse(source, f"weight {name!r} has shape {list(records[name].dims)}, expected {list(shape)}",
                         "graph.weight_shape", name=name, shape=list(records[name].dims), expected=list(shape))
        weights[name] = records[name].array(source)
    return weights
