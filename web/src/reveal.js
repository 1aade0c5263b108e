// Mirrors runtime/reveal.py (render_tile, tile_field, reveal), with runtime/render.py's chunking (rays_per_chunk,
// render_in_chunks), runtime/marching.py's front-to-back march (16 samples at a time, early_stop 0: only rays
// whose transmittance is exactly 0 stop), runtime/networks.py's render network, and runtime/session.py's points
// per onnxruntime run (DEFAULT_BATCH) and its sessions: one per network, of the graph pruned to that network's
// outputs (onnxruntime-web runs every node of a graph whatever is fetched: a fine network's model would run its
// coarse network too, a nerfacto model its proposal networks). A chunk of rays holds its own noise only: memory is
// bounded by the chunk.

import * as ort from "onnxruntime-web";
import { sha256 } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { UserError } from "./errors.js";
import { OUTPUT_NAMES, COARSE_OUTPUT_NAMES, INPUT_NAMES } from "./graph.js";
import { parseModel, prunedModel } from "./onnx.js";
import { cameraRayBatch } from "./camera.js";
import { samplePositions, sampleAlong } from "./sampling.js";
import { compositeRays, opticalDepth, pairwiseSum, toUint8 } from "./compositing.js";
import { chunkNoise, chunkRows } from "./bundle.js";

const f32 = Math.fround;
export const CHUNK_SAMPLES = 1 << 17;
export const CHUNK_RAYS = 4096;
export const DEFAULT_BATCH = 16384;
const MARCH_SAMPLES = 16;

export const renderNetwork = (names) => (names.includes("fine") ? "fine" : "coarse");
export const raysPerChunk = (nSamples, mostRays = CHUNK_RAYS) => Math.max(1, Math.min(mostRays, Math.floor(CHUNK_SAMPLES / nSamples)));

/** The outputs network `name` answers on (runtime/session.py's OnnxField.network): the render network's rgb, sigma,
 * the other's rgb_coarse, sigma_coarse. */
export const networkOutputs = (networks, name) =>
  (name === renderNetwork(networks) ? OUTPUT_NAMES : COARSE_OUTPUT_NAMES);

/** [network, the model's bytes pruned to its outputs] for each of `needed` (of the model's `networks`), made one at
 * a time as they are asked for, so that one pruned copy is held at once beside the model. */
export function* prunedNetworks(model, networks, needed = networks) {
  const file = parseModel(model, "model.onnx");
  for (const network of needed) yield [network, prunedModel(file, networkOutputs(networks, network))];
}

/** OnnxField: onnxruntime-web sessions, one per network (session_for), each of the graph pruned to that network's
 * outputs; `create` opens one for each of the networks `needed` (all the model's by default), on `provider`: "wasm"
 * (the page's), or "webgpu" in a build of onnxruntime-web that has it (tools/webgpu_exactness.py measures it). */
export class OnnxField {
  static async create(model, networks, needed = networks, provider = "wasm") {
    const field = new OnnxField(networks, provider);
    try {
      for (const [network, pruned] of prunedNetworks(model, networks, needed)) await field.open(network, pruned);
    } catch (error) {
      await field.release();
      throw error;
    }
    return field;
  }
  constructor(networks, provider = "wasm") {
    this.networks = networks;
    this.provider = provider;
    this.sessions = new Map(); // network -> session
  }
  /** A session of `model` (the graph pruned to the network's outputs: prunedNetworks) answering for `network`.
   * onnxruntime's own logging is silenced, as runtime/session.py's is (a pruned graph's unused initializers would
   * each be a warning); a failure is thrown. */
  async open(network, model) {
    const session = await ort.InferenceSession.create(model, { executionProviders: [this.provider], logSeverityLevel: 4 });
    await this.sessions.get(network)?.release?.();
    this.sessions.set(network, session);
  }
  session(network) {
    const session = this.sessions.get(network);
    if (session === undefined) throw new Error(`no session answers for the ${network} network`);
    return session;
  }
  /** points (m·3), viewdirs (m·3), noise (m·dims) -> {rgb (m·3), sigma (m)}, DEFAULT_BATCH points per run. */
  async evaluate(network, points, viewdirs, noise, m, dims) {
    const [rgbName, sigmaName] = networkOutputs(this.networks, network);
    const rgb = new Float32Array(m * 3), sigma = new Float32Array(m);
    for (let start = 0; start < m; start += DEFAULT_BATCH) {
      const n = Math.min(DEFAULT_BATCH, m - start);
      const feeds = {
        [INPUT_NAMES[0]]: new ort.Tensor("float32", points.subarray(start * 3, (start + n) * 3), [n, 3]),
        [INPUT_NAMES[1]]: new ort.Tensor("float32", viewdirs.subarray(start * 3, (start + n) * 3), [n, 3]),
        [INPUT_NAMES[2]]: new ort.Tensor("float32", noise.subarray(start * dims, (start + n) * dims), [n, dims]),
      };
      let result;
      try {
        result = await this.session(network).run(feeds, [rgbName, sigmaName]);
      } catch (error) {
        throw new UserError(`model.onnx failed to evaluate: ${String(error.message ?? error).split(/\s+/).join(" ").slice(0, 200)}`,
          { code: "session.evaluate_failed" });
      }
      rgb.set(result[rgbName].data, start * 3);
      sigma.set(result[sigmaName].data, start);
      for (const tensor of Object.values(result)) tensor.dispose?.();
    }
    return { rgb, sigma };
  }
  /** Every session closed. */
  async release() {
    const sessions = [...this.sessions.values()];
    this.sessions.clear();
    await Promise.all(sessions.map((session) => session.release?.()));
  }
}

