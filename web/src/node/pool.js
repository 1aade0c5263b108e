// A FieldPool of Node worker_threads (./field-worker.js): the library's parallel renderer in Node, as the page's
// worker pool is in the browser. `reveal({model, bundle, openRenderer: (...args) => pool.open(...args)})`.
import { Worker } from "node:worker_threads";
import { FieldPool } from "../pool.js";

const endpoint = (worker) => ({
  post: (message, transfer) => worker.postMessage(message, transfer),
  listen: (onMessage, onError) => {
    worker.on("message", onMessage);
    worker.on("error", onError);
    worker.on("exit", (code) => onError(`it exited (code ${code})`));
  },
  terminate: () => worker.terminate(),
});

/** A started pool of `size` workers; terminate() it when done. */
export const nodePool = (size) =>
  FieldPool.start(Array.from({ length: size }, () => endpoint(new Worker(new URL("./field-worker.js", import.meta.url)))));
