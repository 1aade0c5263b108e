// Mirrors runtime/onnx_file.py: what a model file holds, read from the protobuf wire format (onnxruntime-web
// exposes neither metadata_props nor initializers), and the model's bytes pruned to the outputs a session fetches
// (prunedModel: onnxruntime-web, like every inference build, runs every node whatever is fetched). Field numbers
// from onnx.proto, as in the Python module:
//   ModelProto ir_version 1, graph 7, opset_import 8 (domain 1, version 2), metadata_props 14 (key 1, value 2),
//              training_info 20, functions 25
//   GraphProto node 1, initializer 5, input 11, output 12, sparse_initializer 15
//   NodeProto input 1, output 2, op_type 4, attribute 5, domain 7
//   AttributeProto name 1, i 3, t 5, g 6, tensors 10, graphs 11, type 20, sparse_tensor 22, sparse_tensors 23
//   ValueInfoProto name 1, type 2 (TypeProto tensor_type 1: elem_type 1, shape 2: dim 1: value 1, param 2)
//   TensorProto dims 1, data_type 2, float_data 4, int64_data 7, name 8, raw_data 9, external_data 13,
//              data_location 14
//
// The checks, in runtime/onnx_file.py's order (its docstring), so that a file is refused with the same code in both:
//   1. framing: the top-level fields by their keys and lengths alone, payloads skipped unread (field number 0, an
//      unknown wire type, a varint or length past the end, more than MAX_MODEL_FIELDS fields: onnx.malformed): a file
//      of zeros or random bytes is refused within a few bytes, whatever its size, and never walked;
//   2. the walk, in file order (training graphs, functions, sparse initializers, subgraphs, sparse tensors:
//      onnx.unsupported; anything not well formed, more than MAX_MODEL_FIELDS fields walked in all: onnx.malformed);
//   3. external data: onnx.external_data.

import { UserError, cut, show } from "./errors.js";
import { MAX_MODEL_FIELDS } from "./limits.js";


export const FLOAT = 1;
export const INT64 = 7;
const EXTERNAL = 1;
const VARINT = 0, FIXED64 = 1, LENGTH = 2, FIXED32 = 5;
const UNSUPPORTED = new Map([
  ["model 20", "training graphs"], ["model 25", "functions"], ["graph 15", "sparse initializers"],
  ["attribute 6", "subgraphs"], ["attribute 11", "subgraphs"], ["attribute 22", "sparse tensors"],
  ["attribute 23", "sparse tensors"],
]);

export class WireError extends Error {}

const utf8 = new TextDecoder("utf-8", { fatal: true });
const utf8Lenient = new TextDecoder("utf-8");

/** One varint at position -> [value (Number, or BigInt beyond 2^53), next position]. */
export function readVarint(data, position) {
  let value = 0n;
  for (let shift = 0n; shift < 70n; shift += 7n) {
    if (position >= data.length) throw new WireError("truncated varint");
    const byte = data[position++];
    value |= BigInt(byte & 0x7f) << shift;
    if (byte < 0x80) return [value <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(value) : value, position];
  }
  throw new WireError("varint longer than 10 bytes");
}

/** FieldBudget: how many more fields one parse may walk (MAX_MODEL_FIELDS in all). */
class FieldBudget {
  constructor(most = MAX_MODEL_FIELDS) { this.most = most; this.left = most; }

  spend() {
    if (--this.left < 0) throw new WireError(`more than ${this.most} protobuf fields`);
  }
}

/** One field's key at `position` -> [number, wire type, next position], refusing field number 0. */
function fieldKey(data, position) {
  let key;
  [key, position] = readVarint(data, position);
  key = BigInt(key);
  const number = Number(key >> 3n), wire = Number(key & 7n);
  if (number === 0) throw new WireError("field number 0");
  return [number, wire, position];
}

/** The fields of one message: [number, wire type, value (number | bigint | Uint8Array), start, end], in file order
 * (start..end: the bytes the field occupies, key included). budget: the parse's (each field spends one). */
export function* fields(data, budget = null) {
  let position = 0;
  const size = data.length;
  while (position < size) {
    const start = position;
    budget?.spend();
    let number, wire;
    [number, wire, position] = fieldKey(data, position);
    let value;
    if (wire === VARINT) {
      [value, position] = readVarint(data, position);
    } else if (wire === FIXED64 || wire === FIXED32) {
      const width = wire === FIXED64 ? 8 : 4;
      if (position + width > size) throw new WireError("truncated fixed-width field");
      value = data.subarray(position, position + width);
      position += width;
    } else if (wire === LENGTH) {
      let length;
      [length, position] = readVarint(data, position);
      if (typeof length === "bigint" || position + length > size) throw new WireError("length-delimited field runs past the end");
      value = data.subarray(position, position + length);
      position += length;
    } else {
      throw new WireError(`unsupported wire type ${wire}`);
    }
    yield [number, wire, value, start, position];
  }
}

