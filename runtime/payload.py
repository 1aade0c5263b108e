"""Payloads: any file's bytes (or a sealed image) as an ordinary 8-bit RGB secret, and back.

A payload travels as a *record*:

    header  struct RECORD (56 bytes, big-endian): magic b"NNPL", record version 1, kind (0 file, 1 image),
            name length (UTF-8 bytes, at most 255; 0 for none), body length, image width and height (0 for
            a file), SHA-256 of the body
    name    the original file name, if any (never used as a path on reveal)
    body    the file's bytes, or an image's (height, width, 3) uint8 pixels row-major

The record's bytes fill the secret's pixels row-major, three per pixel (R, G, B), zero-padded to the end;
that secret is hidden like any image (tiles, any method), and the revealed pixels give the bytes back.
An unsealed record fills a near-square secret. A sealed one (runtime.sealing) is zero-padded to fill a
size bucket and encrypted, so the secret's size says only which bucket the payload fell in: a square of
16, 32, 64, ... px up to one tile, then whole tiles (see `sealed_shape`). The name travels inside.

The bundle's metadata marks a payload with one optional object, the payload marker, validated by `checked_marker`:

    "payload": {"version": 1, "sealed": null | {"cipher", "kdf", "salt", "nonce"}}

Bundles without it are ordinary image secrets.
"""

from __future__ import annotations

import hashlib
import math
import os
import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_PAYLOAD_PIXELS, checked_image_size
from noisenerf.runtime.sealing import TAG_BYTES, Keys, Seal, associated_data, decrypt, encrypt

MAGIC = b"NNPL"
RECORD_VERSION = 1
RECORD = struct.Struct(">4sBBHQII32s")
KINDS = ("file", "image")
MAX_NAME_BYTES = 255
PAYLOAD_VERSION = 1
MIN_BUCKET = 16  # px: the smallest sealed secret's side
MAX_PAYLOAD_BYTES = MAX_PAYLOAD_PIXELS * 3 - RECORD.size - MAX_NAME_BYTES - TAG_BYTES
INEXACT = ("the revealed pixels do not reproduce the payload's SHA-256 (the bundle or model was altered, "
           "or this machine renders differently); nothing written")


@dataclass(frozen=True)
class Record:
    """A payload: a file's bytes (with its name) or an image's pixels."""

    kind: str  # file | image
    body: bytes
    name: bytes = b""  # the original file name (UTF-8 as the file system gave it), b"" for none
    width: int = 0  # image kind only
    height: int = 0

    @property
    def sha256(self) -> str:
        return hashlib.sha256(self.body).hexdigest()

    def pack(self) -> bytes:
        """header | name | body."""
        if len(self.name) > MAX_NAME_BYTES:
            raise UserError(f"the payload's file name is longer than {MAX_NAME_BYTES} bytes",
                            code="payload.name_too_long", name_bytes=len(self.name), most=MAX_NAME_BYTES)
        header = RECORD.pack(MAGIC, RECORD_VERSION, KINDS.index(self.kind), len(self.name), len(self.body),
                             self.width, self.height, hashlib.sha256(self.body).digest())
        return header + self.name + self.body

    def pixels(self) -> np.ndarray:
        """An image record's pixels, (height, width, 3) uint8."""
        return np.frombuffer(self.body, np.uint8).reshape(self.height, self.width, 3)

    def report(self) -> dict:
        """What --json says about it: kind, size, digest, name (and an image's size)."""
        return {"kind": self.kind, "bytes": len(self.body), "sha256": self.sha256,
                "name": self.name.decode("utf-8", "replace") or None,
                **({"width": self.width, "height": self.height} if self.kind == "image" else {})}


def image_record(pixels: np.ndarray) -> Record:
    """A secret image (h, w, 3) uint8 as a record, for sealing."""
    return Record("image", np.ascontiguousarray(pixels, np.uint8).tobytes(), width=pixels.shape[1],
                  height=pixels.shape[0])


def read_payload_file(path: str | os.PathLike) -> Record:
    """A file as a record carrying its name; its size is checked before it is read."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"payload file not found: {path}", code="payload.file_not_found")
    size = path.stat().st_size
    if size > MAX_PAYLOAD_BYTES:
        raise UserError(f"payload file is {size} bytes; at most {MAX_PAYLOAD_BYTES} fit in one secret",
                        code="payload.file_too_large", size=size, most=MAX_PAYLOAD_BYTES)
    try:
        body = path.read_bytes()
    except OSError as error:
        raise UserError(f"cannot read payload file {path}: {error.strerror or error}",
                        code="payload.file_unreadable") from None
    return Record("file", body, name=os.fsencode(path.name)[:MAX_NAME_BYTES])


def unpack_record(data: bytes) -> Record:
    """The record at the start of `data` (padding after it is ignored); INEXACT unless its header is sound
    and its body hashes to the header's SHA-256."""
    if len(data) < RECORD.size:
        raise UserError(INEXACT, code="payload.inexact")
    magic, version, kind, name_length, length, width, height, digest = RECORD.unpack_from(data)
    end = RECORD.size + name_length + length
    if magic != MAGIC or version != RECORD_VERSION or kind >= len(KINDS) or end > len(data):
        raise UserError(INEXACT, code="payload.inexact")
    body = data[RECORD.size + name_length:end]
    if hashlib.sha256(body).digest() != digest or (KINDS[kind] == "image" and width * height * 3 != length):
        raise UserError(INEXACT, code="payload.inexact")
    if name_length > MAX_NAME_BYTES:  # what Record.pack writes at most
        raise UserError(f"the payload's file name is {name_length} bytes; a record holds at most {MAX_NAME_BYTES}",
                        code="payload.name_too_long", name_bytes=name_length, most=MAX_NAME_BYTES)
    if KINDS[kind] == "image":  # before any image library sees them
        checked_image_size(width, height, "the payload's image", code="payload.image_size")
    return Record(KINDS[kind], body, data[RECORD.size:RECORD.size + name_length], width, height)


