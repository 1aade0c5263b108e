"""Reading what a model file holds, without the onnx package: its metadata and its weights.

The runtime must know a model's weights before it trusts it (the fingerprint check in runtime.model)
and must refuse tensors stored outside the file before onnxruntime sees it: a session created from
bytes still resolves an external `location` against the current directory, so any file where the
recipient runs could feed the model. onnxruntime exposes neither, so this module reads the protobuf
wire format directly, only the few ONNX fields it needs (field numbers from onnx.proto):

    ModelProto      ir_version 1, graph 7, opset_import 8 (domain 1, version 2), metadata_props 14
                    (key 1, value 2), training_info 20, functions 25
    GraphProto      node 1, initializer 5, input 11, output 12, sparse_initializer 15
    NodeProto       input 1, output 2, op_type 4, attribute 5, domain 7
    AttributeProto  name 1, i 3, t 5, g 6, tensors 10, graphs 11, type 20, sparse_tensor 22, sparse_tensors 23
    ValueInfoProto  name 1, type 2 (TypeProto tensor_type 1: elem_type 1, shape 2: dim 1: value 1, param 2)
    TensorProto     dims 1, data_type 2, float_data 4, int64_data 7, name 8, raw_data 9, external_data 13,
                    data_location 14

The graph's nodes, ports and opsets are read so that runtime.graph can compare them with the graph the
model's architecture exports; fields that compute nothing (names, doc strings) are skipped, and any
other field of a graph or node is recorded as unexpected, which that comparison refuses.

A noisenerf model never has subgraphs, functions, training graphs or sparse tensors, so a model with
any is refused rather than searched: every tensor onnxruntime could load then lies where this module
looks. Everything here is bounded by the file's own size.

The cost of refusing a file is bounded by a constant, not by its size. The checks, in this order (and in
web/src/onnx.js's parseModel):

  1. framing: the model's top-level fields walked by their keys and lengths alone, every payload skipped
     unread: a field number 0, a wire type protobuf does not have, a varint past 10 bytes or the end, a length
     or fixed width past the end, or more than MAX_MODEL_FIELDS fields, is onnx.malformed. Zeros (field 0)
     and random bytes are refused within a few bytes, a well-formed initializer of any size in one step; a
     path's file is checked so before it is read whole (check_model_file), so a junk file is never held;
  2. the walk: the top-level fields in file order (training graphs, functions: onnx.unsupported), the graph's
     fields in file order (sparse initializers, subgraphs and sparse tensors in a node's attributes:
     onnx.unsupported; anything not well formed, and more than MAX_MODEL_FIELDS fields walked in all:
     onnx.malformed);
  3. external data, once everything is read: onnx.external_data.
"""

from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.graph import FLOAT, Node, Port
from noisenerf.runtime.limits import MAX_MODEL_FIELDS

EXTERNAL = 1  # TensorProto.DataLocation.EXTERNAL
VARINT, FIXED64, LENGTH, FIXED32 = 0, 1, 2, 5
UNSUPPORTED = {  # (message, field number) -> what it is
    ("model", 20): "training graphs", ("model", 25): "functions", ("graph", 15): "sparse initializers",
    ("attribute", 6): "subgraphs", ("attribute", 11): "subgraphs", ("attribute", 22): "sparse tensors",
    ("attribute", 23): "sparse tensors",
}


class WireError(ValueError):
    """The bytes are not a well-formed protobuf message."""


class FieldBudget:
    """How many more fields one parse may walk (MAX_MODEL_FIELDS in all): a file of many tiny fields is refused
    after a bounded walk rather than walked to its end."""

    def __init__(self, most: int = MAX_MODEL_FIELDS):
        self.most, self.left = most, most

    def spend(self) -> None:
        self.left -= 1
        if self.left < 0:
            raise WireError(f"more than {self.most} protobuf fields")


def read_varint(data: memoryview, position: int) -> tuple[int, int]:
    """One base-128 varint at `position` -> (value, next position)."""
    value = 0
    for shift in range(0, 70, 7):
        if position >= len(data):
            raise WireError("truncated varint")
        byte = data[position]
        position += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, position
    raise WireError("varint longer than 10 bytes")


def field_head(data: memoryview, position: int, size: int) -> tuple[int, int, int, int]:
    """One field's key and extent, its payload unread: data holds the message from its start at least up to the
    key and its varints; size: the message's length. -> (number, wire type, where the payload starts, the varint's
    value for VARINT, else the payload's length)."""
    key, position = read_varint(data, position)
    number, wire = key >> 3, key & 7
    if number == 0:
        raise WireError("field number 0")
    if wire == VARINT:
        value, position = read_varint(data, position)
        return number, wire, position, value
    if wire in (FIXED64, FIXED32):
        width = 8 if wire == FIXED64 else 4
        if position + width > size:
            raise WireError("truncated fixed-width field")
        return number, wire, position, width
    if wire == LENGTH:
        length, position = read_varint(data, position)
        if position + length > size:
            raise WireError("length-delimited field runs past the end")
        return number, wire, position, length
    raise WireError(f"unsupported wire type {wire}")


