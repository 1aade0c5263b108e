// The page's Web Worker: runs the reveal library (src/index.js) on onnxruntime-web so that the page stays
// responsive. Messages in: {id, type: "init", wasmBinary?, numThreads?} | {id, type: "inspect", bundle} |
// {id, type: "reveal", model, bundle, passphrase}. Out: {id, type: "progress", progress} | {id, type: "done",
// result} | {id, type: "error", message, userError}. A refusal is a UserError: its message is the CLI's line.

import * as ort from "onnxruntime-web";
import { reveal, inspectBundle, UserError } from "../index.js";

async function handle({ id, type, ...data }) {
  try {
    if (type === "init") {
      // the single-file build hands the WASM binary over (nothing is fetched from file://), one thread there
      if (data.wasmBinary) ort.env.wasm.wasmBinary = data.wasmBinary;
      if (data.numThreads) ort.env.wasm.numThreads = data.numThreads;
      self.postMessage({ id, type: "done", result: { crossOriginIsolated: self.crossOriginIsolated === true } });
    } else if (type === "inspect") {
      self.postMessage({ id, type: "done", result: await inspectBundle(data.bundle) });
    } else if (type === "reveal") {
      const result = await reveal({ model: data.model, bundle: data.bundle, passphrase: data.passphrase,
        onProgress: (progress) => self.postMessage({ id, type: "progress", progress }) });
      const transfer = [result.bytes.buffer, result.pixels?.buffer].filter(Boolean);
      self.postMessage({ id, type: "done", result }, [...new Set(transfer)]);
    }
  } catch (error) {
    const userError = error instanceof UserError;
    self.postMessage({ id, type: "error", userError,
      message: userError ? error.message : `unexpected error: ${String(error?.message ?? error)}` });
  }
}

// onnxruntime-web starts its own threads (where the page is cross-origin isolated) from this very script,
// named em-pthread: those are not ours to answer
if (!self.name?.startsWith("em-pthread")) self.onmessage = (event) => handle(event.data);
