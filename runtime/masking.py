"""The mask: a bundle's tensors read only with its model (bundle format 5).

Without it a bundle is a picture of its secret: each pixel's noise is solved for that pixel's colour, so the
compact layout's coefficient planes, decompressed and drawn, show the photo. From format 5 every tensor's
bytes, as stored (a compact tile's xz stream after compression, so keys do not grow), are XORed with a
ChaCha20 keystream:

    key    = HKDF-SHA256(ikm = the model's mask secret, salt = the bundle's 16-byte salt, info = MASK_INFO), 32 bytes
    stream = ChaCha20(key, nonce = the first 12 bytes of SHA-256(tensor name), block counter 0)

The mask secret is a digest of the model's weights that the fingerprint, stated in clear in the model and the
bundle, does not give (runtime.fingerprint.weights_digests). The metadata states the mask as
{"cipher": "chacha20", "kdf": "hkdf-sha256", "salt": base64}. XOR is its own inverse: `xor_masked` masks and
unmasks. This protects a bundle seen without its model; the model is meant to be public, and whoever holds both
holds the secret (sealing, runtime.sealing, layers a passphrase on top). web/src/masking.js mirrors this module.
"""

from __future__ import annotations

import base64
import binascii
import hashlib

import numpy as np
from cryptography.hazmat.primitives import hashes
from cryptography.hazmat.primitives.ciphers import Cipher, algorithms
from cryptography.hazmat.primitives.kdf.hkdf import HKDF

from noisenerf.runtime.errors import UserError

CIPHER, KDF = "chacha20", "hkdf-sha256"
SALT_BYTES = 16
MASK_INFO = b"noisenerf bundle mask 1"


def mask_metadata(salt: bytes) -> dict:
    """The bundle metadata's mask object."""
    return {"cipher": CIPHER, "kdf": KDF, "salt": base64.b64encode(salt).decode("ascii")}


def checked_mask(data) -> bytes:
    """A bundle's mask object, refused unless it is exactly one mask_metadata writes. -> its salt."""
    salt = None
    if isinstance(data, dict) and set(data) == {"cipher", "kdf", "salt"} and data["cipher"] == CIPHER \
            and data["kdf"] == KDF and isinstance(data["salt"], str) and len(data["salt"]) < 64:
        try:
            salt = base64.b64decode(data["salt"], validate=True)
        except binascii.Error:
            salt = None
    if salt is None or len(salt) != SALT_BYTES:
        raise UserError(f"bundle: the mask must be an object with cipher {CIPHER!r}, kdf {KDF!r} and a salt of "
                        f"{SALT_BYTES} bytes in base64", code="mask.malformed", cipher=CIPHER, kdf=KDF,
                        salt_bytes=SALT_BYTES)
    return salt


def mask_salt(identity: str) -> bytes:
    """A hide's salt, from what the hide is (train.hide.plan.run_key): the same seed and inputs give the same
    bundle, and two different hides in one model never share a keystream."""
    return hashlib.sha256(b"noisenerf mask salt\0" + identity.encode()).digest()[:SALT_BYTES]


def mask_key(mask_secret: bytes, salt: bytes) -> bytes:
    """The bundle's key: HKDF-SHA256 of the model's mask secret under the bundle's salt."""
    return HKDF(algorithm=hashes.SHA256(), length=32, salt=salt, info=MASK_INFO).derive(mask_secret)


def keystream(key: bytes, name: str, length: int) -> np.ndarray:
    """`length` bytes of tensor `name`'s keystream, uint8."""
    nonce = hashlib.sha256(name.encode()).digest()[:12]
    encryptor = Cipher(algorithms.ChaCha20(key, bytes(4) + nonce), mode=None).encryptor()  # counter 0, then nonce
    return np.frombuffer(encryptor.update(bytes(length)), np.uint8)


def xor_masked(tensors: dict[str, np.ndarray], key: bytes) -> dict[str, np.ndarray]:
    """Each tensor with its bytes XORed with its keystream (masked, or unmasked: the same), dtype and shape kept."""
    result = {}
    for name, array in tensors.items():
        stored = np.ascontiguousarray(array)
        flipped = np.frombuffer(stored.tobytes(), np.uint8) ^ keystream(key, name, stored.nbytes)
        result[name] = flipped.view(stored.dtype).reshape(stored.shape)
    return result
