// Mirrors runtime/graph.py: the graph a noisenerf model holds as a pure function of its architecture
// (field_graph), and the rule that binds a model file's graph to it (check_graph), with the same messages.

import { UserError, repr, tuple, PyFloat } from "./errors.js";
import { FLOAT, INT64, tensorArray } from "./onnx.js";
import { MAX_FIELD_DEPTH, MAX_FIELD_WIDTH, MAX_FREQUENCIES, checkedInt, checkedList } from "./limits.js";

export const OPSET = 17;
export const INPUT_NAMES = ["points", "viewdirs", "noise"];
export const OUTPUT_NAMES = ["rgb", "sigma"];
export const COARSE_OUTPUT_NAMES = ["rgb_coarse", "sigma_coarse"];
const BATCH = "n";

export const encodingDims = (nFreqs) => 3 + 6 * nFreqs;

class GraphBuilder {
  constructor() {
    this.nodes = [];
    this.constants = new Map(); // name -> {dtype, shape, values}
    this.weights = new Map(); // name -> shape
  }
  add(op, inputs, output, attributes = {}) {
    const attrs = Object.entries(attributes).sort((a, b) => (a[0] < b[0] ? -1 : 1));
    this.nodes.push({ op, inputs: [...inputs], outputs: [output], attributes: attrs });
    return output;
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
  computed(name) { return this.nodes.some((node) => node.outputs.includes(name)); }
  encoding(x, nFreqs) {
    const name = `gamma.${x}.${nFreqs}`;
    if (this.computed(name)) return name;
    const axis1 = this.constant("axes.1", "int64", [1], [1]);
    const axis2 = this.constant("axes.2", "int64", [1], [2]);
    const freqs = this.constant(`freqs.${nFreqs}`, "float32", [nFreqs, 1], Array.from({ length: nFreqs }, (_, i) => 2 ** i));
    const scaled = this.add("Mul", [this.add("Unsqueeze", [x, axis1], `${name}.x`), freqs], `${name}.scaled`);
    const sin = this.add("Unsqueeze", [this.add("Sin", [scaled], `${name}.sin`), axis2], `${name}.sin4`);
    const cos = this.add("Unsqueeze", [this.add("Cos", [scaled], `${name}.cos`), axis2], `${name}.cos4`);
    const bands = this.add("Concat", [sin, cos], `${name}.bands4`, { axis: 2 });
    const flat = this.add("Reshape", [bands, this.constant("shape.flat", "int64", [2], [0, -1])], `${name}.bands`);
    return this.add("Concat", [x, flat], name, { axis: 1 });
  }
  noisyInputs(config) {
    const xyz = this.encoding("points", config.xyz_freqs);
    if (!config.use_viewdirs) {
      const name = `${xyz}+noise`;
      return [this.computed(name) ? name : this.add("Add", [xyz, "noise"], name), null];
    }
    const dirs = this.encoding("viewdirs", config.dir_freqs);
    const name = `${xyz}|${dirs}+noise`;
    if (!this.computed(name)) {
      this.add("Add", [this.add("Concat", [xyz, dirs], `${xyz}|${dirs}`, { axis: 1 }), "noise"], name);
      const sizes = this.constant(`split.${config.xyz_freqs}.${config.dir_freqs}`, "int64", [2],
        [encodingDims(config.xyz_freqs), encodingDims(config.dir_freqs)]);
      this.nodes.push({ op: "Split", inputs: [name, sizes], outputs: [`${name}.xyz`, `${name}.dirs`], attributes: [["axis", 1]] });
    }
    return [`${name}.xyz`, `${name}.dirs`];
  }
  network(prefix, config, rgb, sigma) {
    const [xyz, dirs] = this.noisyInputs(config);
    const xyzDims = encodingDims(config.xyz_freqs), width = config.width;
    let h = xyz, fanIn = xyzDims;
    for (let i = 0; i < config.depth; i++) {
      h = this.add("Relu", [this.linear(prefix, `pts_linears.${i}`, h, fanIn, width)], `${prefix}.h${i}`);
      fanIn = width;
      if (config.skips.includes(i)) {
        h = this.add("Concat", [xyz, h], `${prefix}.skip${i}`, { axis: 1 });
        fanIn = width + xyzDims;
      }
    }
    let rawRgb, density;
    if (config.use_viewdirs) {
      density = this.linear(prefix, "alpha_linear", h, width, 1);
      const feature = this.linear(prefix, "feature_linear", h, width, width);
      const branch = this.add("Concat", [feature, dirs], `${prefix}.branch`, { axis: 1 });
      const hidden = this.linear(prefix, "views_linears.0", branch, width + encodingDims(config.dir_freqs), Math.floor(width / 2));
      rawRgb = this.linear(prefix, "rgb_linear", this.add("Relu", [hidden], `${prefix}.views`), Math.floor(width / 2), 3);
    } else {
      const raw = this.linear(prefix, "output_linear", h, width, 4);
      const sizes = this.constant("split.rgb_density", "int64", [2], [3, 1]);
      rawRgb = `${prefix}.raw_rgb`;
      density = `${prefix}.raw_density`;
      this.nodes.push({ op: "Split", inputs: [raw, sizes], outputs: [rawRgb, density], attributes: [["axis", 1]] });
    }
    this.add("Sigmoid", [rawRgb], rgb);
    this.add("Squeeze", [this.add("Relu", [density], `${prefix}.sigma`), this.constant("axes.1", "int64", [1], [1])], sigma);
  }
}

const NETWORK_KEYS = ["depth", "width", "skips", "xyz_freqs", "dir_freqs", "use_viewdirs"];

/** checked_network: a network's architecture as metadata states it, every number within the caps. */
export function checkedNetwork(config, what) {
  if (config === null || typeof config !== "object" || Array.isArray(config) ||
      Object.keys(config).length !== NETWORK_KEYS.length || !NETWORK_KEYS.every((k) => Object.hasOwn(config, k))) {
    throw new UserError(`the ${what} network's architecture must have exactly depth, width, skips, xyz_freqs, ` +
      "dir_freqs and use_viewdirs");
  }
  const depth = checkedInt(config.depth, `${what} depth`, 1, MAX_FIELD_DEPTH);
  const skips = checkedList(config.skips, "skips", null, depth).map((skip) => checkedInt(skip, `${what} skip`, 0, depth - 1));
  if (typeof config.use_viewdirs !== "boolean") throw new UserError(`the ${what} network's use_viewdirs must be true or false`);
  const width = checkedInt(config.width, `${what} width`, 2, MAX_FIELD_WIDTH);
  const freqs = {};
  for (const key of ["xyz_freqs", "dir_freqs"]) freqs[key] = checkedInt(config[key], `${what} ${key}`, 0, MAX_FREQUENCIES);
  return { depth, width, skips: [...new Set(skips)].sort((a, b) => a - b), use_viewdirs: config.use_viewdirs, ...freqs };
}

/** field_graph: the graph of a model with this architecture ({coarse, fine}) and noise width. */
export function fieldGraph(architecture, noiseDims) {
  const builder = new GraphBuilder();
  const checked = {};
  for (const [name, config] of Object.entries(architecture)) checked[name] = config === null ? null : checkedNetwork(config, name);
  const fine = checked.fine ?? null;
  const outputs = [{ name: "rgb", shape: [BATCH, 3], elemType: FLOAT }, { name: "sigma", shape: [BATCH], elemType: FLOAT }];
  if (fine === null) builder.network("coarse", checked.coarse, ...OUTPUT_NAMES);
  else {
    builder.network("fine", fine, ...OUTPUT_NAMES);
    builder.network("coarse", checked.coarse, ...COARSE_OUTPUT_NAMES);
    outputs.push({ name: "rgb_coarse", shape: [BATCH, 3], elemType: FLOAT }, { name: "sigma_coarse", shape: [BATCH], elemType: FLOAT });
  }
  const inputs = [{ name: "points", shape: [BATCH, 3], elemType: FLOAT }, { name: "viewdirs", shape: [BATCH, 3], elemType: FLOAT },
    { name: "noise", shape: [BATCH, noiseDims], elemType: FLOAT }];
  return { nodes: builder.nodes, constants: builder.constants, weights: builder.weights, inputs, outputs };
}

function refuse(source, what) {
  return new UserError(`${source}: the model's graph is not the one its scene exports: ${what}; export the scene again`);
}

function describe(node) {
  const attributes = node.attributes.map(([name, value]) => `, ${name}=${value}`).join("");
  return `${node.op}(${node.inputs.join(", ")}${attributes}) -> ${node.outputs.join(", ")}`;
}

const sameList = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);
const sameNode = (a, b) => a.op === b.op && sameList(a.inputs, b.inputs) && sameList(a.outputs, b.outputs) &&
  a.attributes.length === b.attributes.length && a.attributes.every(([n, v], i) => n === b.attributes[i][0] && v === b.attributes[i][1]);
