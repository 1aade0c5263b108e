"""Sealing: a payload encrypted under a passphrase before it is hidden, and the finished bundle authenticated.

One scrypt derivation (random salt, parameters recorded in the bundle) gives two 32-byte keys:

- the **cipher key** for ChaCha20-Poly1305, which encrypts the payload record *before* it becomes the
  secret's pixels, so the NeRF reveals ciphertext. Its associated data is what the bundle fixes before
  any noise is solved: the model fingerprint, the secret's size and this seal (`associated_data`).
- the **bundle key** for an HMAC-SHA256 over the finished bundle file: the canonical JSON of its whole
  safetensors header (every piece of metadata, the tensors' names, dtypes, shapes and offsets) and every
  byte of its tensor data. The noise and the metadata written after solving (the pixels' digest, the
  noise layout's own fields) cannot be associated data of an encryption that happens before solving;
  this tag covers them, whatever the noise layout, and it is checked before anything is rendered. It is
  stored under MAC_KEY in the safetensors metadata, beside (not inside) the bundle's own JSON.

So one changed byte in the bundle's noise or metadata fails the tag, changed model weights fail the
model's fingerprint check, and a model changed elsewhere (its cameras, say) reveals other pixels, which
fail the AEAD tag: each is the same refusal as a wrong passphrase, since none of them can be told apart.

Salt and nonce come from os.urandom, so sealed bundles differ on every run ("same seed, same bundle"
holds for unsealed ones only); `new_seal` takes fixed ones for deterministic tests.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import hmac
import json
import os
from dataclasses import dataclass
from pathlib import Path

from cryptography.exceptions import InvalidTag
from cryptography.hazmat.primitives.ciphers.aead import ChaCha20Poly1305
from cryptography.hazmat.primitives.kdf.scrypt import Scrypt

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import parse_json
from noisenerf.runtime.limits import checked_int

CIPHER = "chacha20-poly1305"
KDF = "scrypt"
SALT_BYTES = 16
NONCE_BYTES = 12
TAG_BYTES = 16  # Poly1305's: the ciphertext is this much longer than the plaintext
MAC_KEY = "noisenerf_seal_mac"
WRONG = "wrong passphrase, or the bundle or model was altered"
NOT_SEALED = ("a passphrase was given but the bundle is not sealed (a sealed bundle stripped of its seal reads so); "
              "nothing revealed: reveal it without a passphrase only if it was sent unsealed")

# Caps on the scrypt parameters a bundle may ask for, so a hostile bundle cannot demand huge memory or time:
# at most 512 MiB (128·r·n bytes, 4x the default's) and 8x the default's work (a few seconds).
MAX_KDF_MEMORY = 1 << 29
MAX_KDF_WORK = 1 << 24  # n·r·p


@dataclass(frozen=True)
class ScryptParams:
    """scrypt's cost: n = 2^log2_n, block size r, parallelism p. The default takes about 0.5 s and
    128 MiB on 2 cores (OpenSSL's scrypt runs its p lanes one after another)."""

    log2_n: int = 17
    r: int = 8
    p: int = 2

    @property
    def memory(self) -> int:
        """Bytes scrypt allocates: 128·r·n."""
        return 128 * self.r * (1 << self.log2_n)

    def to_dict(self) -> dict:
        return {"name": KDF, "log2_n": self.log2_n, "r": self.r, "p": self.p}

    @staticmethod
    def from_dict(data) -> "ScryptParams":
        """Parameters read from a bundle, refused beyond MAX_KDF_MEMORY or MAX_KDF_WORK."""
        if not isinstance(data, dict) or data.get("name") != KDF:
            raise UserError(f"bundle: sealed payload needs a {KDF} kdf object", code="seal.bad_kdf", kdf=KDF)
        params = ScryptParams(checked_int(data.get("log2_n"), "bundle: kdf log2_n", 1, 30, code="seal.kdf_log2_n"),
                              checked_int(data.get("r"), "bundle: kdf r", 1, 64, code="seal.kdf_r"),
                              checked_int(data.get("p"), "bundle: kdf p", 1, 64, code="seal.kdf_p"))
        if params.memory > MAX_KDF_MEMORY or (1 << params.log2_n) * params.r * params.p > MAX_KDF_WORK:
            raise UserError(f"bundle: kdf asks for {params.memory >> 20} MiB and n·r·p = "
                            f"{(1 << params.log2_n) * params.r * params.p}; at most {MAX_KDF_MEMORY >> 20} MiB "
                            f"and {MAX_KDF_WORK} are allowed", code="seal.kdf_too_costly",
                            memory_mib=params.memory >> 20, work=(1 << params.log2_n) * params.r * params.p,
                            max_memory_mib=MAX_KDF_MEMORY >> 20, max_work=MAX_KDF_WORK)
        return params


@dataclass(frozen=True)
class Seal:
    """What a recipient needs besides the passphrase: the KDF's parameters and salt, the cipher's nonce."""

    kdf: ScryptParams
    salt: bytes
    nonce: bytes

    def to_dict(self) -> dict:
        return {"cipher": CIPHER, "kdf": self.kdf.to_dict(), "salt": base64.b64encode(self.salt).decode("ascii"),
                "nonce": base64.b64encode(self.nonce).decode("ascii")}

    @staticmethod
    def from_dict(data) -> "Seal":
        """A seal read from a bundle: known cipher, capped KDF, salt and nonce of the right lengths."""
        if not isinstance(data, dict) or data.get("cipher") != CIPHER:
            raise UserError(f"bundle: sealed payload needs cipher {CIPHER!r}", code="seal.bad_cipher", cipher=CIPHER)
        seal = Seal(ScryptParams.from_dict(data.get("kdf")), decoded(data.get("salt"), "salt", SALT_BYTES),
                    decoded(data.get("nonce"), "nonce", NONCE_BYTES))
        if seal.to_dict() != data:
            raise UserError("bundle: sealed payload object has unexpected fields", code="seal.unexpected_fields")
        return seal


def decoded(text, what: str, length: int) -> bytes:
    """Base64 text of exactly `length` bytes."""
    try:
        value = base64.b64decode(text, validate=True) if isinstance(text, str) and len(text) < 64 else None
    except binascii.Error:
        value = None
    if value is None or len(value) != length:
        raise UserError(f"bundle: sealed payload {what} must be {length} bytes in base64", code="seal.bad_base64",
                        what=what, length=length)
    return value


def new_seal(kdf: ScryptParams = ScryptParams(), salt: bytes | None = None, nonce: bytes | None = None) -> Seal:
    """A fresh seal: salt and nonce from os.urandom unless given (fixed ones are for deterministic tests)."""
    return Seal(kdf, os.urandom(SALT_BYTES) if salt is None else salt, os.urandom(NONCE_BYTES) if nonce is None else nonce)


@dataclass(frozen=True)
class Keys:
    cipher: bytes  # ChaCha20-Poly1305 key of the payload
    bundle: bytes  # HMAC-SHA256 key of the bundle file


def derive_keys(passphrase: bytes, seal: Seal) -> Keys:
    """scrypt(passphrase, salt) -> 64 bytes: the cipher key, then the bundle key."""
    if not passphrase:
        raise UserError("the passphrase is empty", code="seal.empty_passphrase")
    kdf = seal.kdf
    material = Scrypt(salt=seal.salt, length=64, n=1 << kdf.log2_n, r=kdf.r, p=kdf.p).derive(passphrase)
    return Keys(material[:32], material[32:])


def canonical_json(data) -> bytes:
    """The one byte string a JSON value is authenticated as: sorted keys, no spaces, ASCII."""
    return json.dumps(data, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False).encode()


def associated_data(model_fingerprint: str, width: int, height: int, marker: dict) -> bytes:
    """The AEAD's associated data: what the bundle fixes before its noise is solved. marker: the bundle
    metadata's payload marker (runtime.payload; this seal included)."""
    return canonical_json({"model_fingerprint": model_fingerprint, "secret": [width, height], "payload": marker})


def encrypt(plaintext: bytes, keys: Keys, seal: Seal, associated: bytes) -> bytes:
    """ChaCha20-Poly1305: the ciphertext is TAG_BYTES longer than the plaintext."""
    return ChaCha20Poly1305(keys.cipher).encrypt(seal.nonce, plaintext, associated)


def decrypt(ciphertext: bytes, keys: Keys, seal: Seal, associated: bytes) -> bytes:
    """The plaintext, or the one refusal a wrong passphrase and an altered bundle or model share."""
    try:
        return ChaCha20Poly1305(keys.cipher).decrypt(seal.nonce, ciphertext, associated)
    except InvalidTag:
        raise UserError(WRONG, code="seal.wrong_passphrase") from None


def split_safetensors(data: bytes, source: str | Path) -> tuple[dict, bytes]:
    """A safetensors file's parsed header and its tensor data (everything after the header)."""
    size = int.from_bytes(data[:8], "little") if len(data) >= 8 else -1
    if not 0 < size <= len(data) - 8:
        raise UserError(f"not a readable safetensors bundle: {source}", code="bundle.not_safetensors")
    try:
        header = parse_json(data[8:8 + size], "bundle header", source)
    except UserError as error:
        raise UserError(f"not a readable safetensors bundle: {source} ({str(error).split(': ', 1)[0]})",
                        code="bundle.not_safetensors") from None
    if not isinstance(header, dict) or not isinstance(header.get("__metadata__", {}), dict):
        raise UserError(f"not a readable safetensors bundle: {source}", code="bundle.not_safetensors")
    return header, data[8 + size:]


def bundle_tag(header: dict, body: bytes, keys: Keys) -> str:
    """HMAC-SHA256 over the header's canonical JSON without the tag itself, then the tensor data."""
    metadata = {k: v for k, v in header.get("__metadata__", {}).items() if k != MAC_KEY}
    signed = canonical_json({**header, "__metadata__": metadata})
    mac = hmac.new(keys.bundle, len(signed).to_bytes(8, "little") + signed, hashlib.sha256)
    mac.update(body)
    return mac.hexdigest()


def tagged(data: bytes, keys: Keys) -> bytes:
    """A bundle's bytes with its tag in the safetensors metadata (the tensor data unchanged), before they are
    written: a sealed bundle is written once, whole."""
    header, body = split_safetensors(data, "the bundle")
    header["__metadata__"] = {**header.get("__metadata__", {}), MAC_KEY: bundle_tag(header, body, keys)}
    text = json.dumps(header, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 8)  # safetensors keeps the data 8-byte aligned
    return len(text).to_bytes(8, "little") + text + body


def check_bundle_tag(data: bytes, keys: Keys) -> None:
    """Refuse (WRONG) a bundle (its bytes) whose tag is missing or is not this key's over those bytes."""
    header, body = split_safetensors(data, "the bundle")
    stored = header.get("__metadata__", {}).get(MAC_KEY)
    if not isinstance(stored, str) or not stored.isascii() or not hmac.compare_digest(stored, bundle_tag(header, body, keys)):
        raise UserError(WRONG, code="seal.wrong_passphrase")


def unseal_keys(data: bytes, seal: Seal, passphrase: bytes) -> Keys:
    """The keys of the sealed bundle of these bytes, once its tag shows it unchanged under this passphrase."""
    keys = derive_keys(passphrase, seal)
    check_bundle_tag(data, keys)
    return keys
