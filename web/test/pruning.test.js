// The graph each session runs (src/onnx.js's prunedModel, runtime/onnx_file.py's pruned_model): onnxruntime-web
// evaluates every node of a graph whatever is fetched, so each network gets a session of the model pruned to its
// outputs. tests/test_web.py writes Python's pruned bytes of a fine network's and the nerfacto scenes' models (under
// pruned/, described by the manifest's `pruned`): the JavaScript must give the same bytes, which keep only the
// fetched outputs and fewer nodes, and compute those outputs as the whole graph does. The renderers (this thread's
// and the worker pool's) open a session per network the bundle's tiles name, each of the pruned graph, and a worker
// is sent the pruned bytes only.

import { test } from "node:test";
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";
import * as ort from "onnxruntime-web";
import { reveal } from "../src/index.js";
import { parseModel, prunedModel } from "../src/onnx.js";
import { checkModel } from "../src/model.js";
import { LocalRenderer, networkOutputs, renderNetwork } from "../src/reveal.js";
import { FieldPool, fieldWorker } from "../src/pool.js";

const root = process.env.NOISENERF_WEB_FIXTURES;
const skip = root ? false : "NOISENERF_WEB_FIXTURES is not set (tests/test_web.py writes the fixtures and sets it)";
const manifest = root ? JSON.parse(fs.readFileSync(path.join(root, "manifest.json"), "utf8")) : { fixtures: {} };
const read = (...names) => new Uint8Array(fs.readFileSync(path.join(root, ...names)));
const outputNames = (file) => file.outputs.map((port) => port.name);

/** Deterministic float32 values in [low, high) (a linear congruential generator). */
function values(count, seed, low = -1, high = 1) {
  const out = new Float32Array(count);
  let state = seed >>> 0;
  for (let i = 0; i < count; i++) {
    state = (Math.imul(state, 1664525) + 1013904223) >>> 0;
    out[i] = low + (high - low) * (state / 2 ** 32);
  }
  return out;
}

/** A session's outputs on n points (random points, unit view directions, noise). */
async function run(session, outputs, noiseDims, n = 1000) {
  const viewdirs = values(n * 3, 2);
  for (let i = 0; i < n; i++) {
    const norm = Math.hypot(viewdirs[i * 3], viewdirs[i * 3 + 1], viewdirs[i * 3 + 2]);
    for (let c = 0; c < 3; c++) viewdirs[i * 3 + c] /= norm;
  }
  const result = await session.run({
    points: new ort.Tensor("float32", values(n * 3, 1, -2, 2), [n, 3]),
    viewdirs: new ort.Tensor("float32", viewdirs, [n, 3]),
    noise: new ort.Tensor("float32", values(n * noiseDims, 3, -0.1, 0.1), [n, noiseDims]),
  }, outputs);
  return outputs.map((name) => result[name].data);
}

for (const golden of manifest.pruned ?? []) {
  const label = `${golden.model} pruned to ${golden.outputs.join(", ")}`;

  test(`${label}: Python's bytes, the fetched outputs alone, fewer nodes`, { skip }, () => {
    const whole = parseModel(read(golden.model), "model.onnx");
    const pruned = prunedModel(whole, golden.outputs);
    assert.ok(Buffer.from(pruned).equals(Buffer.from(read(golden.file))), "the pruned bytes differ from Python's");
    const file = parseModel(pruned, "pruned");
    assert.deepEqual(outputNames(file), golden.outputs);
    assert.equal(file.nodes.length, golden.nodes);
    assert.equal(whole.nodes.length, golden.whole_nodes);
    if (outputNames(whole).length > golden.outputs.length) assert.ok(file.nodes.length < whole.nodes.length);
    else assert.ok(Buffer.from(pruned).equals(Buffer.from(whole.data)), "a model pruned to all its outputs changed");
    // what the pruned graph keeps is the whole graph's: every node, port, opset and initializer as it was
    const keptOutputs = new Set(file.nodes.map((node) => node.outputs[0]));
    assert.deepEqual(file.nodes, whole.nodes.filter((node) => keptOutputs.has(node.outputs[0])));
    const kept = ({ inputs, opsets, irVersion, metadataProps }) => [inputs, opsets, irVersion, metadataProps];
    assert.deepEqual(kept(file), kept(whole));
    assert.deepEqual(file.initializers.map((t) => t.name), whole.initializers.map((t) => t.name));
  });

  test(`${label}: onnxruntime-web computes the whole graph's values`, { skip }, async () => {
    const model = read(golden.model), file = parseModel(model, "model.onnx");
    const noiseDims = file.inputs.find((port) => port.name === "noise").shape[1];
    const whole = await ort.InferenceSession.create(model, { executionProviders: ["wasm"] });
    const pruned = await ort.InferenceSession.create(prunedModel(file, golden.outputs),
      { executionProviders: ["wasm"], logSeverityLevel: 4 });
    assert.deepEqual(pruned.outputNames, golden.outputs);
    const [want, got] = [await run(whole, golden.outputs, noiseDims), await run(pruned, golden.outputs, noiseDims)];
    for (const [i, name] of golden.outputs.entries()) {
      assert.ok(Buffer.from(got[i].buffer).equals(Buffer.from(want[i].buffer)), `${name} differs from the whole graph's`);
    }
    await Promise.all([whole.release(), pruned.release()]);
  });
}