/** The noisy field evaluated front to back over m rays of S samples (march_rays with no grid). */
async function marchRays(field, network, points, viewdirs, deltas, rows, m, S) {
  const { values: noiseRows, perSample, dims } = rows;
  const sigmas = new Float32Array(m * S), rgbs = new Float32Array(m * S * 3);
  const depthSoFar = new Float32Array(m);
  const chunkDepths = new Float32Array(MARCH_SAMPLES);
  const chosen = new Int32Array(m * Math.min(MARCH_SAMPLES, S));
  for (let s0 = 0; s0 < S; s0 += MARCH_SAMPLES) {
    const s1 = Math.min(s0 + MARCH_SAMPLES, S);
    let n = 0;
    for (let r = 0; r < m; r++) {
      if (f32(Math.exp(-depthSoFar[r])) > 0) for (let s = s0; s < s1; s++) chosen[n++] = r * S + s;
    }
    if (n === m && S === 1) {
      // one sample a ray, every ray (a compact or exact tile): the chunk's own arrays are already in order
      const out = await field.evaluate(network, points, viewdirs, noiseRows, n, dims);
      sigmas.set(out.sigma);
      rgbs.set(out.rgb);
    } else if (n) {
      const p = new Float32Array(n * 3), v = new Float32Array(n * 3), noise = new Float32Array(n * dims);
      for (let q = 0; q < n; q++) {
        const index = chosen[q], r = Math.floor(index / S), s = index - r * S;
        for (let c = 0; c < 3; c++) { p[q * 3 + c] = points[index * 3 + c]; v[q * 3 + c] = viewdirs[r * 3 + c]; }
        const row = (r * perSample + (perSample === 1 ? 0 : s)) * dims;
        for (let d = 0; d < dims; d++) noise[q * dims + d] = noiseRows[row + d];
      }
      const out = await field.evaluate(network, p, v, noise, n, dims);
      for (let q = 0; q < n; q++) {
        const index = chosen[q];
        sigmas[index] = out.sigma[q];
        for (let c = 0; c < 3; c++) rgbs[index * 3 + c] = out.rgb[q * 3 + c];
      }
    }
    for (let r = 0; r < m; r++) {
      for (let s = s0; s < s1; s++) chunkDepths[s - s0] = opticalDepth(sigmas[r * S + s], deltas[r * S + s]);
      depthSoFar[r] = f32(depthSoFar[r] + pairwiseSum(chunkDepths, 0, s1 - s0));
    }
  }
  return { sigmas, rgbs };
}

/** What a worker needs to render pixels start..stop of a tile (structured-cloneable, the chunk's noise alone). */
export function chunkJob(tile, bundle, config, network, start, stop) {
  return { camera: tile.camera, config, sampling: tile.sampling, network, start, stop,
    noise: chunkNoise(tile, bundle, start, stop) };
}

