// The JavaScript reveal against golden files written by the Python runtime (tests/test_web.py writes them and
// runs these tests with NOISENERF_WEB_FIXTURES set; without it they skip). Rays and expanded noise must equal
// Python's where the port is bit-exact (measured and reported otherwise); colours come from another onnxruntime
// build (WASM), so they are compared within a tolerance and their largest difference reported; the revealed 8-bit
// pixels must be Python's byte for byte, for every fixture, and every refusal must read as the CLI's.

import { test } from "node:test";
import assert from "node:assert/strict";
import fs from "node:fs";
import path from "node:path";
import { reveal } from "../src/index.js";
import { sameRefusal } from "./refusals.js";
import { loadBundle, tileRows } from "../src/bundle.js";
import { checkModel } from "../src/model.js";
import { cameraRayBatch } from "../src/camera.js";
import { LocalRenderer, renderTile, tileNetwork } from "../src/reveal.js";

const root = process.env.NOISENERF_WEB_FIXTURES;
const skip = root ? false : "NOISENERF_WEB_FIXTURES is not set (tests/test_web.py writes the fixtures and sets it)";
const manifest = root ? JSON.parse(fs.readFileSync(path.join(root, "manifest.json"), "utf8")) : { fixtures: {}, tampered: [] };

function golden(folder, entry) {
  const bytes = fs.readFileSync(path.join(folder, entry.file));
  const copy = new Uint8Array(bytes).buffer;
  return entry.dtype === "float32" ? new Float32Array(copy) : new Uint8Array(copy);
}

function compare(got, want) {
  assert.equal(got.length, want.length);
  let maxDiff = 0, unequal = 0, scale = 0;
  for (let i = 0; i < got.length; i++) {
    const d = Math.abs(got[i] - want[i]);
    if (!(d <= maxDiff)) maxDiff = Number.isNaN(d) ? Infinity : d;
    if (got[i] !== want[i]) unequal++;
    scale = Math.max(scale, Math.abs(want[i]));
  }
  return { maxDiff, unequal, total: got.length, scale };
}

const summary = {};
const FLOAT32_APART = 2 ** -20; // a few ulps of the largest value a tile holds

for (const [name, fixture] of Object.entries(manifest.fixtures)) {
  const folder = path.join(root ?? "", name);
  test(`${name}: rays, noise and colours against Python`, { skip }, async (t) => {
    const model = fs.readFileSync(path.join(folder, "model.onnx"));
    const bundleBytes = fs.readFileSync(path.join(folder, "secret.bundle"));
    const checked = checkModel(new Uint8Array(model));
    const bundle = await loadBundle(new Uint8Array(bundleBytes), "secret.bundle", checked.maskSecret);
    assert.equal(checked.metadata.fingerprint, fixture.fingerprint);
    const renderer = await LocalRenderer.open(new Uint8Array(model), checked.networks);
    const stats = { rays: [], noise: [], colors: [] };
    for (const [i, tile] of bundle.tiles.entries()) {
      const want = fixture.tiles[i];
      const rays = cameraRayBatch(tile.camera, checked.metadata.renderConfig);
      for (const key of ["origins", "directions", "viewdirs"]) stats.rays.push(compare(rays[key], golden(folder, want[key])));
      const n = tile.rect[2] * tile.rect[3];
      stats.noise.push(compare(tileRows(tile, bundle, 0, n).values, golden(folder, want.noise)));
      const colors = await renderTile(tile, bundle, checked.metadata.renderConfig, renderer, tileNetwork(tile, checked.networks));
      stats.colors.push(compare(colors, golden(folder, want.colors)));
    }
    await renderer.release();
    const reduce = (list) => list.reduce((a, b) => ({ maxDiff: Math.max(a.maxDiff, b.maxDiff), unequal: a.unequal + b.unequal,
      total: a.total + b.total, scale: Math.max(a.scale, b.scale) }), { maxDiff: 0, unequal: 0, total: 0, scale: 0 });
    summary[name] = Object.fromEntries(Object.entries(stats).map(([k, v]) => [k, reduce(v)]));
    t.diagnostic(`${name}: ${JSON.stringify(summary[name])}`);
    // numpy's float32 order, without the multiply-adds its BLAS may fuse: float32 rounding apart (what the
    // product promises, the 8-bit pixels, is checked byte for byte below)
    for (const what of ["rays", "noise"]) {
      const { maxDiff, scale } = summary[name][what];
      assert.ok(maxDiff <= FLOAT32_APART * Math.max(1, scale), `${what} differ by ${maxDiff} (largest value ${scale})`);
    }
    // the field itself is onnxruntime-web's WASM build, not Python's onnxruntime: close, not equal
    assert.ok(summary[name].colors.maxDiff <= 1e-4, `colours differ by ${summary[name].colors.maxDiff}`);
  });

  test(`${name}: the revealed 8-bit pixels are Python's byte for byte`, { skip }, async () => {
    const result = await reveal({ model: new Uint8Array(fs.readFileSync(path.join(folder, "model.onnx"))),
      bundle: new Uint8Array(fs.readFileSync(path.join(folder, "secret.bundle"))) });
    const want = golden(folder, fixture.pixels);
    assert.equal(result.kind, "image");
    assert.equal(result.width, fixture.width);
    assert.equal(result.height, fixture.height);
    assert.equal(result.exact, fixture.exact);
    assert.ok(Buffer.from(result.pixels).equals(Buffer.from(want)), `${compare(result.pixels, want).unequal} 8-bit values differ`);
    if (fixture.exact) assert.equal(result.sha256, fixture.sha256);
    assert.deepEqual([...result.bytes.subarray(0, 8)], [137, 80, 78, 71, 13, 10, 26, 10]);
  });
}

for (const [name, payload] of Object.entries(manifest.payloads ?? {})) {
  test(`${name}: the payload's bytes are noisenerf-reveal's`, { skip }, async () => {
    const folder = path.join(root, name);
    const stages = new Set();
    const result = await reveal({ model: new Uint8Array(fs.readFileSync(path.join(folder, "model.onnx"))),
      bundle: new Uint8Array(fs.readFileSync(path.join(folder, "secret.bundle"))), passphrase: payload.passphrase,
      onProgress: ({ stage }) => stages.add(stage) });
    const want = fs.readFileSync(path.join(folder, payload.file));
    assert.equal(result.kind, "file");
    assert.ok(Buffer.from(result.bytes).equals(want), "the payload's bytes differ");
    assert.equal(result.name, payload.name);
    assert.equal(result.sha256, payload.sha256);
    assert.equal(result.sealed, payload.sealed);
    assert.deepEqual([result.width, result.height], [payload.width, payload.height]);
    assert.deepEqual([...stages].sort(), payload.sealed ? ["kdf", "render"] : ["render"]);
  });
}

for (const tampered of manifest.tampered) {
  test(`refused as noisenerf-reveal refuses it: ${tampered.case} (${tampered.code})`, { skip }, async () => {
    const folder = path.join(root, tampered.folder);
    await assert.rejects(reveal({ model: new Uint8Array(fs.readFileSync(path.join(folder, "model.onnx"))),
      bundle: new Uint8Array(fs.readFileSync(path.join(folder, "secret.bundle"))), passphrase: tampered.passphrase }),
    (error) => sameRefusal(error, tampered));
  });
}

test("summary of the measured differences", { skip }, (t) => {
  for (const [name, stats] of Object.entries(summary)) t.diagnostic(`${name} ${JSON.stringify(stats)}`);
});
