// The reveal page: pick or drop model.onnx and the bundle, a passphrase field when the bundle is sealed, a progress
// bar, the revealed image shown and downloadable as the library's PNG (never a canvas export), or the payload
// saved under the name the user chooses. The reveal runs in a Web Worker (worker.js). Every refusal is one
// message in the page and nothing is downloaded. `window.noisenerf = {reveal, inspect}` is the library's API
// through the worker: `await noisenerf.reveal({model, bundle, passphrase})` returns the library's object.
//
// The two builds (build.mjs) differ in where the worker and onnxruntime's WASM come from: the static site loads
// worker.js (a module worker) and the .wasm beside index.html; the single file carries both inline (the worker as
// a classic worker from a Blob URL, the WASM handed over as bytes). Both render in a pool of workers, one per core
// (src/pool.js), which needs no cross-origin isolation: a page opened from disk is never isolated.

import { workerCode, wasmBase64 } from "noisenerf-embedded";
import { FIELD_WORKER, REVEAL_WORKER } from "./roles.js";
import { UserError, postedError, receivedError } from "../errors.js";
import { framing } from "../onnx.js";

const MOST_WORKERS = 16; // beyond the cores there are, more workers only hold more memory
let worker = null, ready = null, nextId = 0, workerUrl = null;
let fieldWorkers = [], fieldFailed = false;
let revealing = Promise.resolve(); // one reveal at a time: they share the pool's sessions
const pending = new Map();

/** The worker's script, started under a name (its role): a Blob URL's in the single file, worker.js's in the site. */
function spawn(name) {
  if (!workerCode) return new Worker(new URL("./worker.js", import.meta.url), { type: "module", name });
  workerUrl ??= URL.createObjectURL(new Blob([workerCode], { type: "text/javascript" }));
  return new Worker(workerUrl, { name });
}

function startWorker() {
  if (ready) return ready;
  worker = spawn(REVEAL_WORKER);
  worker.onmessage = ({ data }) => {
    const call = pending.get(data.id);
    if (!call) return;
    if (data.type === "progress") call.onProgress?.(data.progress);
    else {
      pending.delete(data.id);
      if (data.type === "done") call.resolve(data.result);
      else {
        call.reject(receivedError(data));
      }
    }
  };
  // it failed (to start, or out of memory): what it held fails, and the next reveal starts it and its pool afresh
  worker.onerror = (event) => {
    const error = new Error(`the reveal worker failed: ${event.message ?? "unknown error"}`);
    for (const call of pending.values()) call.reject(error);
    pending.clear();
    worker.terminate();
    for (const field of fieldWorkers) field.terminate();
    fieldWorkers = [];
    ready = null;
  };
  const init = wasmBase64 ? { wasmBinary: decodeBase64(wasmBase64) } : {};
  ready = call("init", init, null, init.wasmBinary ? [init.wasmBinary.buffer] : []);
  return ready;
}

/** The reveal worker's pool of field workers, `size` of them, each joined to it by a MessageChannel. The page
 * starts them: a worker of a page opened from disk may not start workers of its own (its origin is opaque). */
async function usePool(size) {
  if (fieldWorkers.length === size && !fieldFailed) return;
  for (const field of fieldWorkers) field.terminate();
  fieldWorkers = [];
  fieldFailed = false;
  const started = Array.from({ length: size }, () => spawn(FIELD_WORKER));
  const ports = started.map((field, index) => {
    const channel = new MessageChannel();
    field.postMessage({ port: channel.port1 }, [channel.port1]);
    // a field worker that dies (out of memory) fails the chunks it holds rather than leaving the reveal waiting,
    // and the pool is started afresh for the next reveal
    field.onerror = (event) => {
      fieldFailed = true;
      worker.postMessage({ type: "fieldFailed", index, message: event.message ?? "unknown error" });
    };
    return channel.port2;
  });
  try {
    await call("pool", { ports }, null, ports);
  } catch (error) {
    for (const field of started) field.terminate();
    throw error;
  }
  fieldWorkers = started;
}

function decodeBase64(text) {
  const binary = atob(text);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes;
}

function call(type, data, onProgress = null, transfer = []) {
  return new Promise((resolve, reject) => {
    const id = nextId++;
    pending.set(id, { resolve, reject, onProgress });
    worker.postMessage({ id, type, ...data }, transfer);
  });
}

/** What the worker is sent of the model: the model, or, where its framing (check 1, a few bytes of a file of junk)
 * refuses it, that refusal instead of a copy of the file (a file of 1 GiB cannot be cloned to a worker). */
function modelOrRefusal(model) {
  try {
    framing(model, "model.onnx");
    return { model };
  } catch (error) {
    if (!(error instanceof UserError)) throw error;
    return { model: null, modelRefusal: postedError(error) };
  }
}

/** The library's reveal, run in the worker: same arguments (Uint8Arrays), same result (and `workers`, how many
 * rendered), same refusals. workers: the pool's size, by default one per core. */
export async function reveal({ model, bundle, passphrase = null, onProgress = null,
  workers = Math.min(navigator.hardwareConcurrency || 1, MOST_WORKERS) }) {
  if (!(model instanceof Uint8Array) || !(bundle instanceof Uint8Array)) throw new TypeError("model and bundle must be Uint8Arrays");
  if (!(Number.isInteger(workers) && workers >= 1 && workers <= MOST_WORKERS)) {
    throw new TypeError(`workers must be an integer from 1 to ${MOST_WORKERS}`);
  }
  const turn = revealing.then(async () => {
    await startWorker();
    await usePool(workers);
    return { ...(await call("reveal", { ...modelOrRefusal(model), bundle, passphrase }, onProgress)), workers };
  });
  revealing = turn.catch(() => {});
  return turn;
}