/** render_chunk: a chunk's rays, samples, noisy field and compositing -> colours ((stop − start)·3 float32). */
export async function renderChunk(job, field) {
  const { start, stop, config } = job, m = stop - start;
  const rays = cameraRayBatch(job.camera, config, start, stop);
  const tVals = samplePositions(job.sampling);
  const { points, deltas } = sampleAlong(rays, 0, m, tVals);
  const { sigmas, rgbs } = await marchRays(field, job.network, points, rays.viewdirs, deltas, chunkRows(job.noise), m, tVals.length);
  return compositeRays(sigmas, rgbs, deltas, m, tVals.length, config.background);
}

/** Chunks rendered in this thread on its onnxruntime-web sessions (one per network `needed`: OnnxField), one at a
 * time (a renderer: slots, render, release; src/pool.js's FieldPool is the other, over Web Workers). */
export class LocalRenderer {
  static async open(model, networks, needed = networks, provider = "wasm") {
    return new LocalRenderer(await OnnxField.create(model, networks, needed, provider));
  }
  constructor(field) {
    this.field = field;
    this.slots = 1;
    this.queue = Promise.resolve();
  }
  render(job) {
    const rendered = this.queue.then(() => renderChunk(job, this.field));
    this.queue = rendered.catch(() => {});
    return rendered;
  }
  async release() {
    await this.queue; // chunks already queued finish (or fail) before their sessions go
    await this.field.release();
  }
}

/** render_tile: a tile's secret view, (height·width·3) float32, a chunk of rays (and of noise) at a time, the
 * renderer's slots + 1 chunks in flight (so that none of its workers waits for the next), each holding its own
 * noise only: memory is bounded by the chunk. */
export async function renderTile(tile, bundle, config, renderer, network, progress = null,
  chunk = raysPerChunk(tile.sampling.nSamples)) {
  const n = tile.rect[2] * tile.rect[3];
  const colors = new Float32Array(n * 3);
  const inFlight = new Set();
  for (let start = 0; start < n; start += chunk) {
    const stop = Math.min(start + chunk, n);
    const done = renderer.render(chunkJob(tile, bundle, config, network, start, stop)).then((chunkColors) => {
      colors.set(chunkColors, start * 3);
      progress?.(stop - start);
    });
    inFlight.add(done);
    done.then(() => inFlight.delete(done), () => {});
    if (inFlight.size > renderer.slots) await Promise.race(inFlight);
  }
  await Promise.all(inFlight);
  return colors;
}

/** tile_field: the network a tile's noise was trained through, refusing one the model lacks. */
export function tileNetwork(tile, networks) {
  const name = tile.network ?? renderNetwork(networks);
  if (!networks.includes(name)) {
    throw new UserError(`bundle tile at (${tile.rect[0]}, ${tile.rect[1]}) needs the ${name} network; this model has only ${networks.join(" and ")}`,
      { code: "reveal.missing_network", at: [tile.rect[0], tile.rect[1]], network: name, networks: [...networks] });
  }
  return name;
}

/** The networks a bundle's tiles render through (every tile's checked: tileNetwork), in the model's order: the
 * sessions a reveal needs. */
export function bundleNetworks(bundle, networks) {
  const chosen = new Set(bundle.tiles.map((tile) => tileNetwork(tile, networks)));
  return networks.filter((name) => chosen.has(name));
}

/** reveal: every tile rendered, quantised as it comes and stitched, the SHA-256 checked -> {pixels, exact, sha256}.
 * It holds the 8-bit secret and one tile's floats, as runtime/reveal.py does. */
export async function revealBundle(bundle, config, renderer, networks, progress) {
  const chosen = bundle.tiles.map((tile) => tileNetwork(tile, networks));
  const { width, height } = bundle;
  const pixels = new Uint8Array(width * height * 3);
  for (let t = 0; t < bundle.tiles.length; t++) {
    const tile = bundle.tiles[t];
    const [x0, y0, w, h] = tile.rect;
    const tilePixels = toUint8(await renderTile(tile, bundle, config, renderer, chosen[t], progress));
    for (let y = 0; y < h; y++) pixels.set(tilePixels.subarray(y * w * 3, (y + 1) * w * 3), ((y0 + y) * width + x0) * 3);
  }
  const digest = bytesToHex(sha256(pixels));
  return { pixels, exact: digest === bundle.secretSha256, sha256: digest };
}