def near_square(n_pixels: int) -> tuple[int, int]:
    """(width, height) of the squarest image with at least n_pixels (and at least one) pixels."""
    n_pixels = max(1, n_pixels)
    width = math.isqrt(n_pixels - 1) + 1
    return width, -(-n_pixels // width)


def sealed_shape(n_pixels: int, tile_size: int) -> tuple[int, int]:
    """(width, height) of the size bucket holding n_pixels: a square of MIN_BUCKET·2^k px while that is
    smaller than a tile, else a near-square grid of whole tiles."""
    side = MIN_BUCKET
    while side * side < n_pixels and side < tile_size:
        side *= 2
    if n_pixels <= min(side, tile_size) ** 2:
        side = min(side, tile_size)
        return side, side
    cols, rows = near_square(-(-n_pixels // tile_size ** 2))
    return cols * tile_size, rows * tile_size


def secret_shape(n_bytes: int, tile_size: int, sealed: bool) -> tuple[int, int]:
    """(width, height) of the secret that carries n_bytes, refused beyond what a bundle may hold."""
    n_pixels = -(-n_bytes // 3)
    width, height = sealed_shape(n_pixels, tile_size) if sealed else near_square(n_pixels)
    if width * height > MAX_PAYLOAD_PIXELS:
        raise UserError(f"a payload of {n_bytes} bytes needs a {width}x{height} secret, more than the "
                        f"{MAX_PAYLOAD_PIXELS} pixels a payload may take", code="payload.too_large", bytes=n_bytes,
                        width=width, height=height, most=MAX_PAYLOAD_PIXELS)
    checked_image_size(width, height, "the payload's secret", code="payload.secret_size")
    return width, height


def to_pixels(data: bytes, width: int, height: int) -> np.ndarray:
    """Bytes into (height, width, 3) uint8 pixels row-major, zero-padded."""
    pixels = np.zeros(width * height * 3, np.uint8)
    pixels[:len(data)] = np.frombuffer(data, np.uint8)
    return pixels.reshape(height, width, 3)


def payload_marker(seal: Seal | None) -> dict:
    """The bundle metadata's payload marker."""
    return {"version": PAYLOAD_VERSION, "sealed": None if seal is None else seal.to_dict()}


def checked_marker(data) -> dict:
    """A bundle's payload marker, refused unless it is exactly one payload_marker writes."""
    if not isinstance(data, dict) or data.get("version") != PAYLOAD_VERSION or set(data) != {"version", "sealed"}:
        raise UserError(f"bundle: payload must be an object with version {PAYLOAD_VERSION} and sealed",
                        code="payload.malformed", version=PAYLOAD_VERSION)
    seal_of(data)
    return data


def seal_of(marker: dict) -> Seal | None:
    """The seal of a payload marker, None when it is not sealed."""
    return None if marker["sealed"] is None else Seal.from_dict(marker["sealed"])


def payload_secret(record: Record, tile_size: int, model_fingerprint: str,
                   sealing: tuple[Seal, Keys] | None = None) -> tuple[np.ndarray, dict]:
    """The (h, w, 3) uint8 secret a record is hidden as, and the bundle's payload marker. Sealed: the
    record zero-padded to fill its size bucket, encrypted with the bundle's fixed fields as associated data."""
    packed = record.pack()
    if sealing is None:
        return to_pixels(packed, *secret_shape(len(packed), tile_size, sealed=False)), payload_marker(None)
    seal, keys = sealing
    width, height = secret_shape(len(packed) + TAG_BYTES, tile_size, sealed=True)
    marker = payload_marker(seal)
    plaintext = packed + bytes(width * height * 3 - TAG_BYTES - len(packed))
    ciphertext = encrypt(plaintext, keys, seal, associated_data(model_fingerprint, width, height, marker))
    return to_pixels(ciphertext, width, height), marker


def open_payload(pixels: np.ndarray, marker: dict, model_fingerprint: str, keys: Keys | None) -> Record:
    """The record in revealed pixels (h, w, 3) uint8; a sealed one is decrypted with `keys` first."""
    data = np.ascontiguousarray(pixels, np.uint8).tobytes()
    seal = seal_of(marker)
    if seal is not None:
        height, width = pixels.shape[:2]
        data = decrypt(data, keys, seal, associated_data(model_fingerprint, width, height, marker))
    return unpack_record(data)
