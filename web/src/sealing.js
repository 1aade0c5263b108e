// Mirrors runtime/sealing.py (and cli/reveal.py unseal): the seal's checks and caps (ScryptParams.from_dict,
// Seal.from_dict, decoded), scrypt -> the cipher key then the bundle key, the bundle's HMAC-SHA256 over its
// header's canonical JSON (without the tag) and its tensor data, checked before anything renders, and
// ChaCha20-Poly1305 with the associated data of the bundle's fixed fields. Every failure of a check that a wrong
// passphrase and an altered bundle or model share is the one refusal WRONG.

import { scryptAsync } from "@noble/hashes/scrypt.js";
import { hmac } from "@noble/hashes/hmac.js";
import { sha256 } from "@noble/hashes/sha2.js";
import { bytesToHex } from "@noble/hashes/utils.js";
import { chacha20poly1305 } from "@noble/ciphers/chacha.js";
import { UserError } from "./errors.js";
import { canonicalJson, isJsonObject as isObject, parseJson, pyEqual } from "./json.js";
import { checkedInt } from "./limits.js";

export const CIPHER = "chacha20-poly1305";
export const KDF = "scrypt";
export const SALT_BYTES = 16;
export const NONCE_BYTES = 12;
export const MAC_KEY = "noisenerf_seal_mac";
export const WRONG = "wrong passphrase, or the bundle or model was altered";
export const MAX_KDF_MEMORY = 2 ** 29;
export const MAX_KDF_WORK = 2 ** 24;
// runtime/api.py's refusal without a passphrase, without the CLI's ways of giving one (a page has a passphrase field)
export const NO_PASSPHRASE = "the bundle is sealed: give its passphrase";
export const EMPTY_PASSPHRASE = "the passphrase is empty";
export const NOT_SEALED = "a passphrase was given but the bundle is not sealed (a sealed bundle stripped of its seal reads so); "
  + "nothing revealed: reveal it without a passphrase only if it was sent unsealed";

/** ScryptParams.from_dict: parameters read from a bundle, refused beyond MAX_KDF_MEMORY or MAX_KDF_WORK. */
export function scryptParams(data) {
  if (!isObject(data) || data.name !== KDF) throw new UserError(`bundle: sealed payload needs a ${KDF} kdf object`, { code: "seal.bad_kdf", kdf: KDF });
  const log2n = checkedInt(data.log2_n ?? null, "bundle: kdf log2_n", 1, 30, { code: "seal.kdf_log2_n" });
  const r = checkedInt(data.r ?? null, "bundle: kdf r", 1, 64, { code: "seal.kdf_r" });
  const p = checkedInt(data.p ?? null, "bundle: kdf p", 1, 64, { code: "seal.kdf_p" });
  const memory = 128 * r * 2 ** log2n, work = 2 ** log2n * r * p;
  if (memory > MAX_KDF_MEMORY || work > MAX_KDF_WORK) {
    throw new UserError(`bundle: kdf asks for ${Math.floor(memory / 2 ** 20)} MiB and n·r·p = ${work}; at most ` +
      `${MAX_KDF_MEMORY / 2 ** 20} MiB and ${MAX_KDF_WORK} are allowed`, { code: "seal.kdf_too_costly",
      memory_mib: Math.floor(memory / 2 ** 20), work, max_memory_mib: MAX_KDF_MEMORY / 2 ** 20, max_work: MAX_KDF_WORK });
  }
  return { log2n, r, p };
}

const toBase64 = (bytes) => btoa(String.fromCharCode(...bytes));

/** decoded: base64 text (validated as Python's b64decode(validate=True)) of exactly `length` bytes. */
function decoded(text, what, length) {
  let value = null;
  if (typeof text === "string" && text.length < 64 && /^[A-Za-z0-9+/]*={0,2}$/.test(text) && text.length % 4 === 0) {
    value = Uint8Array.from(atob(text), (c) => c.charCodeAt(0));
  }
  if (value === null || value.length !== length) throw new UserError(`bundle: sealed payload ${what} must be ${length} bytes in base64`, { code: "seal.bad_base64", what, length });
  return value;
}

/** The seal's dict as Python's Seal.to_dict writes it. */
function sealDict(seal) {
  return { cipher: CIPHER, kdf: { name: KDF, log2_n: seal.kdf.log2n, r: seal.kdf.r, p: seal.kdf.p },
    salt: toBase64(seal.salt), nonce: toBase64(seal.nonce) };
}