/** framing: check 1, the model's top-level fields by their keys and lengths alone, every payload skipped unread (as
 * `fields` walks them, without making a value of any). Refuses with onnx.malformed. */
export function framing(data, source) {
  const budget = new FieldBudget();
  let position = 0;
  try {
    while (position < data.length) {
      budget.spend();
      let number, wire;
      [number, wire, position] = fieldKey(data, position);
      if (wire === VARINT) [, position] = readVarint(data, position);
      else if (wire === FIXED64 || wire === FIXED32) {
        position += wire === FIXED64 ? 8 : 4;
        if (position > data.length) throw new WireError("truncated fixed-width field");
      } else if (wire === LENGTH) {
        let length;
        [length, position] = readVarint(data, position);
        if (typeof length === "bigint" || position + length > data.length) throw new WireError("length-delimited field runs past the end");
        position += length;
      } else throw new WireError(`unsupported wire type ${wire}`);
    }
  } catch (error) {
    throw notOnnx(source, error);
  }
}

function notOnnx(source, error) {
  if (error instanceof UserError) return error;
  const detail = error instanceof TypeError ? "invalid UTF-8" : error.message;
  return new UserError(`${source} is not a loadable ONNX model (not ONNX, or truncated): ${detail}`, { code: "onnx.malformed" });
}

/** field_spans: the fields of one message with the bytes each occupies (key included): [number, span, value]. */
export function* fieldSpans(data) {
  for (const [number, , value, start, end] of fields(data)) yield [number, data.subarray(start, end), value];
}

/** varint: a non-negative integer (below 2^53) as a base-128 varint. */
export function varint(value) {
  const out = [];
  for (;;) {
    const byte = value % 128;
    value = Math.floor(value / 128);
    out.push(byte | (value ? 0x80 : 0));
    if (!value) return Uint8Array.from(out);
  }
}

/** Byte arrays joined into one new array. */
function concatenated(parts) {
  const bytes = new Uint8Array(parts.reduce((n, part) => n + part.length, 0));
  let at = 0;
  for (const part of parts) {
    bytes.set(part, at);
    at += part.length;
  }
  return bytes;
}

function blob(value, wire) {
  if (!(value instanceof Uint8Array) || wire !== LENGTH) throw new WireError("a number where bytes or a message belong");
  return value;
}

function fixedInt(value) { // a fixed-width field as the integer Python's int.from_bytes(little) gives
  let n = 0n;
  for (let i = value.length - 1; i >= 0; i--) n = (n << 8n) | BigInt(value[i]);
  return n <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(n) : n;
}

function plain(value) { return value instanceof Uint8Array ? fixedInt(value) : value; }

function packedVarints(data) {
  const values = [];
  let position = 0;
  while (position < data.length) {
    let value;
    [value, position] = readVarint(data, position);
    values.push(value);
  }
  return values;
}

function text(value, wire) {
  return utf8.decode(blob(value, wire));
}

/** A TensorProto as stored: values decoded only by tensorArray. */
export function readTensor(data, budget = null) {
  let name = "", dataType = 0, raw = null, external = false;
  const dims = [], floats = [], integers = [];
  for (const [number, wire, value] of fields(data, budget)) {
    if (number === 1) dims.push(...(wire === LENGTH ? packedVarints(value) : [plain(value)]));
    else if (number === 2) dataType = plain(value);
    else if (number === 4) {
      if (wire !== LENGTH && wire !== FIXED32) throw new WireError("float_data neither packed nor 32-bit");
      if (value.length % 4) throw new WireError(`buffer size must be a multiple of element size`);
      floats.push(value);
    } else if (number === 7) integers.push(...(wire === LENGTH ? packedVarints(value) : [plain(value)]));
    else if (number === 8) name = utf8Lenient.decode(blob(value, wire));
    else if (number === 9) raw = blob(value, wire);
    else if (number === 13 || (number === 14 && plain(value) === EXTERNAL)) external = true;
  }
  if (dims.some((d) => typeof d === "bigint" && d >= 2n ** 63n)) throw new WireError("negative tensor dimension");
  let floatData = null;
  if (floats.length) {
    const bytes = concatenated(floats);
    floatData = new Float32Array(bytes.buffer, 0, bytes.length / 4);
  }
  const int64Data = integers.length ? integers.map((v) => BigInt.asIntN(64, BigInt(v))) : null;
  return { name, dataType, dims: dims.map(Number), rawData: raw, floatData, int64Data, external };
}

