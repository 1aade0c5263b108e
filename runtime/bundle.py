"""The secret bundle: the key a recipient gets. safetensors (never pickle): noise tensors + JSON metadata.

    tensors   tile_0000, tile_0001, …   noise per tile, (h, w, dims) for the "ray" layout (one vector per
              pixel shared by all its samples) or (h, w, n_samples, dims) for the paper's "sample" layout
    metadata  {"noisenerf_bundle": JSON}: format version, model fingerprint, secret size and the SHA-256
              of its 8-bit RGB pixels, noise layout and dtype, per tile its rectangle in the final image,
              camera, sampling and network ("coarse" or "fine": the network the noise was trained
              through; a tile without it, as bundles made before the field existed, means the scene's
              render network, the fine one where there is one).

The bundle holds noise and metadata only: without the model's exact weights it renders nothing.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors import SafetensorError, safe_open
from safetensors.numpy import save_file

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import atomic_output
from noisenerf.runtime.sampling import NETWORKS, SamplingConfig

BUNDLE_FORMAT_VERSION = 1
METADATA_KEY = "noisenerf_bundle"
LAYOUTS = ("ray", "sample")
DTYPES = {"float16": np.float16, "float32": np.float32}


def secret_digest(pixels: np.ndarray) -> str:
    """SHA-256 of an 8-bit RGB image's bytes, (height, width, 3) uint8 row-major."""
    pixels = np.ascontiguousarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        raise ValueError(f"secret digest needs (h, w, 3) uint8 pixels, got {pixels.dtype} {pixels.shape}")
    return hashlib.sha256(pixels.tobytes()).hexdigest()


@dataclass(frozen=True)
class Tile:
    """One piece of the secret: where it goes, the view it is hidden in, and its noise."""

    rect: tuple[int, int, int, int]  # x0, y0, width, height in the final image
    camera: Camera  # width × height equal to the rect's
    sampling: SamplingConfig
    noise: np.ndarray
    view: int | None = None  # the scene camera it was derived from, if any
    network: str | None = None  # coarse | fine; None: the scene's render network

    def metadata(self, tensor_name: str) -> dict:
        return {"rect": list(self.rect), "camera": self.camera.to_dict(), "view": self.view,
                "sampling": {"near": self.sampling.near, "far": self.sampling.far,
                             "n_samples": self.sampling.n_samples}, "tensor": tensor_name,
                **({"network": self.network} if self.network is not None else {})}


@dataclass(frozen=True)
class Bundle:
    model_fingerprint: str
    width: int
    height: int
    secret_sha256: str
    layout: str
    noise_dims: int
    dtype: str
    tiles: tuple[Tile, ...]
    extra: dict  # how it was made (method, seed, versions): informative only

    def metadata(self) -> dict:
        return {
            "format_version": BUNDLE_FORMAT_VERSION,
            "model_fingerprint": self.model_fingerprint,
            "secret": {"width": self.width, "height": self.height, "sha256": self.secret_sha256},
            "noise": {"layout": self.layout, "dims": self.noise_dims, "dtype": self.dtype},
            "tiles": [tile.metadata(f"tile_{i:04d}") for i, tile in enumerate(self.tiles)],
            "extra": self.extra,
        }

    def noise_bytes(self) -> int:
        return sum(tile.noise.nbytes for tile in self.tiles)

    def save(self, path: str | Path) -> None:
        """Validate, then write atomically."""
        validate(self)
        tensors = {f"tile_{i:04d}": np.ascontiguousarray(tile.noise) for i, tile in enumerate(self.tiles)}
        with atomic_output(path) as tmp:
            save_file(tensors, str(tmp), metadata={METADATA_KEY: json.dumps(self.metadata(), sort_keys=True)})


def expected_noise_shape(tile: Tile, layout: str, dims: int) -> tuple[int, ...]:
    width, height = tile.rect[2], tile.rect[3]
    return (height, width, dims) if layout == "ray" else (height, width, tile.sampling.n_samples, dims)