def fields(data: memoryview, budget: FieldBudget | None = None) -> Iterator[tuple[int, int, int | memoryview]]:
    """The fields of one message: (field number, wire type, integer or bytes), in file order. budget: the parse's
    (each field spends one)."""
    position, size = 0, len(data)
    while position < size:
        if budget is not None:
            budget.spend()
        number, wire, start, extent = field_head(data, position, size)
        if wire == VARINT:
            value, position = extent, start
        elif wire == LENGTH:
            value, position = data[start:start + extent], start + extent
        else:
            value, position = int.from_bytes(data[start:start + extent], "little"), start + extent
        yield number, wire, value


def framing(read: Callable[[int, int], bytes], size: int, source: str) -> None:
    """Check 1 (the module docstring): a model's top-level fields by their keys and lengths alone, as `fields`
    walks them but with every payload skipped unread. read(position, count): up to count of the model's bytes
    from position; size: how many there are. Refuses with onnx.malformed."""
    budget, position = FieldBudget(), 0
    try:
        while position < size:
            budget.spend()
            head = memoryview(read(position, min(20, size - position)))  # a key and a varint: 10 bytes each at most
            _, wire, start, extent = field_head(head, 0, size - position)
            position += start + (0 if wire == VARINT else extent)
    except WireError as error:
        raise not_onnx(source, error) from None


def not_onnx(source: str, error: ValueError) -> UserError:
    """The refusal of bytes that are not a well-formed model (check 1 or 2), saying why."""
    return UserError(f"{source} is not a loadable ONNX model (not ONNX, or truncated): {error}", code="onnx.malformed")


def check_model_file(path: str | os.PathLike) -> None:
    """A model file's framing (check 1) from its keys and lengths, before it is read whole: a file of junk is
    refused having read a few bytes of it, whatever its size. A path that is not a regular file, or cannot be
    read, is left to the read that follows (model.not_found, and the rest as they were)."""
    path = Path(path)
    if not path.is_file():
        return
    try:
        with path.open("rb") as file:
            def read(position: int, count: int) -> bytes:
                file.seek(position)
                return file.read(count)

            framing(read, os.fstat(file.fileno()).st_size, str(path))
    except OSError:
        return


def field_spans(data: memoryview) -> Iterator[tuple[int, memoryview, int | memoryview]]:
    """The fields of one message with the bytes each occupies (key included): (number, span, value)."""
    position = 0
    for number, wire, value in fields(data):  # re-walk the keys to find where each field ends
        start = position
        _, position = read_varint(data, position)
        if wire == VARINT:
            _, position = read_varint(data, position)
        elif wire in (FIXED64, FIXED32):
            position += 8 if wire == FIXED64 else 4
        else:
            length, position = read_varint(data, position)
            position += length
        yield number, data[start:position], value


def varint(value: int) -> bytes:
    out = bytearray()
    while True:
        byte, value = value & 0x7F, value >> 7
        out.append(byte | (0x80 if value else 0))
        if not value:
            return bytes(out)


def pruned_model(file: "ModelFile", outputs: tuple[str, ...]) -> bytes:
    """The model's bytes with only what computes `outputs`: the other outputs and every node none of them
    needs removed (onnxruntime runs a whole graph whatever is fetched, and drops unused initializers itself).
    The file has passed parse_model, so its fields are well formed."""
    needed, kept = set(outputs), set()
    for index in range(len(file.nodes) - 1, -1, -1):  # nodes are in topological order
        if needed & set(file.nodes[index].outputs):
            kept.add(index)
            needed |= set(file.nodes[index].inputs)
    graph = bytearray()
    node_index = 0
    data = memoryview(file.data)
    model = bytearray()
    for number, span, value in field_spans(data):
        if number != 7:
            model += span
            continue
        for inner, inner_span, item in field_spans(blob(value)):
            if inner == 1:
                node_index += 1
                if node_index - 1 not in kept:
                    continue
            elif inner == 12 and getattr(read_port(blob(item)), "name", None) not in outputs:
                continue  # another output (or one that is no tensor port: checked models have none)
            graph += inner_span
        model += varint(7 << 3 | LENGTH) + varint(len(graph)) + graph
    return bytes(model)


def blob(value: int | memoryview) -> memoryview:
    """A length-delimited field's bytes, refusing a number where the schema has bytes or a message."""
    if not isinstance(value, memoryview):
        raise WireError("a number where bytes or a message belong")
    return value


def packed_varints(data: memoryview) -> list[int]:
    """A packed repeated varint field's values."""
    values, position = [], 0
    while position < len(data):
        value, position = read_varint(data, position)
        values.append(value)
    return values


