// Mirrors runtime/graph.py: the builder the field kinds (src/fields/, runtime/fields/) write a model's graph with,
// and the rule that binds a model file's graph to the one its architecture derives (check_graph), refusing with the
// same codes and params.

import { UserError, cut, show } from "./errors.js";
import { FLOAT, INT64, tensorArray } from "./onnx.js";
import { pyCompare } from "./json.js";

export const INPUT_NAMES = ["points", "viewdirs", "noise"];
export const OUTPUT_NAMES = ["rgb", "sigma"];
export const COARSE_OUTPUT_NAMES = ["rgb_coarse", "sigma_coarse"];
export const BATCH = "n";

/** proposal_output: the output of a scene's proposal network `index` (density only; src/fields/nerfacto.js). */
export const proposalOutput = (index) => `sigma_proposal${index}`;

/** A graph input or output: name, shape (BATCH for the free batch axis), element type. */
export const port = (name, shape, elemType = FLOAT) => ({ name, shape, elemType });

/** Collects nodes, constants ({dtype, shape, values}) and weights (shapes); a value computed once (an encoding)
 * is reused by name. The field kinds (src/fields/) write their networks with it. */
export class GraphBuilder {
  constructor() {
    this.nodes = [];
    this.constants = new Map(); // name -> {dtype, shape, values}
    this.weights = new Map(); // name -> shape
  }
  add(op, inputs, output, attributes = {}) {
    return this.node(op, inputs, [output], attributes)[0];
  }
  node(op, inputs, outputs, attributes) {
    const attrs = Object.entries(attributes).sort((a, b) => (a[0] < b[0] ? -1 : 1));
    this.nodes.push({ op, inputs: [...inputs], outputs: [...outputs], attributes: attrs });
    return outputs;
  }
  constant(name, dtype, shape, values) {
    if (!this.constants.has(name)) this.constants.set(name, { dtype, shape, values });
    return name;
  }
  linear(prefix, layer, x, fanIn, fanOut) {
    const weight = `${prefix}.${layer}.weight`, bias = `${prefix}.${layer}.bias`;
    this.weights.set(weight, [fanOut, fanIn]);
    this.weights.set(bias, [fanOut]);
    return this.add("Gemm", [x, weight, bias], `${prefix}.${layer}`, { transB: 1 });
  }
  /** Split x along `axis` into `outputs` of the sizes held by the constant `sizes`. */
  split(x, sizes, outputs, axis = 1) { return this.node("Split", [x, sizes], outputs, { axis }); }
  computed(name) { return this.nodes.some((node) => node.outputs.includes(name)); }
  /** [position ‖ direction] + noise split back into its two segments, computed once per pair of encodings;
   * `addSizes()` adds the constant holding their widths, after the Add, and returns its name. */
  noisyPair(position, direction, addSizes) {
    const name = `${position}|${direction}+noise`;
    if (!this.computed(name)) {
      this.add("Add", [this.add("Concat", [position, direction], `${position}|${direction}`, { axis: 1 }), "noise"], name);
      this.split(name, addSizes(), [`${name}.xyz`, `${name}.dirs`]);
    }
    return [`${name}.xyz`, `${name}.dirs`];
  }
}

function refuse(source, what, { code, ...params }) {
  return new UserError(`${source}: the model's graph is not the one its scene exports: ${what}; export the scene again`,
    { code, ...params });
}

function describe(node) {
  const attributes = node.attributes.map(([name, value]) => `, ${name}=${value}`).join("");
  return `${node.op}(${node.inputs.join(", ")}${attributes}) -> ${node.outputs.join(", ")}`;
}

const sameList = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);
const sameNode = (a, b) => a.op === b.op && sameList(a.inputs, b.inputs) && sameList(a.outputs, b.outputs) &&
  a.attributes.length === b.attributes.length && a.attributes.every(([n, v], i) => n === b.attributes[i][0] && v === b.attributes[i][1]);
const samePort = (a, b) => a !== null && a.name === b.name && a.elemType === b.elemType && sameList(a.shape, b.shape);
const portText = (port) => (port === null ? "null" : `${port.name} [${port.shape.join(", ")}]`);

