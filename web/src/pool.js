// Chunks rendered in parallel: a pool of workers (Web Workers in the page, worker_threads in Node's tests), each
// with its own onnxruntime-web sessions of one thread (one per network, of the graph pruned to its outputs: pruned
// once, here, and only the pruned bytes sent, one network at a time), each chunk rendered whole in one worker (rays,
// noise, the field, compositing: src/reveal.js's renderChunk). WASM threads would need a cross-origin isolated page,
// which a page opened from disk never is, and scale worse than separate sessions on separate chunks
// (docs/bench/browser).
//
// The driver's side is FieldPool, a renderer (slots, render, release) like LocalRenderer; the worker's is
// fieldWorker. They speak over endpoints {post(message, transfer), listen(onMessage, onError), terminate()}.

import * as ort from "onnxruntime-web";
import { postedError, receivedError } from "./errors.js";
import { LocalRenderer, OnnxField, prunedNetworks } from "./reveal.js";

/** The worker's side: a handler of the driver's messages, {id, type: "init", wasmBinary?} | {id, type: "open",
 * networks} (a renderer with no session yet) | {id, type: "session", network, model} (the model pruned to the
 * network's outputs) | {id, type: "chunk", job} | {id, type: "close"} -> Promise<[reply, transfer]>, the reply
 * {id, result} or {id, error} (error: src/errors.js postedError). Messages are answered one at a time, in order. */
export function fieldWorker() {
  let renderer = null, queue = Promise.resolve();
  const answer = async ({ id, type, ...data }) => {
    try {
      if (type === "init") {
        ort.env.wasm.numThreads = 1; // the pool is the parallelism
        if (data.wasmBinary) ort.env.wasm.wasmBinary = data.wasmBinary; // the single file: nothing to fetch
        return [{ id, result: null }, []];
      }
      if (type === "open") {
        const old = renderer;
        renderer = null;
        await old?.release();
        renderer = new LocalRenderer(new OnnxField(data.networks));
        return [{ id, result: null }, []];
      }
      if (type === "session") {
        if (renderer === null) throw new Error("no model is open in this worker");
        await renderer.field.open(data.network, data.model);
        return [{ id, result: null }, []];
      }
      if (type === "chunk") {
        if (renderer === null) throw new Error("no model is open in this worker");
        const colors = await renderer.render(data.job);
        return [{ id, result: colors }, [colors.buffer]];
      }
      if (type === "close") {
        const old = renderer;
        renderer = null;
        await old?.release();
        return [{ id, result: null }, []];
      }
      throw new Error(`unknown message ${String(type)}`);
    } catch (error) {
      return [{ id, error: postedError(error) }, []];
    }
  };
  return (data) => {
    const answered = queue.then(() => answer(data));
    queue = answered;
    return answered;
  };
}

/** The driver's side over started workers' endpoints: `await FieldPool.start(endpoints, wasmBinary)`, then per
 * reveal `await pool.open(model, networks, needed)` (the renderer), `pool.release()`; `terminate()` ends the
 * workers. */
export class FieldPool {
  static async start(endpoints, wasmBinary = null) {
    const pool = new FieldPool(endpoints);
    try {
      await Promise.all(pool.workers.map((worker) => pool.call(worker, { type: "init", wasmBinary })));
    } catch (error) {
      pool.terminate();
      throw error;
    }
    return pool;
  }

  constructor(endpoints) {
    this.workers = endpoints.map((endpoint) => ({ endpoint, waiting: new Map() }));
    this.slots = endpoints.length;
    this.nextId = 0;
    for (const worker of this.workers) {
      worker.endpoint.listen((data) => this.answered(worker, data), (error) => this.failed(worker, error));
    }
  }

  answered(worker, { id, result, error }) {
    const call = worker.waiting.get(id);
    if (!call) return;
    worker.waiting.delete(id);
    if (error === undefined) call.resolve(result);
    else call.reject(receivedError(error));
  }

  /** A worker that died (out of memory, a crash) fails everything it was given, and all it is given after. */
  failed(worker, error) {
    worker.dead = new Error(`a reveal worker failed: ${String(error?.message ?? error)}`);
    for (const call of worker.waiting.values()) call.reject(worker.dead);
    worker.waiting.clear();
  }

  call(worker, message, transfer = []) {
    return new Promise((resolve, reject) => {
      if (worker.dead) return reject(worker.dead);
      const id = this.nextId++;
      worker.waiting.set(id, { resolve, reject });
      try {
        worker.endpoint.post({ id, ...message }, transfer);
      } catch (error) { // not sent (a value that cannot be cloned): nothing will answer it
        worker.waiting.delete(id);
        reject(error);
      }
    });
  }

  /** A session per network `needed` (all the model's by default) in every worker, of the graph pruned to that
   * network's outputs; the pool is then the reveal's renderer. The model is pruned here once per network and the
   * pruned bytes sent to every worker before the next network's are made: a worker is sent no more than it runs. If
   * any worker fails to open one, those opened are closed and the first failure thrown. */
  async open(model, networks, needed = networks) {
    try {
      await this.each({ type: "open", networks });
      for (const [network, pruned] of prunedNetworks(model, networks, needed)) {
        await this.each({ type: "session", network, model: pruned });
      }
    } catch (error) {
      await this.release();
      throw error;
    }
    return this;
  }

  /** A message to every worker; once all have answered, the first failure is thrown. */
  async each(message) {
    const answers = await Promise.allSettled(this.workers.map((worker) => this.call(worker, message)));
    const failure = answers.find((result) => result.status === "rejected");
    if (failure) throw failure.reason;
  }

  /** A chunk (src/reveal.js's chunkJob) to the worker with the fewest waiting; its own stored values are
   * handed over, not copied. */
  render(job) {
    const alive = this.workers.filter((worker) => !worker.dead);
    const worker = (alive.length ? alive : this.workers).reduce((best, next) => (next.waiting.size < best.waiting.size ? next : best));
    const noise = job.noise, own = [noise.coefficients ?? noise.values, noise.basis?.escapes, noise.basis?.escapeNoise];
    return this.call(worker, { type: "chunk", job }, own.filter(Boolean).map((array) => array.buffer));
  }

  /** Every live worker's session closed (a dead worker has none to close). */
  async release() {
    await Promise.allSettled(this.workers.filter((worker) => !worker.dead).map((worker) => this.call(worker, { type: "close" })));
  }

  terminate() {
    for (const worker of this.workers) {
      worker.endpoint.terminate();
      this.failed(worker, "terminated");
    }
  }
}