/** Whether a bundle is a payload and sealed (inspectBundle), run in the worker. */
export async function inspect(bundle) {
  await startWorker();
  return call("inspect", { bundle });
}

window.noisenerf = { reveal, inspect };

// ---- the page ----

const $ = (id) => document.getElementById(id);
const files = { model: null, bundle: null };
let sealed = false, shown = null, last = null; // last: the shown result, for its save buttons
let busy = false, picked = 0; // busy: a reveal runs (the files cannot change); picked: bundles chosen so far

function message(text, kind = "error") {
  $("message").textContent = text;
  $("message").className = kind;
}

function clearResult() {
  if (shown) URL.revokeObjectURL(shown);
  shown = null;
  last = null;
  $("result").hidden = true;
  $("image-result").hidden = true;
  $("file-result").hidden = true;
}

async function readFile(file) {
  return new Uint8Array(await file.arrayBuffer());
}

/** Reveal is pressable when both files are chosen, the bundle inspected, and no reveal runs. */
function updateControls(inspecting = false) {
  $("model").disabled = $("bundle").disabled = busy;
  $("reveal").disabled = busy || inspecting || !(files.model && files.bundle);
}

async function setFile(kind, file) {
  if (busy) return;
  files[kind] = file;
  $(`${kind}-name`).textContent = file ? file.name : "none";
  clearResult();
  message("", "");
  if (kind !== "bundle") return updateControls();
  const pick = ++picked;
  sealed = false;
  $("passphrase-row").hidden = true;
  if (!file) return updateControls();
  updateControls(true);
  let info = null, refusal = null;
  try {
    info = await inspect(await readFile(file));
  } catch (error) {
    refusal = error;
  }
  if (pick !== picked) return; // another bundle was chosen meanwhile: this answer is not about it
  if (refusal) {
    files.bundle = null;
    $("bundle-name").textContent = "none";
    message(refusal.message);
  } else {
    sealed = info.sealed;
    $("passphrase-row").hidden = !sealed;
  }
  updateControls();
}

function download(bytes, name, type) {
  const url = URL.createObjectURL(new Blob([bytes], { type }));
  const link = document.createElement("a");
  link.href = url;
  link.download = name;
  document.body.append(link);
  link.click();
  link.remove();
  setTimeout(() => URL.revokeObjectURL(url), 60_000);
}

async function onReveal() {
  if (busy) return;
  clearResult();
  if (!files.model || !files.bundle) return message("pick model.onnx and the bundle first");
  const passphrase = sealed ? $("passphrase").value || null : null; // none given: the library's refusal
  busy = true;
  updateControls();
  $("progress").value = 0;
  $("progress").hidden = false;
  message("revealing…", "info");
  try {
    const started = performance.now();
    const result = await reveal({ model: await readFile(files.model), bundle: await readFile(files.bundle), passphrase,
      onProgress: ({ stage, done, total }) => {
        $("progress").value = stage === "kdf" ? 0.05 * done : 0.05 + 0.95 * (done / total);
        message(stage === "kdf" ? "checking the passphrase…" : `revealing… ${done} of ${total} rays`, "info");
      } });
    const seconds = ((performance.now() - started) / 1000).toFixed(2);
    $("progress").value = 1;
    $("result").hidden = false;
    if (result.kind === "image") {
      shown = URL.createObjectURL(new Blob([result.bytes], { type: "image/png" }));
      $("image").src = shown;
      $("image-result").hidden = false;
      last = result;
      message(`exact: ${result.exact} · ${result.width}x${result.height} · sha256 ${result.sha256} · ${seconds} s`,
        result.exact ? "ok" : "warn");
    } else {
      $("save-name").value = result.name ?? "payload.bin";
      $("file-result").hidden = false;
      last = result;
      message(`payload: file${result.name ? ` '${result.name}'` : ""}, ${result.bytes.length} bytes, sha256 ` +
        `${result.sha256}${result.sealed ? ", sealed" : ""} · ${seconds} s`, "ok");
    }
  } catch (error) {
    message(error.message);
  } finally {
    $("progress").hidden = true;
    busy = false;
    updateControls();
  }
}

function onDrop(event) {
  event.preventDefault();
  $("drop").classList.remove("over");
  if (busy) return message("a reveal is running: drop the files when it ends", "warn");
  for (const file of event.dataTransfer.files) setFile(file.name.toLowerCase().endsWith(".onnx") ? "model" : "bundle", file);
}

document.addEventListener("DOMContentLoaded", () => {
  $("model").addEventListener("change", (e) => setFile("model", e.target.files[0] ?? null));
  $("bundle").addEventListener("change", (e) => setFile("bundle", e.target.files[0] ?? null));
  $("reveal").addEventListener("click", onReveal);
  $("passphrase-row").addEventListener("submit", (e) => { e.preventDefault(); if (!$("reveal").disabled) onReveal(); }); // Enter
  $("save-image").addEventListener("click", () => last && download(last.bytes, last.name, "image/png"));
  $("save").addEventListener("click", () => {
    const name = $("save-name").value.trim();
    if (!name) return message("give the file a name");
    if (last) download(last.bytes, name, "application/octet-stream");
  });
  const drop = $("drop");
  drop.addEventListener("dragover", (e) => { e.preventDefault(); drop.classList.add("over"); });
  drop.addEventListener("dragleave", () => drop.classList.remove("over"));
  drop.addEventListener("drop", onDrop);
  startWorker().catch((error) => message(error.message));
});
