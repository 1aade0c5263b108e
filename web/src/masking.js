// Mirrors runtime/masking.py: a bundle's tensors read only with its model (bundle format 5). Every tensor's stored
// bytes are XORed with ChaCha20(key, nonce = SHA-256(tensor name)[:12], counter 0), key = HKDF-SHA256(the model's
// mask secret, the bundle's salt, MASK_INFO); the metadata states {"cipher": "chacha20", "kdf": "hkdf-sha256",
// "salt": base64}. The mask secret comes from the model's weights (src/model.js weightsDigests).

import { chacha20 } from "@noble/ciphers/chacha.js";
import { hkdf } from "@noble/hashes/hkdf.js";
import { sha256 } from "@noble/hashes/sha2.js";
import { UserError } from "./errors.js";
import { isJsonObject } from "./json.js";

export const CIPHER = "chacha20";
export const KDF = "hkdf-sha256";
export const SALT_BYTES = 16;
const MASK_INFO = new TextEncoder().encode("noisenerf bundle mask 1");

/** checked_mask: a bundle's mask object, refused unless it is exactly one mask_metadata writes. -> its salt. */
export function checkedMask(data) {
  let salt = null;
  if (isJsonObject(data) && Object.keys(data).sort().join() === "cipher,kdf,salt" && data.cipher === CIPHER &&
      data.kdf === KDF && typeof data.salt === "string" && data.salt.length < 64 &&
      /^[A-Za-z0-9+/]*={0,2}$/.test(data.salt) && data.salt.length % 4 === 0) {
    salt = Uint8Array.from(atob(data.salt), (c) => c.charCodeAt(0));
  }
  if (salt === null || salt.length !== SALT_BYTES) {
    throw new UserError(`bundle: the mask must be an object with cipher "${CIPHER}", kdf "${KDF}" and a salt of ` +
      `${SALT_BYTES} bytes in base64`, { code: "mask.malformed", cipher: CIPHER, kdf: KDF, salt_bytes: SALT_BYTES });
  }
  return salt;
}

/** mask_key: the bundle's key, HKDF-SHA256 of the model's mask secret under the bundle's salt. */
export const maskKey = (maskSecret, salt) => hkdf(sha256, maskSecret, salt, MASK_INFO, 32);

/** A tensor's stored bytes XORed with its keystream (masked, or unmasked: the same). */
export function xorMasked(bytes, key, name) {
  return chacha20(key, sha256(new TextEncoder().encode(name)).slice(0, 12), bytes);
}