@dataclass(frozen=True)
class TensorRecord:
    """A TensorProto as stored: name, element type, dims, and where its values are."""

    name: str
    data_type: int
    dims: tuple[int, ...]
    raw_data: bytes | None
    float_data: np.ndarray | None  # float32 values stored in the float_data field
    external: bool
    int64_data: np.ndarray | None = None  # int64 values stored in the int64_data field

    def array(self, source: str, data_type: int = FLOAT) -> np.ndarray:
        """The values as a little-endian float32 (or int64) array of shape dims; refuses any other element
        type and a byte count that disagrees with the dims."""
        if self.data_type != data_type:
            raise UserError(f"{source}: initializer {self.name!r} has ONNX data type {self.data_type}, "
                            f"expected {data_type} (noisenerf weights are float32)", code="onnx.data_type",
                            name=self.name[:60], data_type=self.data_type, expected=data_type)
        count = int(np.prod(self.dims, dtype=np.int64))
        dtype = np.dtype("<f4" if data_type == FLOAT else "<i8")
        if self.raw_data is not None:  # a ragged byte count holds no whole number of values: refused below
            whole = len(self.raw_data) % dtype.itemsize == 0
            values = np.frombuffer(self.raw_data, dtype) if whole else np.zeros(count + 1, dtype)
        else:
            typed = self.float_data if data_type == FLOAT else self.int64_data
            values = typed if typed is not None else np.zeros(0, dtype)
        if values.size != count:
            raise UserError(f"{source}: initializer {self.name!r} holds {values.size} values, its dims "
                            f"{list(self.dims)} need {count}", code="onnx.value_count", name=self.name[:60],
                            values=values.size, dims=list(self.dims), needed=count)
        return values.reshape(self.dims)


def read_tensor(data: memoryview, budget: FieldBudget | None = None) -> TensorRecord:
    """One TensorProto's fields; values are not decoded until TensorRecord.array."""
    name, data_type, dims, raw, floats, integers, external = "", 0, [], None, [], [], False
    for number, wire, value in fields(data, budget):
        if number == 1:
            dims.extend(packed_varints(value) if wire == LENGTH else [value])
        elif number == 2:
            data_type = value
        elif number == 4:
            if wire not in (LENGTH, FIXED32):
                raise WireError("float_data neither packed nor 32-bit")
            floats.append(np.frombuffer(value, "<f4") if wire == LENGTH else np.array([value], "<u4").view("<f4"))
        elif number == 7:
            integers.extend(packed_varints(value) if wire == LENGTH else [value])
        elif number == 8:
            name = bytes(blob(value)).decode("utf-8", "replace")
        elif number == 9:
            raw = bytes(blob(value))
        elif number == 13 or (number == 14 and value == EXTERNAL):
            external = True
    if any(d >= 2 ** 63 for d in dims):
        raise WireError("negative tensor dimension")
    return TensorRecord(name, data_type, tuple(dims), raw, np.concatenate(floats) if floats else None, external,
                        np.array(integers, np.uint64).view(np.int64) if integers else None)


@dataclass(frozen=True)
class ModelFile:
    """A model's bytes, read once: metadata_props, the graph's initializers, nodes and ports. Holding one
    means its bytes keep no tensor in external data, so onnxruntime may be given them."""

    data: bytes = dataclasses.field(repr=False)
    source: str  # the model's name in messages
    metadata_props: dict[str, str]
    initializers: tuple[TensorRecord, ...]
    nodes: tuple[Node, ...] = ()
    inputs: tuple[Port | None, ...] = ()  # None: a port that is not a tensor of known element type and rank
    outputs: tuple[Port | None, ...] = ()
    opsets: tuple[tuple[str, int], ...] = ()  # (domain, version)
    ir_version: int = 0
    unexpected: tuple[str, ...] = ()  # fields a noisenerf graph never has ("graph field 13", ...)


def refuse_unsupported(message: str, number: int, source: str) -> None:
    """Refuse field `number` of a `message` kind that is in UNSUPPORTED."""
    if (message, number) in UNSUPPORTED:
        raise UserError(f"{source} holds {UNSUPPORTED[message, number]}, which a noisenerf model never has",
                        code="onnx.unsupported", holds=UNSUPPORTED[message, number])


def node_tensors(node: memoryview, source: str, budget: FieldBudget | None = None) -> Iterator[TensorRecord]:
    """The tensors in a NodeProto's attributes (a Constant's value, ...), refusing subgraphs."""
    for number, _, attribute in fields(node, budget):
        if number != 5:
            continue
        for inner, _, value in fields(blob(attribute), budget):
            refuse_unsupported("attribute", inner, source)
            if inner in (5, 10):
                yield read_tensor(blob(value), budget)