/** Seal.from_dict: known cipher, capped KDF, salt and nonce of the right lengths, nothing else. */
export function sealFromDict(data) {
  if (!isObject(data) || data.cipher !== CIPHER) throw new UserError(`bundle: sealed payload needs cipher "${CIPHER}"`, { code: "seal.bad_cipher", cipher: CIPHER });
  const seal = { kdf: scryptParams(data.kdf), salt: decoded(data.salt, "salt", SALT_BYTES),
    nonce: decoded(data.nonce, "nonce", NONCE_BYTES) };
  if (!pyEqual(sealDict(seal), data)) throw new UserError("bundle: sealed payload object has unexpected fields", { code: "seal.unexpected_fields" });
  return seal;
}

/** A passphrase as bytes: a string's UTF-8, or the bytes given. null/undefined: none given. */
export function passphraseBytes(passphrase) {
  if (passphrase === null || passphrase === undefined) return null;
  if (passphrase instanceof Uint8Array) return passphrase;
  if (typeof passphrase === "string") return new TextEncoder().encode(passphrase);
  throw new TypeError("passphrase must be a string or a Uint8Array");
}

/** derive_keys: scrypt(passphrase, salt) -> 64 bytes, the cipher key then the bundle key. onProgress(0..1). */
export async function deriveKeys(passphrase, seal, onProgress = null) {
  if (!passphrase || passphrase.length === 0) throw new UserError(EMPTY_PASSPHRASE, { code: "seal.empty_passphrase" });
  const material = await scryptAsync(passphrase, seal.salt, { N: 2 ** seal.kdf.log2n, r: seal.kdf.r, p: seal.kdf.p,
    dkLen: 64, maxmem: MAX_KDF_MEMORY + 4096, ...(onProgress ? { onProgress } : {}) });
  return { cipher: material.slice(0, 32), bundle: material.slice(32) };
}

/** split_safetensors, the one reader of a safetensors header (the bundle's check 3 and the seal's tag both read it
 * here): the parsed header (Python's JSON: ints apart from floats) and the tensor data. */
export function splitSafetensors(data, source) {
  const size = data.length >= 8 ? Number(new DataView(data.buffer, data.byteOffset, 8).getBigUint64(0, true)) : -1;
  const refused = (why = null) => new UserError(`not a readable safetensors bundle: ${source}${why === null ? "" : ` (${why})`}`,
    { code: "bundle.not_safetensors" });
  if (!(size > 0 && size <= data.length - 8)) throw refused();
  let header;
  try {
    header = parseJson(data.subarray(8, 8 + size), "bundle header", source);
  } catch (error) {
    if (!(error instanceof UserError)) throw error;
    throw refused(error.message.split(": ")[0]);
  }
  if (!isObject(header) || (Object.hasOwn(header, "__metadata__") && !isObject(header.__metadata__))) throw refused();
  return { header, body: data.subarray(8 + size) };
}

/** bundle_tag: HMAC-SHA256 over the header's canonical JSON without the tag itself, then the tensor data. */
export function bundleTag(header, body, keys) {
  const metadata = Object.fromEntries(Object.entries(header.__metadata__ ?? {}).filter(([k]) => k !== MAC_KEY));
  const signed = canonicalJson({ ...header, __metadata__: metadata });
  const length = new Uint8Array(8);
  new DataView(length.buffer).setBigUint64(0, BigInt(signed.length), true);
  return bytesToHex(hmac.create(sha256, keys.bundle).update(length).update(signed).update(body).digest());
}

/** check_bundle_tag: refuse (WRONG) a bundle whose tag is missing or is not this key's over its present bytes. */
export function checkBundleTag(data, keys, source = "secret.bundle") {
  const { header, body } = splitSafetensors(data, source);
  const stored = (header.__metadata__ ?? {})[MAC_KEY];
  // Python's hmac.compare_digest; the tag is public, so a plain comparison leaks nothing a recipient lacks
  if (typeof stored !== "string" || !/^[\x00-\x7f]*$/.test(stored) || stored !== bundleTag(header, body, keys)) {
    throw new UserError(WRONG, { code: "seal.wrong_passphrase" });
  }
}

/** unseal_keys: the keys of a sealed bundle, once its tag shows it unchanged under this passphrase. */
export async function unsealKeys(data, seal, passphrase, onProgress = null) {
  const keys = await deriveKeys(passphrase, seal, onProgress);
  checkBundleTag(data, keys);
  return keys;
}

/** associated_data: what the bundle fixes before its noise is solved. */
export function associatedData(modelFingerprint, width, height, marker) {
  return canonicalJson({ model_fingerprint: modelFingerprint, secret: [width, height], payload: marker });
}

/** decrypt: the plaintext, or the one refusal a wrong passphrase and an altered bundle or model share. */
export function decrypt(ciphertext, keys, seal, associated) {
  try {
    return chacha20poly1305(keys.cipher, seal.nonce, associated).decrypt(ciphertext);
  } catch {
    throw new UserError(WRONG, { code: "seal.wrong_passphrase" });
  }
}
