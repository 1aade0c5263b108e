// The stable API: `await reveal({model, bundle, passphrase})`, the browser's `noisenerf-reveal` (cli/reveal.py run):
// the bundle is read and checked first, a sealed one's tag checked under the passphrase, then the model (graph and
// fingerprint) on the whole file, then the bundle against the model and every tile's network, then every tile
// renders (onnxruntime-web given only the checked graph pruned to those networks' outputs); a payload is opened
// from the revealed pixels (cli/reveal.py write_payload). Every refusal is a UserError with the stable code and
// params runtime/ raises for the same input (src/errors.js) and a one-line message.

import { sha256 as sha256Of } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { UserError } from "./errors.js";
import { loadBundle } from "./bundle.js";
import { checkModel, checkBundle } from "./model.js";
import { LocalRenderer, bundleNetworks, revealBundle } from "./reveal.js";
import { encodePng } from "./png.js";
import { INEXACT, openPayload, sealOf } from "./payload.js";
import { NO_PASSPHRASE, NOT_SEALED, passphraseBytes, unsealKeys } from "./sealing.js";

export { UserError } from "./errors.js";

/** Whether a bundle's bytes are a sealed payload (the page asks for a passphrase then); throws as reveal would. */
export async function inspectBundle(bundle) {
  const loaded = await loadBundle(bundle, "loaded.bundle");
  return { payload: loaded.payloadMarker !== null, sealed: loaded.payloadMarker !== null && loaded.payloadMarker.sealed !== null,
    width: loaded.width, height: loaded.height, tiles: loaded.tiles.length };
}

/** The reveal's first steps, on the bundle alone: read and checked, a sealed one's tag checked under the passphrase
 * (a passphrase for an unsealed one refused). -> {loaded: the loaded bundle, keys: a sealed one's, else null}. */
export async function openBundle(bundle, passphrase = null, onProgress = null) {
  const loaded = await loadBundle(bundle, "loaded.bundle");
  const seal = loaded.payloadMarker === null ? null : sealOf(loaded.payloadMarker);
  const phrase = passphraseBytes(passphrase);
  if (seal === null && phrase !== null) throw new UserError(NOT_SEALED, { code: "seal.not_sealed" });
  if (seal === null) return { loaded, keys: null };
  if (phrase === null) throw new UserError(NO_PASSPHRASE, { code: "seal.no_passphrase" });
  return { loaded, keys: await unsealKeys(bundle, seal, phrase, onProgress && ((done) => onProgress({ stage: "kdf", done, total: 1 }))) };
}

/**
 * model, bundle: Uint8Array; passphrase: string or Uint8Array (sealed bundles only: given for an unsealed one, it is
 *   refused, as a sealed bundle stripped of its seal would be revealed as its ciphertext).
 * onProgress({stage: "kdf" | "render", done, total}), optional.
 * openRenderer(model, networks, needed) -> a renderer of chunks (src/reveal.js's LocalRenderer, this thread, by
 *   default; src/pool.js's FieldPool renders them in Web Workers), released when the reveal ends: `model` the checked
 *   model's bytes, `networks` its networks, `needed` those the bundle's tiles render through (a session each, of
 *   the graph pruned to that network's outputs).
 * -> {kind: "image", bytes (PNG), name, width, height, exact, sha256, pixels}
 *  | {kind: "file", bytes, name (the payload's own, or null), width, height (the secret's), exact: true, sha256 (of
 *     the bytes), sealed}; a sealed image payload comes back as kind "image" with its PNG.
 */
export async function reveal({ model, bundle, passphrase = null, onProgress = null, openRenderer = LocalRenderer.open }) {
  if (!(model instanceof Uint8Array) || !(bundle instanceof Uint8Array)) throw new TypeError("model and bundle must be Uint8Arrays");
  const { loaded, keys } = await openBundle(bundle, passphrase, onProgress);
  const checked = checkModel(model, "model.onnx");
  checkBundle(checked, loaded);
  const total = loaded.tiles.reduce((n, tile) => n + tile.rect[2] * tile.rect[3], 0);
  let done = 0;
  const progress = onProgress && ((rays) => onProgress({ stage: "render", done: (done += rays), total }));
  const renderer = await openRenderer(model, checked.networks, bundleNetworks(loaded, checked.networks));
  let revealed;
  try {
    revealed = await revealBundle(loaded, checked.metadata.renderConfig, renderer, checked.networks, progress);
  } finally {
    await renderer.release();
  }
  const { width, height } = loaded;
  if (loaded.payloadMarker === null) {
    return { kind: "image", bytes: encodePng(revealed.pixels, width, height), name: "revealed.png", width, height,
      exact: revealed.exact, sha256: revealed.sha256, pixels: revealed.pixels };
  }
  if (!revealed.exact) throw new UserError(INEXACT, { code: "payload.inexact" });
  const record = openPayload(revealed.pixels, width, height, loaded.payloadMarker, checked.metadata.fingerprint, keys);
  const name = record.name.length ? new TextDecoder("utf-8").decode(record.name) : null;
  const sha256 = bytesToHex(sha256Of(record.body));
  if (record.kind === "image") {
    return { kind: "image", bytes: encodePng(record.body, record.width, record.height), name: name ?? "revealed.png",
      width: record.width, height: record.height, exact: true, sha256, pixels: record.body, sealed: keys !== null };
  }
  return { kind: "file", bytes: record.body, name, width, height, exact: true, sha256, sealed: keys !== null };
}