/** TensorRecord.array: the values as a Float32Array (or BigInt64Array for INT64) of dims' size. */
export function tensorArray(record, source, dataType = FLOAT) {
  if (record.dataType !== dataType) {
    throw new UserError(`${source}: initializer ${show(record.name)} has ONNX data type ${record.dataType}, ` +
      `expected ${dataType} (noisenerf weights are float32)`,
    { code: "onnx.data_type", name: cut(record.name), data_type: record.dataType, expected: dataType });
  }
  const count = record.dims.reduce((a, b) => a * b, 1);
  const size = dataType === FLOAT ? 4 : 8;
  let values;
  if (record.rawData !== null) {
    const whole = record.rawData.length % size === 0;
    if (!whole) values = { length: count + 1 };
    else {
      const copy = record.rawData.slice(); // aligned
      values = dataType === FLOAT ? new Float32Array(copy.buffer, 0, copy.length / 4)
        : new BigInt64Array(copy.buffer, 0, copy.length / 8);
    }
  } else {
    const typed = dataType === FLOAT ? record.floatData : (record.int64Data && BigInt64Array.from(record.int64Data));
    values = typed ?? (dataType === FLOAT ? new Float32Array(0) : new BigInt64Array(0));
  }
  if (values.length !== count) {
    throw new UserError(`${source}: initializer ${show(record.name)} holds ${values.length} values, its dims ` +
      `${show(record.dims)} need ${count}`,
    { code: "onnx.value_count", name: cut(record.name), values: values.length, dims: record.dims, needed: count });
  }
  return values;
}

function refuseUnsupported(message, number, source) {
  const what = UNSUPPORTED.get(`${message} ${number}`);
  if (what) throw new UserError(`${source} holds ${what}, which a noisenerf model never has`, { code: "onnx.unsupported", holds: what });
}

function* nodeTensors(node, source, budget = null) {
  for (const [number, wire, attribute] of fields(node, budget)) {
    if (number !== 5) continue;
    for (const [inner, innerWire, value] of fields(blob(attribute, wire), budget)) {
      refuseUnsupported("attribute", inner, source);
      if (inner === 5 || inner === 10) yield readTensor(blob(value, innerWire), budget);
    }
  }
}

function readAttribute(data, budget = null) {
  let name = "", value = "not an integer";
  const kinds = new Set();
  for (const [number, wire, item] of fields(data, budget)) {
    if (number === 1) name = text(item, wire);
    else if (number === 3 && wire === VARINT) {
      const big = BigInt.asIntN(64, BigInt(item));
      value = big >= -BigInt(Number.MAX_SAFE_INTEGER) && big <= BigInt(Number.MAX_SAFE_INTEGER) ? Number(big) : big;
    } else if (number !== 13 && number !== 20) kinds.add(number);
  }
  return [name, kinds.size ? "not an integer" : value];
}

/** runtime.graph.Node: {op, inputs, outputs, attributes: [[name, value], …] sorted as Python sorts by str}. */
export function readNode(data, budget = null) {
  const inputs = [], outputs = [], attributes = [];
  let op = "", domain = "";
  for (const [number, wire, value] of fields(data, budget)) {
    if (number === 1) inputs.push(text(value, wire));
    else if (number === 2) outputs.push(text(value, wire));
    else if (number === 4) op = text(value, wire);
    else if (number === 7) domain = text(value, wire);
    else if (number === 5) attributes.push(readAttribute(blob(value, wire), budget));
    else if (number !== 3 && number !== 6) attributes.push([`field ${number}`, "unexpected"]);
  }
  if (domain !== "" && domain !== "ai.onnx") op = `${domain}.${op}`;
  // Python sorts the (name, value) pairs by their str(): by name, then value (only the order of a node that is refused
  // anyway can differ: an attribute set equal to the expected one sorts by name in both)
  const key = ([name, value]) => JSON.stringify([name, String(value)]);
  attributes.sort((a, b) => (key(a) < key(b) ? -1 : key(a) > key(b) ? 1 : 0));
  return { op, inputs, outputs, attributes };
}