const samePort = (a, b) => a !== null && a.name === b.name && a.elemType === b.elemType && sameList(a.shape, b.shape);
const portRepr = (port) => (port === null ? null : tuple(port.name, tuple(...port.shape)));

/** check_graph: refuse a model file whose graph differs from `expected`; return its weights (name -> Float32Array). */
export function checkGraph(file, expected, source) {
  if (file.unexpected.length) throw refuse(source, `it holds ${file.unexpected[0]}`);
  for (const [kind, got, want] of [["inputs", file.inputs, expected.inputs], ["outputs", file.outputs, expected.outputs]]) {
    if (got.length !== want.length || !got.every((port, i) => samePort(port, want[i]))) {
      throw refuse(source, `its ${kind} are ${repr(got.map(portRepr))}, expected ${repr(want.map(portRepr))}`);
    }
  }
  if (file.opsets.length !== 1 || file.opsets[0][0] !== "" || file.opsets[0][1] !== OPSET) {
    throw refuse(source, `it imports opsets ${repr(file.opsets.map(([d, v]) => tuple(d, v)))}, not [('', ${OPSET})]`);
  }
  const n = Math.min(file.nodes.length, expected.nodes.length);
  for (let i = 0; i < n; i++) {
    if (!sameNode(file.nodes[i], expected.nodes[i])) throw refuse(source, `node ${i} is ${describe(file.nodes[i])}, expected ${describe(expected.nodes[i])}`);
  }
  if (file.nodes.length !== expected.nodes.length) {
    const more = file.nodes.length - expected.nodes.length;
    throw refuse(source, `it has ${Math.abs(more)} ${more > 0 ? "more" : "fewer"} nodes than the ${expected.nodes.length} expected`);
  }
  const records = new Map();
  for (const record of file.initializers) {
    if (records.has(record.name)) throw refuse(source, `initializer ${repr(record.name)} appears twice`);
    records.set(record.name, record);
  }
  const wanted = new Set([...expected.weights.keys(), ...expected.constants.keys()]);
  const extra = [...records.keys()].filter((name) => !wanted.has(name)).sort();
  const missing = [...wanted].filter((name) => !records.has(name)).sort();
  if (extra.length || missing.length) {
    throw refuse(source, `initializer ${repr(extra.length ? extra[0] : missing[0])} is ${extra.length ? "extra" : "missing"}`);
  }
  for (const [name, constant] of expected.constants) {
    const isInt = constant.dtype === "int64";
    const record = records.get(name);
    const got = tensorArray(record, source, isInt ? INT64 : FLOAT);
    const gotValues = Array.from(got, (v) => (isInt ? Number(v) : v));
    const equal = sameList(record.dims, constant.shape) && gotValues.length === constant.values.length &&
      gotValues.every((v, i) => v === constant.values[i]);
    if (!equal) {
      const show = (values) => repr(values.slice(0, 4).map((v) => (isInt ? v : new PyFloat(v))));
      throw refuse(source, `constant ${repr(name)} holds ${show(gotValues)}…, expected ${show(constant.values)}…`);
    }
  }
  const weights = new Map();
  for (const [name, shape] of expected.weights) {
    const record = records.get(name);
    if (!sameList(record.dims, shape)) throw refuse(source, `weight ${repr(name)} has shape ${repr(record.dims)}, expected ${repr(shape)}`);
    weights.set(name, { shape, values: tensorArray(record, source) });
  }
  return weights;
}
