"""A scene's identity: SHA-256 over its weights and architecture.

The scene directory (train side) and the model file (runtime side) compute it with this one function,
the model from its ONNX initializers, so a model whose weights were changed is refused even when its
metadata still carries the original fingerprint.
"""

from __future__ import annotations

import hashlib
import json

import numpy as np


def weights_fingerprint(tensors: dict[str, np.ndarray], architecture: dict) -> str:
    """SHA-256 over the weights in sorted-name order (name, dtype, shape, little-endian bytes) and the
    canonical JSON of the architecture."""
    digest = hashlib.sha256()
    for name in sorted(tensors):
        array = np.ascontiguousarray(tensors[name]).astype(np.asarray(tensors[name]).dtype.newbyteorder("<"))
        digest.update(f"{name}|{array.dtype.str}|{list(array.shape)}|".encode())
        digest.update(array.tobytes())
    digest.update(json.dumps(architecture, sort_keys=True).encode())
    return digest.hexdigest()