/** The networks a fixture's tiles name (Python's tile.network, or the render network), in the model's order. */
const tileNetworks = (fixture, networks) => networks.filter((name) =>
  fixture.tiles.some((tile) => (tile.network ?? renderNetwork(networks)) === name));

test("a renderer's sessions are each of the graph pruned to one network's outputs", { skip }, async () => {
  for (const name of Object.keys(manifest.fixtures)) {
    const model = read(name, "model.onnx"), { networks } = checkModel(model);
    const renderer = await LocalRenderer.open(model, networks);
    assert.deepEqual([...renderer.field.sessions.keys()], networks);
    for (const network of networks) {
      const session = renderer.field.sessions.get(network);
      assert.deepEqual(session.outputNames, networkOutputs(networks, network), `${name} ${network}`);
    }
    await renderer.release();
    assert.equal(renderer.field.sessions.size, 0);
  }
});

test("a reveal opens sessions for the networks its tiles name only, and reveals Python's pixels", { skip }, async () => {
  for (const [name, fixture] of Object.entries(manifest.fixtures)) {
    const model = read(name, "model.onnx"), { networks } = checkModel(model);
    let opened = null;
    const result = await reveal({ model, bundle: read(name, "secret.bundle"), openRenderer: async (...args) => {
      const renderer = await LocalRenderer.open(...args);
      opened = [...renderer.field.sessions.keys()];
      return renderer;
    } });
    assert.deepEqual(opened, tileNetworks(fixture, networks), name);
    assert.ok(Buffer.from(result.pixels).equals(Buffer.from(read(name, fixture.pixels.file))), `${name}: pixels differ`);
  }
});

/** Workers in this thread (src/pool.js's fieldWorker behind an endpoint), every message they are sent kept. */
function recordingEndpoint(sent) {
  const answer = fieldWorker();
  let deliver = null;
  return {
    post: (message) => {
      sent.push(message);
      answer(structuredClone(message)).then(([reply]) => deliver(reply));
    },
    listen: (onMessage) => { deliver = onMessage; },
    terminate: () => {},
  };
}

test("a pool's workers are sent each network's pruned model alone, and reveal Python's pixels", { skip }, async () => {
  const sent = [];
  const pool = await FieldPool.start([recordingEndpoint(sent), recordingEndpoint(sent)]);
  for (const [name, fixture] of Object.entries(manifest.fixtures)) {
    const model = read(name, "model.onnx"), { file: whole, networks } = checkModel(model);
    sent.length = 0;
    const result = await reveal({ model, bundle: read(name, "secret.bundle"),
      openRenderer: (...args) => pool.open(...args) });
    assert.ok(Buffer.from(result.pixels).equals(Buffer.from(read(name, fixture.pixels.file))), `${name}: pixels`);
    const sessions = sent.filter((message) => message.type === "session");
    const needed = tileNetworks(fixture, networks);
    assert.deepEqual(sessions.map((message) => message.network), needed.flatMap((network) => [network, network]));
    for (const message of sessions) {
      const file = parseModel(message.model, "sent");
      assert.deepEqual(outputNames(file), networkOutputs(networks, message.network), name);
      assert.ok(Buffer.from(message.model).equals(Buffer.from(prunedModel(whole, outputNames(file)))));
    }
    // opened for every network of the model (by default), each network's pruned bytes are sent in turn
    await pool.open(model, networks);
    assert.deepEqual(sent.filter((message) => message.type === "session").slice(sessions.length).map((m) => m.network),
      networks.flatMap((network) => [network, network]));
    await pool.release();
    if (outputNames(whole).length > 2) { // a model of more than one network's outputs is never sent whole
      assert.ok(sent.every((message) => !Object.values(message).some((value) => value instanceof Uint8Array &&
        value.length >= model.length)), `${name}: a worker was sent the whole model`);
    }
  }
  pool.terminate();
});