def text(value: int | memoryview) -> str:
    return bytes(blob(value)).decode("utf-8")


def read_attribute(data: memoryview, budget: FieldBudget | None = None) -> tuple[str, int | str]:
    """(name, value) of an integer attribute; any other kind reads as (name, "not an integer")."""
    name, value, kinds = "", "not an integer", set()
    for number, wire, item in fields(data, budget):
        if number == 1:
            name = text(item)
        elif number == 3 and wire == VARINT:
            value = item - (1 << 64) if item >= 1 << 63 else item
        elif number not in (13, 20):  # doc_string, type
            kinds.add(number)
    return name, value if not kinds else "not an integer"


def read_node(data: memoryview, budget: FieldBudget | None = None) -> Node:
    """A NodeProto as runtime.graph.Node; a field that computes nothing is skipped, an unknown one kept
    as an attribute that no expected node has."""
    inputs, outputs, op, domain, attributes = [], [], "", "", []
    for number, _, value in fields(data, budget):
        if number == 1:
            inputs.append(text(value))
        elif number == 2:
            outputs.append(text(value))
        elif number == 4:
            op = text(value)
        elif number == 7:
            domain = text(value)
        elif number == 5:
            attributes.append(read_attribute(blob(value), budget))
        elif number not in (3, 6):  # name, doc_string
            attributes.append((f"field {number}", "unexpected"))
    if domain not in ("", "ai.onnx"):
        op = f"{domain}.{op}"
    return Node(op, tuple(inputs), tuple(outputs), tuple(sorted(attributes, key=str)))


def read_port(data: memoryview, budget: FieldBudget | None = None) -> Port | None:
    """A ValueInfoProto as runtime.graph.Port (symbolic dims by their names), None if it is not a tensor
    whose every dim is a value or a name."""
    name, elem_type, shape, tensor = "", 0, None, False
    for number, _, value in fields(data, budget):
        if number == 1:
            name = text(value)
        elif number == 2:
            for kind, _, tensor_type in fields(blob(value), budget):
                if kind != 1:
                    return None
                tensor = True
                for part, _, item in fields(blob(tensor_type), budget):
                    if part == 1:
                        elem_type = item
                    elif part == 2:
                        shape = []
                        for _, _, dim in fields(blob(item), budget):
                            sizes = {k: v for k, _, v in fields(blob(dim), budget) if k in (1, 2)}
                            if len(sizes) != 1:
                                return None
                            shape.append(sizes[1] if 1 in sizes else text(sizes[2]))
    return Port(name, tuple(shape), elem_type) if tensor and shape is not None else None


def parse_model(data: bytes, source: str) -> ModelFile:
    """Read a model's metadata, tensors and graph, in the module docstring's order of checks: its framing, then
    the walk, refusing malformed bytes and unsupported structures, then, before anything could load them,
    tensors whose data lives outside the file."""
    view = memoryview(data)
    framing(lambda position, count: view[position:position + count], len(view), source)
    budget = FieldBudget()
    try:
        props, initializers, attributes, nodes, ports, opsets = {}, [], [], [], {11: [], 12: []}, []
        ir_version, unexpected = 0, []
        for number, _, value in fields(view, budget):
            refuse_unsupported("model", number, source)
            if number == 14:
                entry = {k: text(v) for k, _, v in fields(blob(value), budget) if k in (1, 2)}
                props[entry.get(1, "")] = entry.get(2, "")
            elif number == 1:
                ir_version = value
            elif number == 8:
                entry = {k: v for k, _, v in fields(blob(value), budget) if k in (1, 2)}
                opsets.append((text(entry.get(1, memoryview(b""))), entry.get(2, 0)))
            elif number == 7:
                for inner, _, item in fields(blob(value), budget):
                    refuse_unsupported("graph", inner, source)
                    if inner == 5:
                        initializers.append(read_tensor(blob(item), budget))
                    elif inner == 1:
                        attributes.extend(node_tensors(blob(item), source, budget))
                        nodes.append(read_node(blob(item), budget))
                    elif inner in ports:
                        ports[inner].append(read_port(blob(item), budget))
                    elif inner not in (2, 10):  # name, doc_string
                        unexpected.append(f"graph field {inner}")
    except ValueError as error:  # WireError, UnicodeDecodeError, float_data of a length not divisible by 4
        raise not_onnx(source, error) from None
    external = [t.name or "(unnamed)" for t in initializers + attributes if t.external]
    if external:
        raise UserError(f"{source} keeps tensor {external[0]!r} in external data; a noisenerf model must be "
                        "one self-contained .onnx file", code="onnx.external_data", tensor=external[0][:60])
    return ModelFile(data, source, props, tuple(initializers), tuple(nodes), tuple(ports[11]), tuple(ports[12]),
                     tuple(opsets), ir_version, tuple(unexpected))
