"""The secret bundle: the key a recipient gets. safetensors (never pickle): noise tensors + JSON metadata.

    tensors   tile_0000, tile_0001, …   noise per tile, (h, w, dims) for the "ray" layout (one vector per
              pixel shared by all its samples) or (h, w, n_samples, dims) for the paper's "sample" layout
    metadata  {"noisenerf_bundle": JSON}: format version, model fingerprint, secret size and the SHA-256
              of its 8-bit RGB pixels, noise layout and dtype, per tile its rectangle in the final image,
              camera, sampling and network ("coarse" or "fine": the network the noise was trained
              through; a tile without it, as bundles made before the field existed, means the scene's
              render network, the fine one where there is one), and for a payload (a file, or a sealed
              secret) the optional "payload" object that runtime.payload defines and validates.

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
from noisenerf.runtime.files import atomic_output, parse_json
from noisenerf.runtime.limits import (
    MAX_CAMERAS, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_RAY_LAYOUT_SAMPLES, MAX_TILES, checked_image_size, checked_int,
    checked_list,
)
from noisenerf.runtime.payload import checked_payload
from noisenerf.runtime.sampling import NETWORKS, SamplingConfig

BUNDLE_FORMAT_VERSION = 1
METADATA_KEY = "noisenerf_bundle"
LAYOUTS = ("ray", "sample")
DTYPES = {"float16": np.float16, "float32": np.float32}
SAFETENSORS_DTYPES = ("F16", "F32")  # the same two, as safetensors names them


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
    payload: dict | None = None  # runtime.payload's object for a file or sealed payload; None: an image

    def metadata(self) -> dict:
        return {
            "format_version": BUNDLE_FORMAT_VERSION,
            "model_fingerprint": self.model_fingerprint,
            "secret": {"width": self.width, "height": self.height, "sha256": self.secret_sha256},
            "noise": {"layout": self.layout, "dims": self.noise_dims, "dtype": self.dtype},
            "tiles": [tile.metadata(f"tile_{i:04d}") for i, tile in enumerate(self.tiles)],
            "extra": self.extra,
            **({"payload": self.payload} if self.payload is not None else {}),
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


def validate_tile(i: int, tile: Tile, bundle: Bundle) -> None:
    """One tile against the secret's size and the bundle's noise layout. In the ray layout one stored vector
    serves every sample of its ray, so n_samples is capped there: the render's work stays tied to the noise
    the bundle actually holds."""
    x0, y0, w, h = tile.rect
    if tile.network is not None and tile.network not in NETWORKS:
        raise UserError(f"bundle: tile {i} names network {tile.network!r:.40} (expected one of {NETWORKS})")
    if w < 1 or h < 1 or x0 < 0 or y0 < 0 or x0 + w > bundle.width or y0 + h > bundle.height:
        raise UserError(f"bundle: tile {i} rectangle {tile.rect} lies outside the "
                        f"{bundle.width}x{bundle.height} image")
    if (tile.camera.width, tile.camera.height) != (w, h):
        raise UserError(f"bundle: tile {i} camera is {tile.camera.width}x{tile.camera.height}, "
                        f"its rectangle {w}x{h}")
    if bundle.layout == "ray" and tile.sampling.n_samples > MAX_RAY_LAYOUT_SAMPLES:
        raise UserError(f"bundle: tile {i} asks for {tile.sampling.n_samples} samples per ray; the ray layout "
                        f"allows at most {MAX_RAY_LAYOUT_SAMPLES}")
    shape = expected_noise_shape(tile, bundle.layout, bundle.noise_dims)
    if tile.noise.shape != shape or tile.noise.dtype != DTYPES[bundle.dtype]:
        raise UserError(f"bundle: tile {i} noise is {tile.noise.dtype} {tile.noise.shape}, "
                        f"expected {bundle.dtype} {shape}")
    if not np.isfinite(tile.noise).all():
        raise UserError(f"bundle: tile {i} noise holds NaN or Inf")


def validate(bundle: Bundle) -> None:
    """Refuse anything a reveal could not render faithfully, with one clear message. Sizes are checked
    against the tiles' noise before the coverage mask is built, so the mask is never larger than the
    noise the bundle holds."""
    if bundle.layout not in LAYOUTS:
        raise UserError(f"bundle: unknown noise layout {bundle.layout!r} (expected one of {LAYOUTS})")
    if bundle.dtype not in DTYPES:
        raise UserError(f"bundle: unknown noise dtype {bundle.dtype!r} (expected one of {tuple(DTYPES)})")
    if bundle.width < 1 or bundle.height < 1 or not bundle.tiles:
        raise UserError(f"bundle: empty secret ({bundle.width}x{bundle.height}, {len(bundle.tiles)} tiles)")
    if len(bundle.tiles) > MAX_TILES:
        raise UserError(f"bundle: {len(bundle.tiles)} tiles, at most {MAX_TILES} allowed")
    for i, tile in enumerate(bundle.tiles):
        validate_tile(i, tile, bundle)
    if sum(tile.rect[2] * tile.rect[3] for tile in bundle.tiles) != bundle.width * bundle.height:
        raise UserError(f"bundle: the tiles' areas do not add up to the {bundle.width}x{bundle.height} secret")
    covered = np.zeros((bundle.height, bundle.width), dtype=np.uint8)
    for x0, y0, w, h in (tile.rect for tile in bundle.tiles):
        if covered[y0:y0 + h, x0:x0 + w].any():
            raise UserError("bundle: tile rectangles overlap")
        covered[y0:y0 + h, x0:x0 + w] = 1


def read_tensors(handle, path: Path) -> dict[str, np.ndarray]:
    """Every noise tensor, refusing any dtype but float16/float32 (bfloat16 has no numpy type) before reading."""
    tensors = {}
    for name in handle.keys():
        dtype = handle.get_slice(name).get_dtype()
        if dtype not in SAFETENSORS_DTYPES:
            raise UserError(f"bundle tensor {name!r} is {dtype}; noise is stored as "
                            f"{' or '.join(SAFETENSORS_DTYPES)}: {path}")
        tensors[name] = handle.get_tensor(name)
    return tensors


def parse_tile(i: int, data, tensors: dict[str, np.ndarray]) -> Tile:
    """One tile's metadata, every number type- and range-checked, joined to its tensor."""
    if not isinstance(data, dict):
        raise UserError(f"bundle: tile {i} must be a JSON object")
    rect = checked_list(data.get("rect"), f"bundle: tile {i} rect", length=4)
    x0, y0 = (checked_int(v, f"bundle: tile {i} rect origin", 0, MAX_IMAGE_SIDE) for v in rect[:2])
    width, height = checked_image_size(rect[2], rect[3], f"bundle: tile {i} rect")
    name = data.get("tensor")
    if not isinstance(name, str) or name not in tensors:
        raise UserError(f"bundle: tile {i} tensor {name!r:.40} is missing")
    view = data.get("view")
    return Tile(rect=(x0, y0, width, height), camera=Camera.from_dict(data.get("camera")),
                sampling=SamplingConfig.from_dict(data.get("sampling")), noise=tensors[name],
                view=None if view is None else checked_int(view, f"bundle: tile {i} view", 0, MAX_CAMERAS),
                network=None if data.get("network") is None else checked_text(data["network"], f"bundle: tile {i} network"))