/** check_graph: refuse a model file whose graph differs from `expected`; return its weights (name -> Float32Array). */
export function checkGraph(file, expected, source) {
  if (file.unexpected.length) {
    throw refuse(source, `it holds ${file.unexpected[0]}`, { code: "graph.unexpected_field", field: file.unexpected[0] });
  }
  for (const [kind, got, want] of [["inputs", file.inputs, expected.inputs], ["outputs", file.outputs, expected.outputs]]) {
    if (got.length !== want.length || !got.every((port, i) => samePort(port, want[i]))) {
      throw refuse(source, `its ${kind} are ${got.map(portText).join(", ")}, expected ${want.map(portText).join(", ")}`,
        { code: "graph.ports", ports: kind, names: got.slice(0, 16).map((port) => port && cut(port.name)),
          expected: want.map((port) => port.name) });
    }
  }
  if (file.opsets.length !== 1 || file.opsets[0][0] !== "" || file.opsets[0][1] !== expected.opset) {
    throw refuse(source, `it imports opsets ${show(file.opsets)}, not [["", ${expected.opset}]]`,
      { code: "graph.opsets", opsets: file.opsets.slice(0, 16).map(([domain, version]) => [cut(domain), version]),
        expected: expected.opset });
  }
  const n = Math.min(file.nodes.length, expected.nodes.length);
  for (let i = 0; i < n; i++) {
    const [got, want] = [file.nodes[i], expected.nodes[i]];
    if (!sameNode(got, want)) {
      throw refuse(source, `node ${i} is ${describe(got)}, expected ${describe(want)}`,
        { code: "graph.node", index: i, op: cut(got.op), expected: want.op });
    }
  }
  if (file.nodes.length !== expected.nodes.length) {
    const more = file.nodes.length - expected.nodes.length;
    throw refuse(source, `it has ${Math.abs(more)} ${more > 0 ? "more" : "fewer"} nodes than the ${expected.nodes.length} expected`,
      { code: "graph.node_count", nodes: file.nodes.length, expected: expected.nodes.length });
  }
  const records = new Map();
  for (const record of file.initializers) {
    if (records.has(record.name)) {
      throw refuse(source, `initializer ${show(record.name)} appears twice`, { code: "graph.initializer_twice", name: cut(record.name) });
    }
    records.set(record.name, record);
  }
  const wanted = new Set([...expected.weights.keys(), ...expected.constants.keys()]);
  const extra = [...records.keys()].filter((name) => !wanted.has(name)).sort(pyCompare);
  const missing = [...wanted].filter((name) => !records.has(name)).sort(pyCompare);
  if (extra.length) throw refuse(source, `initializer ${show(extra[0])} is extra`, { code: "graph.initializer_extra", name: cut(extra[0]) });
  if (missing.length) throw refuse(source, `initializer ${show(missing[0])} is missing`, { code: "graph.initializer_missing", name: missing[0] });
  for (const [name, constant] of expected.constants) {
    const isInt = constant.dtype === "int64";
    const record = records.get(name);
    const got = tensorArray(record, source, isInt ? INT64 : FLOAT);
    const gotValues = Array.from(got, (v) => (isInt ? Number(v) : v));
    const equal = sameList(record.dims, constant.shape) && gotValues.length === constant.values.length &&
      gotValues.every((v, i) => v === constant.values[i]);
    if (!equal) {
      const first = (values) => `[${values.slice(0, 4).join(", ")}]`;
      throw refuse(source, `constant ${show(name)} holds ${first(gotValues)}…, expected ${first(constant.values)}…`,
        { code: "graph.constant", name });
    }
  }
  const weights = new Map();
  for (const [name, shape] of expected.weights) {
    const record = records.get(name);
    if (!sameList(record.dims, shape)) {
      throw refuse(source, `weight ${show(name)} has shape ${show(record.dims)}, expected ${show(shape)}`,
        { code: "graph.weight_shape", name, shape: record.dims, expected: shape });
    }
    weights.set(name, { shape, values: tensorArray(record, source) });
  }
  return weights;
}