/** runtime.graph.Port {name, shape, elemType}, or null when it is not a tensor of known dims. */
export function readPort(data, budget = null) {
  let name = "", elemType = 0, shape = null, tensor = false;
  for (const [number, wire, value] of fields(data, budget)) {
    if (number === 1) name = text(value, wire);
    else if (number === 2) {
      for (const [kind, kindWire, tensorType] of fields(blob(value, wire), budget)) {
        if (kind !== 1) return null;
        tensor = true;
        for (const [part, partWire, item] of fields(blob(tensorType, kindWire), budget)) {
          if (part === 1) elemType = plain(item);
          else if (part === 2) {
            shape = [];
            for (const [, dimWire, dim] of fields(blob(item, partWire), budget)) {
              const sizes = new Map();
              for (const [k, w, v] of fields(blob(dim, dimWire), budget)) if (k === 1 || k === 2) sizes.set(k, [w, v]);
              if (sizes.size !== 1) return null;
              shape.push(sizes.has(1) ? plain(sizes.get(1)[1]) : text(sizes.get(2)[1], sizes.get(2)[0]));
            }
          }
        }
      }
    }
  }
  return tensor && shape !== null ? { name, shape, elemType } : null;
}

/** parse_model: a model's metadata, tensors and graph, in the order of checks above: its framing, then the walk,
 * refusing malformed bytes and unsupported structures, then tensors whose data lives outside the file. */
export function parseModel(data, source) {
  framing(data, source);
  const props = new Map(), initializers = [], attributes = [], nodes = [], opsets = [], unexpected = [];
  const ports = { 11: [], 12: [] };
  const budget = new FieldBudget();
  let irVersion = 0;
  try {
    for (const [number, wire, value] of fields(data, budget)) {
      refuseUnsupported("model", number, source);
      if (number === 14) {
        const entry = new Map();
        for (const [k, w, v] of fields(blob(value, wire), budget)) if (k === 1 || k === 2) entry.set(k, text(v, w));
        props.set(entry.get(1) ?? "", entry.get(2) ?? "");
      } else if (number === 1) irVersion = plain(value);
      else if (number === 8) {
        const entry = new Map();
        for (const [k, w, v] of fields(blob(value, wire), budget)) if (k === 1 || k === 2) entry.set(k, [w, v]);
        const domain = entry.has(1) ? text(entry.get(1)[1], entry.get(1)[0]) : "";
        opsets.push([domain, entry.has(2) ? plain(entry.get(2)[1]) : 0]);
      } else if (number === 7) {
        for (const [inner, innerWire, item] of fields(blob(value, wire), budget)) {
          refuseUnsupported("graph", inner, source);
          if (inner === 5) initializers.push(readTensor(blob(item, innerWire), budget));
          else if (inner === 1) {
            attributes.push(...nodeTensors(blob(item, innerWire), source, budget));
            nodes.push(readNode(blob(item, innerWire), budget));
          } else if (inner in ports) ports[inner].push(readPort(blob(item, innerWire), budget));
          else if (inner !== 2 && inner !== 10) unexpected.push(`graph field ${inner}`);
        }
      }
    }
  } catch (error) {
    throw notOnnx(source, error);
  }
  const external = [...initializers, ...attributes].filter((t) => t.external).map((t) => t.name || "(unnamed)");
  if (external.length) {
    throw new UserError(`${source} keeps tensor ${show(external[0])} in external data; a noisenerf model must be ` +
      "one self-contained .onnx file", { code: "onnx.external_data", tensor: cut(external[0]) });
  }
  return { data, source, metadataProps: props, initializers, nodes, inputs: ports[11], outputs: ports[12], opsets,
    irVersion, unexpected };
}

/** pruned_model: the model's bytes with only what computes `outputs`: the other outputs and every node none of them
 * needs removed (onnxruntime-web runs a whole graph whatever is fetched, and drops unused initializers itself). The
 * file has passed parseModel, so its fields are well formed. The kept fields are copied once, into the result. */
export function prunedModel(file, outputs) {
  const needed = new Set(outputs), kept = new Set(), wanted = new Set(outputs);
  for (let index = file.nodes.length - 1; index >= 0; index--) { // nodes are in topological order
    if (file.nodes[index].outputs.some((name) => needed.has(name))) {
      kept.add(index);
      for (const name of file.nodes[index].inputs) needed.add(name);
    }
  }
  const parts = [];
  let nodeIndex = 0;
  for (const [number, span, value] of fieldSpans(file.data)) {
    if (number !== 7) {
      parts.push(span);
      continue;
    }
    const graph = [];
    for (const [inner, innerSpan, item] of fieldSpans(value)) {
      if (inner === 1 && !kept.has(nodeIndex++)) continue;
      if (inner === 12 && !wanted.has(readPort(item)?.name)) continue;
      graph.push(innerSpan);
    }
    parts.push(varint((7 << 3) | LENGTH), varint(graph.reduce((n, part) => n + part.length, 0)), ...graph);
  }
  return concatenated(parts);
}
