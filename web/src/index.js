// The stable API: `await reveal({model, bundle, passphrase})`, the browser's `noisenerf-reveal` (cli/reveal.py run):
// the bundle is read and checked first (a masked one up to its mask), a sealed one's tag checked under the
// passphrase, then the model (graph and fingerprint) on the whole file, then the bundle against the model (a masked
// one unmasked with it and checked) and every tile's network, then every tile
// renders (onnxruntime-web given only the checked graph pruned to those networks' outputs); a payload is opened
// from the revealed pixels (cli/reveal.py write_payload). Every refusal is a UserError with the stable code and
// params runtime/ raises for the same input (src/errors.js) and a one-line message.

import { sha256 as sha256Of } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { UserError } from "./errors.js";
import { bundleOf, fileFingerprint, filePayloadMarker, readBundleFile } from "./bundle.js";
import { checkBundle, checkFingerprint, checkModel } from "./model.js";
import { LocalRenderer, bundleNetworks, revealBundle } from "./reveal.js";
import { encodePng } from "./png.js";
import { INEXACT, openPayload, sealOf } from "./payload.js";
import { NO_PASSPHRASE, NOT_SEALED, passphraseBytes, unsealKeys } from "./sealing.js";

export { UserError } from "./errors.js";

/** Whether a bundle's bytes are a payload and sealed (the page asks for a passphrase then); throws as reveal would
 * before its model is open. */
export async function inspectBundle(bundle) {
  const marker = filePayloadMarker((await readBundle(bundle)).file);
  return { payload: marker !== null, sealed: marker !== null && marker.sealed !== null };
}

/** read_bundle: a bundle's bytes read and checked, all of it unless it is masked (runtime/api.py ReadBundle) ->
 * {file, checked: the checked bundle, or null for a masked one until its model is open (`opened`)}. */
async function readBundle(bytes) {
  const file = readBundleFile(bytes, "secret.bundle");
  return { file, checked: file.salt === null ? await bundleOf(file) : null };
}

/** ReadBundle.opened: the bundle's contents checked against the model; a masked bundle's unmasked with it, once the
 * model is the one it names (another's would unmask to junk). */
async function opened(read, model) {
  if (read.checked === null) checkFingerprint(model, fileFingerprint(read.file));
  const bundle = read.checked ?? await bundleOf(read.file, model.maskSecret);
  checkBundle(model, bundle);
  return bundle;
}

/** The reveal's first steps, on the bundle alone: read and checked (a masked one up to its mask), a sealed one's tag
 * checked under the passphrase (a passphrase for an unsealed one refused). -> {read (readBundle's), keys: a sealed
 * one's, else null}. */
export async function openBundle(bundle, passphrase = null, onProgress = null) {
  const read = await readBundle(bundle);
  const marker = filePayloadMarker(read.file);
  const seal = marker === null ? null : sealOf(marker);
  const phrase = passphraseBytes(passphrase);
  if (seal === null && phrase !== null) throw new UserError(NOT_SEALED, { code: "seal.not_sealed" });
  if (seal === null) return { read, keys: null };
  if (phrase === null) throw new UserError(NO_PASSPHRASE, { code: "seal.no_passphrase" });
  return { read, keys: await unsealKeys(bundle, seal, phrase, onProgress && ((done) => onProgress({ stage: "kdf", done, total: 1 }))) };
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
  const { read, keys } = await openBundle(bundle, passphrase, onProgress);
  const checked = checkModel(model, "model.onnx");
  const loaded = await opened(read, checked);
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