def validate(bundle: Bundle) -> None:
    """Refuse anything a reveal could not render faithfully, with one clear message."""
    if bundle.layout not in LAYOUTS:
        raise UserError(f"bundle: unknown noise layout {bundle.layout!r} (expected one of {LAYOUTS})")
    if bundle.dtype not in DTYPES:
        raise UserError(f"bundle: unknown noise dtype {bundle.dtype!r} (expected one of {tuple(DTYPES)})")
    if bundle.width < 1 or bundle.height < 1 or not bundle.tiles:
        raise UserError(f"bundle: empty secret ({bundle.width}x{bundle.height}, {len(bundle.tiles)} tiles)")
    covered = np.zeros((bundle.height, bundle.width), dtype=np.int32)
    for i, tile in enumerate(bundle.tiles):
        x0, y0, w, h = tile.rect
        if tile.network is not None and tile.network not in NETWORKS:
            raise UserError(f"bundle: tile {i} names network {tile.network!r} (expected one of {NETWORKS})")
        if w < 1 or h < 1 or x0 < 0 or y0 < 0 or x0 + w > bundle.width or y0 + h > bundle.height:
            raise UserError(f"bundle: tile {i} rectangle {tile.rect} lies outside the "
                            f"{bundle.width}x{bundle.height} image")
        if (tile.camera.width, tile.camera.height) != (w, h):
            raise UserError(f"bundle: tile {i} camera is {tile.camera.width}x{tile.camera.height}, "
                            f"its rectangle {w}x{h}")
        shape = expected_noise_shape(tile, bundle.layout, bundle.noise_dims)
        if tile.noise.shape != shape or tile.noise.dtype != DTYPES[bundle.dtype]:
            raise UserError(f"bundle: tile {i} noise is {tile.noise.dtype} {tile.noise.shape}, "
                            f"expected {bundle.dtype} {shape}")
        if not np.isfinite(tile.noise).all():
            raise UserError(f"bundle: tile {i} noise holds NaN or Inf")
        covered[y0:y0 + h, x0:x0 + w] += 1
    if covered.max() > 1:
        raise UserError("bundle: tile rectangles overlap")
    if covered.min() < 1:
        raise UserError("bundle: tile rectangles do not cover the whole secret")


def load_bundle(path: str | Path) -> Bundle:
    """Read and validate a bundle; anything malformed is one UserError."""
    path = Path(path)
    if not path.is_file():
        raise UserError(f"bundle not found: {path}")
    try:
        with safe_open(str(path), framework="numpy") as handle:
            raw = (handle.metadata() or {}).get(METADATA_KEY)
            if raw is None:
                raise UserError(f"not a noisenerf bundle (no '{METADATA_KEY}' metadata): {path}")
            meta = json.loads(raw)
            tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    except (SafetensorError, OSError, ValueError) as error:
        raise UserError(f"not a readable safetensors bundle: {path} ({error})") from None
    if not isinstance(meta, dict) or meta.get("format_version") != BUNDLE_FORMAT_VERSION:
        raise UserError(f"unsupported bundle format version in {path}")
    try:
        tiles = []
        for i, tile in enumerate(meta["tiles"]):
            if tile["tensor"] not in tensors:
                raise UserError(f"bundle: tile {i} tensor {tile['tensor']!r} is missing")
            tiles.append(Tile(rect=tuple(int(v) for v in tile["rect"]), camera=Camera.from_dict(tile["camera"]),
                              sampling=SamplingConfig(**tile["sampling"]), noise=tensors[tile["tensor"]],
                              view=tile.get("view"), network=tile.get("network")))
        bundle = Bundle(model_fingerprint=str(meta["model_fingerprint"]), width=int(meta["secret"]["width"]),
                        height=int(meta["secret"]["height"]), secret_sha256=str(meta["secret"]["sha256"]),
                        layout=str(meta["noise"]["layout"]), noise_dims=int(meta["noise"]["dims"]),
                        dtype=str(meta["noise"]["dtype"]), tiles=tuple(tiles), extra=dict(meta.get("extra", {})))
    except (KeyError, TypeError, ValueError) as error:
        raise UserError(f"bundle: malformed metadata ({error!r})") from None
    validate(bundle)
    return bundle
