// Mirrors runtime/payload.py: the bundle metadata's "payload" object, the payload marker (checked_marker, seal_of), the record the
// revealed pixels carry (header struct ">4sBBHQII32s": magic NNPL, version 1, kind, name length, body length,
// width, height, SHA-256 of the body; then the name, then the body), and open_payload (a sealed record is
// decrypted first). Any record that does not check is the one refusal INEXACT.

import { sha256 } from "@noble/hashes/sha2.js";
import { UserError } from "./errors.js";
import { checkedImageSize } from "./limits.js";
import { isJsonObject, pyEqual } from "./json.js";
import { sealFromDict, associatedData, decrypt } from "./sealing.js";

export const MAGIC = [0x4e, 0x4e, 0x50, 0x4c]; // b"NNPL"
export const RECORD_VERSION = 1;
export const RECORD_SIZE = 56;
export const KINDS = ["file", "image"];
export const MAX_NAME_BYTES = 255; // what a record's writer (runtime/payload.py Record.pack) allows
export const PAYLOAD_VERSION = 1;
export const INEXACT = "the revealed pixels do not reproduce the payload's SHA-256 (the bundle or model was altered, " +
  "or this machine renders differently); nothing written";

/** checked_marker: a bundle's payload marker, refused unless it is exactly one payload_marker writes. */
export function checkedMarker(data) {
  const keys = isJsonObject(data) ? Object.keys(data).sort() : [];
  if (!isJsonObject(data) || !pyEqual(data.version ?? null, PAYLOAD_VERSION) || keys.length !== 2 || keys[0] !== "sealed" || keys[1] !== "version") {
    throw new UserError(`bundle: payload must be an object with version ${PAYLOAD_VERSION} and sealed`,
      { code: "payload.malformed", version: PAYLOAD_VERSION });
  }
  sealOf(data);
  return data;
}

/** seal_of: the seal of a payload marker, null when it is not sealed. */
export function sealOf(marker) {
  return marker.sealed === null ? null : sealFromDict(marker.sealed);
}

const equalBytes = (a, b) => a.length === b.length && a.every((v, i) => v === b[i]);

/** unpack_record: the record at the start of `data` (padding after it ignored); INEXACT unless it checks. */
export function unpackRecord(data) {
  if (data.length < RECORD_SIZE) throw new UserError(INEXACT, { code: "payload.inexact" });
  const view = new DataView(data.buffer, data.byteOffset, data.byteLength);
  const version = data[4], kind = data[5], nameLength = view.getUint16(6), length = view.getBigUint64(8);
  const width = view.getUint32(16), height = view.getUint32(20), digest = data.subarray(24, 56);
  const end = BigInt(RECORD_SIZE + nameLength) + length;
  if (!equalBytes(data.subarray(0, 4), MAGIC) || version !== RECORD_VERSION || kind >= KINDS.length || end > BigInt(data.length)) {
    throw new UserError(INEXACT, { code: "payload.inexact" });
  }
  const body = data.slice(RECORD_SIZE + nameLength, Number(end));
  if (!equalBytes(sha256(body), digest) || (KINDS[kind] === "image" && width * height * 3 !== Number(length))) {
    throw new UserError(INEXACT, { code: "payload.inexact" });
  }
  if (nameLength > MAX_NAME_BYTES) {
    throw new UserError(`the payload's file name is ${nameLength} bytes; a record holds at most ${MAX_NAME_BYTES}`,
      { code: "payload.name_too_long", name_bytes: nameLength, most: MAX_NAME_BYTES });
  }
  if (KINDS[kind] === "image") checkedImageSize(width, height, "the payload's image", { code: "payload.image_size" });
  return { kind: KINDS[kind], body, name: data.slice(RECORD_SIZE, RECORD_SIZE + nameLength), width, height };
}

/** open_payload: the record in revealed pixels (height·width·3 uint8); a sealed one is decrypted with `keys` first. */
export function openPayload(pixels, width, height, marker, modelFingerprint, keys) {
  let data = pixels;
  const seal = sealOf(marker);
  if (seal !== null) data = decrypt(data, keys, seal, associatedData(modelFingerprint, width, height, marker));
  return unpackRecord(data);
}
