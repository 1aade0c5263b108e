"""A scene's identity: SHA-256 over its weights and architecture; and its mask secret, from the same bytes.

The scene directory (train side) and the model file (runtime side) compute it with this one function,
the model from its ONNX initializers, so a model whose weights were changed is refused even when its
metadata still carries the original fingerprint.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass

import numpy as np


MASK_SECRET_PREFIX = b"noisenerf bundle mask secret\0"  # a second digest of the same bytes, under its own prefix


@dataclass(frozen=True)
class WeightsDigests:
    fingerprint: str  # public: the model's metadata and every bundle state it
    mask_secret: bytes  # known only to whoever holds the weights: what a bundle's mask key comes from (runtime.masking)


def weights_digests(tensors: dict[str, np.ndarray], architecture: dict) -> WeightsDigests:
    """SHA-256 over the weights in sorted-name order (name, dtype, shape, little-endian bytes) and the canonical JSON
    of the architecture: the fingerprint; and SHA-256 over MASK_SECRET_PREFIX then the same bytes: the mask secret,
    which the fingerprint does not give (SHA-256 is preimage resistant, and the prefix leads)."""
    fingerprint, mask = hashlib.sha256(), hashlib.sha256(MASK_SECRET_PREFIX)
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name]).astype(np.asarray(tensors[name]).dtype.newbyteorder("<"))
        for part in (f"{name}|{array.dtype.str}|{list(array.shape)}|".encode(), array.tobytes()):
            fingerprint.update(part)
            mask.update(part)
    architecture_bytes = json.dumps(architecture, sort_keys=True).encode()
    fingerprint.update(architecture_bytes)
    mask.update(architecture_bytes)
    return WeightsDigests(fingerprint.hexdigest(), mask.digest())


def weights_fingerprint(tensors: dict[str, np.ndarray], architecture: dict) -> str:
    """The fingerprint alone (weights_digests)."""
    return weights_digests(tensors, architecture).fingerprint
