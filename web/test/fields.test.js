// The field kinds (src/fields/) against the graphs the Python runtime derives (runtime/fields): tests/test_web.py
// writes field_graph(architecture) as JSON for hash grids and their variants (fine, beside an MLP, other widths,
// degrees and level layouts), for imported nerfacto fields of both implementations and their variants (proposal
// networks, SH conventions, dense or hashed levels), and Python's refusal of architectures out of the caps. The
// JavaScript must derive the same nodes, constants (values to the bit), weights, ports and opset, and refuse with the
// same code and params.

import { test } from "node:test";
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";
import { sameRefusal } from "./refusals.js";
import { parseJson } from "../src/json.js";
import { fieldGraph } from "../src/fields/index.js";
import { gridLevels } from "../src/fields/hashgrid.js";

const root = process.env.NOISENERF_WEB_FIXTURES;
const skip = root ? false : "NOISENERF_WEB_FIXTURES is not set (tests/test_web.py writes the fixtures and sets it)";
const manifest = root ? JSON.parse(fs.readFileSync(path.join(root, "manifest.json"), "utf8")) : {};

/** A graph in the layout tests/test_web.py's graph_golden writes. */
const asJson = (graph) => ({
  opset: graph.opset,
  nodes: graph.nodes.map((node) => [node.op, node.inputs, node.outputs, node.attributes]),
  constants: [...graph.constants].map(([name, { dtype, shape, values }]) => [name, dtype, shape, values]),
  weights: [...graph.weights],
  inputs: graph.inputs.map((port) => [port.name, port.shape, port.elemType]),
  outputs: graph.outputs.map((port) => [port.name, port.shape, port.elemType]),
});

for (const [i, golden] of (manifest.graphs ?? []).entries()) {
  const { architecture, noise_dims: noiseDims, code, params, message, ...want } = golden;
  test(`field graph ${i}: ${code ? `refused (${code})` : "derived"} as Python does: ${architecture.slice(0, 100)}`, { skip }, () => {
    const derive = () => fieldGraph(parseJson(architecture, "architecture"), noiseDims);
    if (code) assert.throws(derive, (error) => sameRefusal(error, golden));
    else assert.deepStrictEqual(asJson(derive()), want);
  });
}

// The level scales are double products rounded once to float32 (runtime/fields/hashgrid.level_scales): the same
// bits in Python on any CPU and here, for scales that are not powers of two too.
test("grid level scales are Python's to the bit for Instant-NGP's per-level scales", {
  skip,
}, (t) => {
  const differ = [];
  for (const { per_level_scale: perLevelScale, scale } of manifest.scales ?? []) {
    const got = gridLevels(scale.length, 19, 16, perLevelScale).scale;
    const levels = scale.flatMap((want, l) => (got[l] === want ? [] : [`${l}: ${got[l]} != ${want}`]));
    if (levels.length) differ.push(`per_level_scale ${perLevelScale}: ${levels.length} levels differ (${levels.slice(0, 3).join(", ")}…)`);
  }
  for (const line of differ) t.diagnostic(line);
  assert.deepEqual(differ, []);
});
