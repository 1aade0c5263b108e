// The page's Web Worker, in one of two roles by its name (src/page/page.js starts both). The reveal worker runs the
// reveal library (src/index.js) so that the page stays responsive, rendering through a pool of field workers
// (src/pool.js): this same script, onnxruntime-web sessions of their own, joined to the reveal worker by MessagePorts.
// The reveal worker's messages in: {id, type: "init", wasmBinary?} | {id, type: "pool", ports} | {type:
// "fieldFailed", index, message} | {id, type: "inspect", bundle} | {id, type: "reveal", model, bundle,
// passphrase}. Out: {id, type: "progress", progress} | {id, type: "done", result} | {id, type: "error", message,
// refusal} (src/errors.js postedError: a UserError's code and params travel as data, page.js rebuilds it). A field
// worker's one message in: {port}.

import { reveal, inspectBundle, openBundle } from "../index.js";
import { postedError, receivedError } from "../errors.js";
import { FieldPool, fieldWorker } from "../pool.js";
import { FIELD_WORKER } from "./roles.js";

let wasmBinary = null, pool = null;
let failed = []; // per field worker: what the page's word that it died calls (FieldPool.failed)

const portEndpoint = (port, index) => ({
  post: (message, transfer) => port.postMessage(message, transfer),
  listen: (onMessage, onError) => {
    port.onmessage = (event) => onMessage(event.data);
    failed[index] = onError;
  },
  terminate: () => port.close(),
});

async function handle({ id, type, ...data }) {
  try {
    if (type === "init") {
      wasmBinary = data.wasmBinary ?? null; // the single file hands the WASM binary over: nothing is fetched from file://
      self.postMessage({ id, type: "done", result: null });
    } else if (type === "pool") {
      pool?.terminate();
      pool = null;
      failed = [];
      pool = await FieldPool.start(data.ports.map(portEndpoint), wasmBinary);
      self.postMessage({ id, type: "done", result: null });
    } else if (type === "fieldFailed") {
      failed[data.index]?.(data.message);
    } else if (type === "inspect") {
      self.postMessage({ id, type: "done", result: await inspectBundle(data.bundle) });
    } else if (type === "reveal" && data.modelRefusal) {
      // the page refused the model's framing before sending it (a file of junk is not copied here): the library
      // refuses a bad bundle first, so the bundle's checks run, then the model's refusal stands
      await openBundle(data.bundle, data.passphrase, (progress) => self.postMessage({ id, type: "progress", progress }));
      throw receivedError(data.modelRefusal);
    } else if (type === "reveal") {
      const result = await reveal({ model: data.model, bundle: data.bundle, passphrase: data.passphrase,
        onProgress: (progress) => self.postMessage({ id, type: "progress", progress }),
        openRenderer: (model, networks, needed) => {
          if (pool === null) throw new Error("the reveal's workers are not started");
          return pool.open(model, networks, needed);
        } });
      const transfer = [result.bytes.buffer, result.pixels?.buffer].filter(Boolean);
      self.postMessage({ id, type: "done", result }, [...new Set(transfer)]);
    }
  } catch (error) {
    const posted = postedError(error);
    if (!posted.refusal) posted.message = `unexpected error: ${posted.message}`;
    self.postMessage({ id, type: "error", ...posted });
  }
}

if (self.name === FIELD_WORKER) {
  const answer = fieldWorker();
  self.onmessage = ({ data: { port } }) => {
    port.onmessage = async (event) => {
      const [reply, transfer] = await answer(event.data);
      port.postMessage(reply, transfer);
    };
  };
} else {
  self.onmessage = (event) => handle(event.data);
}