def checked_text(value, what: str) -> str:
    """A short JSON string (fingerprints, digests, names)."""
    if not isinstance(value, str) or len(value) > 256:
        raise UserError(f"{what} must be a string of at most 256 characters")
    return value


def parse_bundle(meta, tensors: dict[str, np.ndarray], path: Path) -> Bundle:
    """The metadata as a Bundle; nothing is converted by truncation (16.9 is not a size)."""
    if not isinstance(meta, dict) or meta.get("format_version") != BUNDLE_FORMAT_VERSION:
        raise UserError(f"unsupported bundle format version in {path}")
    secret, noise = meta.get("secret"), meta.get("noise")
    if not isinstance(secret, dict) or not isinstance(noise, dict):
        raise UserError("bundle: metadata needs 'secret' and 'noise' objects")
    width, height = checked_image_size(secret.get("width"), secret.get("height"), "bundle: secret")
    tiles = checked_list(meta.get("tiles"), "bundle: tiles", most=MAX_TILES)
    extra = meta.get("extra", {})
    return Bundle(model_fingerprint=checked_text(meta.get("model_fingerprint"), "bundle: model_fingerprint"),
                  width=width, height=height, secret_sha256=checked_text(secret.get("sha256"), "bundle: sha256"),
                  layout=checked_text(noise.get("layout"), "bundle: noise layout"),
                  noise_dims=checked_int(noise.get("dims"), "bundle: noise dims", 1, MAX_NOISE_DIMS),
                  dtype=checked_text(noise.get("dtype"), "bundle: noise dtype"),
                  tiles=tuple(parse_tile(i, tile, tensors) for i, tile in enumerate(tiles)),
                  extra=extra if isinstance(extra, dict) else {},
                  payload=None if meta.get("payload") is None else checked_payload(meta["payload"]))


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
            meta = parse_json(raw, "bundle metadata", path)
            tensors = read_tensors(handle, path)
    except (SafetensorError, OSError, ValueError, TypeError) as error:
        raise UserError(f"not a readable safetensors bundle: {path} ({error})") from None
    bundle = parse_bundle(meta, tensors, path)
    validate(bundle)
    return bundle
