// The worker pool (src/pool.js, here over Node's worker_threads: src/node/pool.js) against the Python runtime's
// golden pixels: chunks rendered out of order in two workers stitch to the same bytes; a worker's refusal reaches
// the caller as the same UserError (its code and params too).

import { test, after } from "node:test";
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";
import { reveal, UserError } from "../src/index.js";
import { loadBundle } from "../src/bundle.js";
import { checkModel } from "../src/model.js";
import { LocalRenderer, chunkJob, renderTile, tileNetwork } from "../src/reveal.js";
import { nodePool } from "../src/node/pool.js";

const root = process.env.NOISENERF_WEB_FIXTURES;
const skip = root ? false : "NOISENERF_WEB_FIXTURES is not set (tests/test_web.py writes the fixtures and sets it)";
const manifest = root ? JSON.parse(fs.readFileSync(path.join(root, "manifest.json"), "utf8")) : { fixtures: {} };
const read = (folder, name) => new Uint8Array(fs.readFileSync(path.join(root, folder, name)));

let pool = null;
const twoWorkers = async () => (pool ??= await nodePool(2));
after(() => pool?.terminate());

for (const [name, fixture] of Object.entries(manifest.fixtures)) {
  test(`${name}: two workers reveal Python's pixels byte for byte`, { skip }, async () => {
    const workers = await twoWorkers();
    const result = await reveal({ model: read(name, "model.onnx"), bundle: read(name, "secret.bundle"),
      openRenderer: (model, networks) => workers.open(model, networks) });
    const want = fs.readFileSync(path.join(root, name, fixture.pixels.file));
    assert.ok(Buffer.from(result.pixels).equals(want), "the pool's pixels differ from Python's");
    assert.equal(result.exact, fixture.exact);
  });
}

test("tiles cut into many small chunks, out of order in two workers, render the same colours as whole", { skip }, async () => {
  for (const name of Object.keys(manifest.fixtures)) {
    const model = read(name, "model.onnx"), checked = checkModel(model), config = checked.metadata.renderConfig;
    const bundle = await loadBundle(read(name, "secret.bundle"), "secret.bundle", checked.maskSecret);
    const local = await LocalRenderer.open(model, checked.networks);
    const workers = await (await twoWorkers()).open(model, checked.networks);
    for (const tile of bundle.tiles) {
      const network = tileNetwork(tile, checked.networks);
      const whole = await renderTile(tile, bundle, config, local, network);
      const chunked = await renderTile(tile, bundle, config, workers, network, null, 7);
      assert.ok(Buffer.from(chunked.buffer).equals(Buffer.from(whole.buffer)), `${name}: chunked colours differ`);
    }
    await local.release();
    await workers.release();
  }
});

test("a worker that dies is left out: the others render on and release does not wait for it", { skip }, async () => {
  const name = Object.keys(manifest.fixtures)[0];
  const model = read(name, "model.onnx"), checked = checkModel(model);
  const bundle = await loadBundle(read(name, "secret.bundle"), "secret.bundle", checked.maskSecret), tile = bundle.tiles[0];
  const job = () => chunkJob(tile, bundle, checked.metadata.renderConfig, tileNetwork(tile, checked.networks), 0, 2);
  const pool = await (await nodePool(2)).open(model, checked.networks);
  try {
    await pool.workers[0].endpoint.terminate();
    for (let waited = 0; !pool.workers[0].dead && waited < 100; waited++) await new Promise((resolve) => setTimeout(resolve, 20));
    assert.ok(pool.workers[0].dead);
    await assert.rejects(pool.call(pool.workers[0], { type: "close" }), /^Error: a reveal worker failed: it exited/);
    for (let i = 0; i < 3; i++) assert.equal((await pool.render(job())).length, 6);
    await pool.release();
  } finally {
    pool.terminate();
  }
});

test("a worker's refusal is the caller's UserError, and the pool renders on after it", { skip }, async () => {
  // a model of one network has no coarse outputs, which a network it lacks is asked for
  const name = Object.keys(manifest.fixtures).find((folder) => checkModel(read(folder, "model.onnx")).networks.length === 1);
  const model = read(name, "model.onnx"), checked = checkModel(model);
  const bundle = await loadBundle(read(name, "secret.bundle"), "secret.bundle", checked.maskSecret);
  const workers = await (await twoWorkers()).open(model, checked.networks);
  const tile = bundle.tiles[0], config = checked.metadata.renderConfig;
  await assert.rejects(workers.render(chunkJob(tile, bundle, config, "nonexistent", 0, 1)), (error) => {
    assert.ok(error instanceof UserError);
    assert.equal(error.code, "session.evaluate_failed"); // the code crosses the worker boundary as data
    assert.match(error.message, /^model\.onnx failed to evaluate: /);
    return true;
  });
  const colors = await workers.render(chunkJob(tile, bundle, config, checked.networks[0], 0, 1));
  assert.equal(colors.length, 3);
  assert.ok(colors.every(Number.isFinite));
  await workers.release();
});
