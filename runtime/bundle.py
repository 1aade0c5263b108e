"""The secret bundle: the key a recipient gets. safetensors (never pickle): noise tensors + JSON metadata.

    tensors   tile_0000, tile_0001, …   noise per tile, in one of three layouts:
              "compact" (format 2, the exact method's default): per pixel k integer coefficients
                  (int16 or int8) of a per-tile basis; tile_NNNN is uint8, the xz stream of the
                  coefficients as byte planes (coefficient-major, then byte, then row-major pixels,
                  little-endian: planes of like bytes compress best), tile_NNNN_basis (dims, k) and
                  tile_NNNN_offset (dims,) float32, and the tile's "scale" in the metadata:
                  noise = offset + (coefficients · scale) basisᵀ, computed in float32; pixels the
                  basis could not reach "escape": tile_NNNN_escapes (e,) int32, their row-major
                  indices in the tile, strictly increasing, and tile_NNNN_escape_noise (e, dims)
                  float16, their full noise (their coefficients are stored as 0);
              "ray": (h, w, dims) float noise, one vector per pixel shared by all its samples;
              "sample": (h, w, n_samples, dims) float noise, the paper's per-sample layout.
    metadata  {"noisenerf_bundle": JSON}: format version, model fingerprint, secret size and the SHA-256
              of its 8-bit RGB pixels, noise layout and dtype, per tile its rectangle in the final image,
              camera, sampling and network ("coarse" or "fine": the network the noise was trained
              through; a tile without it, as bundles made before the field existed, means the scene's
              render network, the fine one where there is one), and for a payload (a file, or a sealed
              secret) the optional "payload" object that runtime.payload defines and validates.

Versions: noisenerf writes format 2 and reads formats 1 and 2. Format 1 (every bundle written before the
compact layout) holds only the ray and sample layouts, which format 2 keeps unchanged, so it reveals as
it always did. A format this version does not know (a newer writer's) is refused in one line naming it.

The bundle holds noise and metadata only: without the model's exact weights it renders nothing.
"""

from __future__ import annotations

import hashlib
import json
import lzma
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load, save

from noisenerf import __version__
from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import os_failure, parse_json, write_bytes
from noisenerf.runtime.limits import (
    MAX_CAMERAS, MAX_COMPACT_COEFFICIENTS, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_RAY_LAYOUT_SAMPLES, MAX_TILES,
    MAX_XZ_MEMORY, checked_expansion, checked_float, checked_image_size, checked_int, checked_list,
)
from noisenerf.runtime.networks import NETWORKS
from noisenerf.runtime.payload import checked_payload
from noisenerf.runtime.sealing import split_safetensors
from noisenerf.runtime.sampling import SamplingConfig

BUNDLE_FORMAT_VERSION = 2
METADATA_KEY = "noisenerf_bundle"
READABLE_FORMATS = {1: ("ray", "sample"), 2: ("ray", "sample", "compact")}  # format -> the layouts it may hold
LAYOUTS = READABLE_FORMATS[BUNDLE_FORMAT_VERSION]
DTYPES = {"float16": np.float16, "float32": np.float32, "int8": np.int8, "int16": np.int16}
LAYOUT_DTYPES = {"ray": ("float16", "float32"), "sample": ("float32", "float16"), "compact": ("int16", "int8")}  # default first
SAFETENSORS_DTYPES = ("F16", "F32", "U8", "I32")  # float noise, bases and offsets, compressed coefficients, escapes
# a compact bundle's coefficients, up to this many bytes unpacked, stay unpacked from the load's check to the render
# (one xz decode for ordinary secrets); beyond, tiles are unpacked again one at a time, so memory stays bounded
KEPT_UNPACKED_BYTES = 1 << 26
XZ_PRESET = 6  # xz level of the coefficient planes (9 saved under 1 % more on photos, at twice the time)


def secret_digest(pixels: np.ndarray) -> str:
    """SHA-256 of an 8-bit RGB image's bytes, (height, width, 3) uint8 row-major."""
    pixels = np.ascontiguousarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        raise ValueError(f"secret digest needs (h, w, 3) uint8 pixels, got {pixels.dtype} {pixels.shape}")
    return hashlib.sha256(pixels.data).hexdigest()  # the buffer itself: no copy of a big secret


@dataclass(frozen=True)
class CompactBasis:
    """A compact tile's basis: a pixel's noise is offset + (coefficients · scale) basisᵀ."""

    basis: np.ndarray  # (dims, k) float32
    offset: np.ndarray  # (dims,) float32
    scale: float  # one integer step of a coefficient (a float32 value)
    escapes: np.ndarray  # (e,) int32, strictly increasing row-major pixel indices with full noise
    escape_noise: np.ndarray  # (e, dims) float16


def expand_coefficients(coefficients: np.ndarray, basis: CompactBasis, start: int = 0) -> np.ndarray:
    """Noise of compact pixels start.. start+m in float32, as the solver computed it
    (train/hide/exact.NoiseSpace.expand: one float32 multiply by the scale, then the matmul), with the
    escaped pixels' stored noise. coefficients: (m, k) int -> (m, dims) float32."""
    params = coefficients.astype(np.float32) * np.float32(basis.scale)
    noise = basis.offset + params @ basis.basis.T
    first, last = np.searchsorted(basis.escapes, [start, start + len(coefficients)])
    noise[basis.escapes[first:last] - start] = basis.escape_noise[first:last]
    return noise


def pack_coefficients(coefficients: np.ndarray) -> np.ndarray:
    """The xz stream of (h, w, k) integer coefficients as byte planes (see the module docstring). -> (n,) uint8."""
    planes = np.ascontiguousarray(coefficients.astype(coefficients.dtype.newbyteorder("<")).transpose(2, 0, 1))
    split = planes.view(np.uint8).reshape(*planes.shape, -1).transpose(0, 3, 1, 2)
    return np.frombuffer(lzma.compress(np.ascontiguousarray(split).tobytes(), preset=XZ_PRESET), dtype=np.uint8)


def unpack_coefficients(packed: np.ndarray, shape: tuple[int, int, int], dtype: str, what: str) -> np.ndarray:
    """pack_coefficients undone, refusing a stream that is corrupt or does not hold exactly shape's bytes
    (at most that many are ever decompressed, within MAX_XZ_MEMORY). -> (h, w, k) of dtype."""
    kind = np.dtype(DTYPES[dtype]).newbyteorder("<")
    expected = int(np.prod(shape)) * kind.itemsize
    decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_XZ, memlimit=MAX_XZ_MEMORY)
    try:
        data = decompressor.decompress(packed.tobytes(), max_length=expected + 1)
    except lzma.LZMAError as error:
        raise UserError(f"{what}: compressed coefficients are corrupt ({error})") from None
    if len(data) != expected or not decompressor.eof or decompressor.unused_data:
        raise UserError(f"{what}: compressed coefficients do not hold exactly {shape} {dtype} values")
    height, width, k = shape
    split = np.frombuffer(data, dtype=np.uint8).reshape(k, kind.itemsize, height, width)
    planes = np.ascontiguousarray(split.transpose(0, 2, 3, 1)).view(kind)[..., 0]
    return planes.transpose(1, 2, 0).astype(DTYPES[dtype])


@dataclass(frozen=True)
class VectorNoise:
    """The ray and sample layouts' noise, as stored: float vectors, (h, w, dims) one per ray or
    (h, w, n_samples, dims) one per sample."""

    values: np.ndarray

    @property
    def shape(self) -> tuple[int, ...]:
        """The stored array's shape, which the bundle header states."""
        return self.values.shape

    @property
    def dtype(self) -> np.dtype:
        return self.values.dtype

    def loaded(self) -> VectorNoise:
        """What a render reads rows from: the stored floats themselves."""
        return self

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Float32 noise of pixels start..stop (row-major): (m, 1 or n_samples, dims)."""
        flat = self.values.reshape(-1, *self.values.shape[2:])[start:stop].astype(np.float32)
        return flat[:, None, :] if flat.ndim == 2 else flat

    def tensors(self, name: str) -> dict[str, np.ndarray]:
        """What the file stores for this noise under `name`."""
        return {name: np.ascontiguousarray(self.values)}


@dataclass(frozen=True)
class CompactCoefficients:
    """A compact tile's coefficients unpacked, (h, w, k) integers, for a render to read rows from."""

    coefficients: np.ndarray
    basis: CompactBasis

    def rows(self, start: int, stop: int) -> np.ndarray:
        """Float32 noise of pixels start..stop (row-major), expanded: (m, 1, dims)."""
        flat = self.coefficients.reshape(-1, self.coefficients.shape[-1])[start:stop]
        return expand_coefficients(flat, self.basis, start)[:, None, :]


@dataclass(frozen=True)
class CompactNoise:
    """The compact layout's noise: per pixel k integer coefficients (h, w, k) of the tile's basis, held as
    the file stores them (pack_coefficients' xz stream). A hide packs a tile once it is solved; a reveal
    renders the coefficients load_bundle kept (KEPT_UNPACKED_BYTES) and unpacks the others one tile at a time
    (`loaded`), so neither holds a big secret's coefficients unpacked."""

    packed: np.ndarray  # (n,) uint8
    shape: tuple[int, int, int]  # (h, w, k)
    dtype: np.dtype  # int16 or int8
    basis: CompactBasis
    unpacked: np.ndarray | None = None  # the coefficients, where load_bundle kept them (KEPT_UNPACKED_BYTES)

    @staticmethod
    def of(coefficients: np.ndarray, basis: CompactBasis) -> CompactNoise:
        """Coefficients (h, w, k) int16 or int8, packed."""
        return CompactNoise(pack_coefficients(coefficients), coefficients.shape, coefficients.dtype, basis)

    def coefficients(self) -> np.ndarray:
        """The unpacked coefficients (h, w, k)."""
        return unpack_coefficients(self.packed, self.shape, self.dtype.name, "bundle: compact tile")

    def loaded(self) -> CompactCoefficients:
        unpacked = self.coefficients() if self.unpacked is None else self.unpacked
        return CompactCoefficients(unpacked, self.basis)

    def tensors(self, name: str) -> dict[str, np.ndarray]:
        return {name: self.packed, f"{name}_basis": np.ascontiguousarray(self.basis.basis),
                f"{name}_offset": np.ascontiguousarray(self.basis.offset),
                f"{name}_escapes": np.ascontiguousarray(self.basis.escapes),
                f"{name}_escape_noise": np.ascontiguousarray(self.basis.escape_noise)}


TileNoise = VectorNoise | CompactNoise


@dataclass(frozen=True)
class Tile:
    """One piece of the secret: where it goes, the view it is hidden in, and its noise."""

    rect: tuple[int, int, int, int]  # x0, y0, width, height in the final image
    camera: Camera  # width × height equal to the rect's
    sampling: SamplingConfig
    noise: TileNoise | None  # None only in a hide's plan, before the tile is solved
    view: int | None = None  # the index of the scene camera it was derived from, if any
    network: str | None = None  # coarse | fine; None: the scene's render network

    def metadata(self, tensor_name: str) -> dict:
        return {"rect": list(self.rect), "camera": self.camera.to_dict(), "view": self.view,
                "sampling": {"near": self.sampling.near, "far": self.sampling.far,
                             "n_samples": self.sampling.n_samples}, "tensor": tensor_name,
                **({"network": self.network} if self.network is not None else {}),
                **({"scale": self.noise.basis.scale} if isinstance(self.noise, CompactNoise) else {})}


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
    coefficients: int | None = None  # compact layout: k per pixel

    def metadata(self) -> dict:
        compact = {"coefficients": self.coefficients, "codec": "xz-byte-planes"} if self.layout == "compact" else {}
        return {
            "format_version": BUNDLE_FORMAT_VERSION,
            "model_fingerprint": self.model_fingerprint,
            "secret": {"width": self.width, "height": self.height, "sha256": self.secret_sha256},
            "noise": {"layout": self.layout, "dims": self.noise_dims, "dtype": self.dtype, **compact},
            "tiles": [tile.metadata(f"tile_{i:04d}") for i, tile in enumerate(self.tiles)],
            "extra": self.extra,
            **({"payload": self.payload} if self.payload is not None else {}),
        }

    def save(self, path: str | Path, replace: bool = False) -> None:
        """Validate, then write atomically (replace: whether an existing file may be replaced, --force)."""
        validate(self)
        tensors = {name: value for i, tile in enumerate(self.tiles)
                   for name, value in tile.noise.tensors(f"tile_{i:04d}").items()}
        write_bytes(path, save(tensors, metadata={METADATA_KEY: json.dumps(self.metadata(), sort_keys=True)}),
                    replace=replace)


def noise_shape(layout: str, height: int, width: int, n_samples: int, per_vector: int) -> tuple[int, ...]:
    """A tile's stored noise array: (h, w, n_samples, per_vector) in the sample layout (a vector per sample),
    else (h, w, per_vector) (a vector per ray: dims noise values, or k compact coefficients)."""
    return (height, width, n_samples, per_vector) if layout == "sample" else (height, width, per_vector)


def expected_noise_shape(tile: Tile, bundle: "Bundle") -> tuple[int, ...]:
    per_vector = bundle.coefficients if bundle.layout == "compact" else bundle.noise_dims
    return noise_shape(bundle.layout, tile.rect[3], tile.rect[2], tile.sampling.n_samples, per_vector)


def validate_basis(i: int, tile: Tile, bundle: "Bundle") -> None:
    """A compact tile's basis (dims, k), offset (dims,) float32 and escape noise (e, dims) float16, all
    finite; its scale > 0; its escapes (e,) int32 strictly increasing inside the tile."""
    basis, dims, k = tile.noise.basis, bundle.noise_dims, bundle.coefficients
    escapes = basis.escapes
    if escapes.ndim != 1 or escapes.dtype != np.int32:
        raise UserError(f"bundle: tile {i} escapes are {escapes.dtype} {escapes.shape}, expected int32 (e,)")
    if len(escapes) and (escapes[0] < 0 or escapes[-1] >= tile.rect[2] * tile.rect[3] or (np.diff(escapes) <= 0).any()):
        raise UserError(f"bundle: tile {i} escapes must be strictly increasing pixel indices inside the tile")
    for what, value, shape, dtype in (("basis", basis.basis, (dims, k), np.float32),
                                      ("offset", basis.offset, (dims,), np.float32),
                                      ("escape noise", basis.escape_noise, (len(escapes), dims), np.float16)):
        if value.shape != shape or value.dtype != dtype:
            raise UserError(f"bundle: tile {i} {what} is {value.dtype} {value.shape}, expected "
                            f"{np.dtype(dtype)} {shape}")
        if not np.isfinite(value).all():
            raise UserError(f"bundle: tile {i} {what} holds NaN or Inf")
    checked_float(basis.scale, f"bundle: tile {i} scale", low=np.finfo(np.float32).tiny,
                  high=float(np.finfo(np.float32).max))


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
    if bundle.layout != "sample" and tile.sampling.n_samples > MAX_RAY_LAYOUT_SAMPLES:
        raise UserError(f"bundle: tile {i} asks for {tile.sampling.n_samples} samples per ray; the {bundle.layout} "
                        f"layout allows at most {MAX_RAY_LAYOUT_SAMPLES}")
    kind = CompactNoise if bundle.layout == "compact" else VectorNoise
    if not isinstance(tile.noise, kind):
        raise UserError(f"bundle: tile {i} noise is {type(tile.noise).__name__}; the {bundle.layout} layout "
                        f"stores {kind.__name__}")
    shape, noise = expected_noise_shape(tile, bundle), tile.noise
    if noise.shape != shape or noise.dtype != DTYPES[bundle.dtype]:
        raise UserError(f"bundle: tile {i} noise is {noise.dtype} {noise.shape}, "
                        f"expected {bundle.dtype} {shape}")
    if bundle.layout == "compact":
        validate_basis(i, tile, bundle)
    elif not np.isfinite(noise.values).all():  # a compact tile's integers are finite by type
        raise UserError(f"bundle: tile {i} noise holds NaN or Inf")


def validate_noise_header(layout: str, dtype: str, dims: int, coefficients: int | None,
                          layouts: tuple[str, ...] = LAYOUTS) -> None:
    """The noise description alone (checked before any tile's coefficients are decompressed)."""
    if layout not in layouts:
        raise UserError(f"bundle: unknown noise layout {layout!r:.40} (expected one of {layouts})")
    if dtype not in LAYOUT_DTYPES[layout]:
        raise UserError(f"bundle: unknown noise dtype {dtype!r:.40} for the {layout} layout (expected one of "
                        f"{LAYOUT_DTYPES[layout]})")
    if (coefficients is not None) != (layout == "compact"):
        raise UserError("bundle: coefficients per pixel are given for, and only for, the compact layout")
    if layout == "compact" and not 1 <= coefficients <= min(dims, MAX_COMPACT_COEFFICIENTS):
        raise UserError(f"bundle: {coefficients} coefficients per pixel, expected 1 to "
                        f"{min(dims, MAX_COMPACT_COEFFICIENTS)}")


def validate(bundle: Bundle) -> None:
    """Refuse anything a reveal could not render faithfully, with one clear message. Sizes are checked
    against the tiles' noise before the coverage mask is built, so the mask is never larger than the
    noise the bundle holds."""
    validate_noise_header(bundle.layout, bundle.dtype, bundle.noise_dims, bundle.coefficients)
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


def read_tensors(header: dict, data: bytes, source: str) -> dict[str, np.ndarray]:
    """Every tensor, refusing any dtype but SAFETENSORS_DTYPES (bfloat16 has no numpy type) before reading."""
    for name, info in header.items():
        dtype = info.get("dtype") if isinstance(info, dict) else None
        if name != "__metadata__" and dtype not in SAFETENSORS_DTYPES:
            raise UserError(f"bundle tensor {name!r:.60} is {dtype!r:.20}; noise is stored as "
                            f"{' or '.join(SAFETENSORS_DTYPES)}: {source}")
    try:
        return load(data)
    except (SafetensorError, ValueError, TypeError) as error:
        raise UserError(f"not a readable safetensors bundle: {source} ({error})") from None


def tile_tensor(tensors: dict[str, np.ndarray], name: str, what: str, dtype=None, ndim: int | None = None) -> np.ndarray:
    """A named tensor that must exist (with this dtype and rank, when given)."""
    if name not in tensors:
        raise UserError(f"{what} tensor {name!r:.60} is missing")
    value = tensors[name]
    if (dtype is not None and value.dtype != dtype) or (ndim is not None and value.ndim != ndim):
        raise UserError(f"{what} tensor {name!r:.60} is {value.dtype} {value.shape}")
    return value


def compact_noise(name: str, data: dict, tensors: dict[str, np.ndarray], shape: tuple[int, int, int], dtype: str,
                  what: str, keep_unpacked: bool) -> CompactNoise:
    """A compact tile's coefficients (h, w, k) and its basis. The stream is decompressed here to check it
    holds exactly that (only once the header and rect are known good, so at most h·w·k values); the
    coefficients are kept if keep_unpacked, else dropped (a reveal unpacks the tile again when it renders)."""
    basis = CompactBasis(basis=tile_tensor(tensors, f"{name}_basis", what), offset=tile_tensor(tensors, f"{name}_offset", what),
                  scale=checked_float(data.get("scale"), f"{what} scale", low=float(np.finfo(np.float32).tiny),
                                      high=float(np.finfo(np.float32).max)),
                  escapes=tile_tensor(tensors, f"{name}_escapes", what),
                  escape_noise=tile_tensor(tensors, f"{name}_escape_noise", what))
    packed = tile_tensor(tensors, name, what, dtype=np.uint8, ndim=1)
    unpacked = unpack_coefficients(packed, shape, dtype, what)
    return CompactNoise(packed, shape, np.dtype(DTYPES[dtype]), basis, unpacked if keep_unpacked else None)


def parse_tile(i: int, data, tensors: dict[str, np.ndarray], header: dict, keep_unpacked: bool) -> Tile:
    """One tile's metadata, every number type- and range-checked, joined to its tensors. header: the
    bundle's checked layout, dtype and coefficients; keep_unpacked: compact_noise's."""
    x0, y0, width, height = checked_rect(i, data)
    name = data.get("tensor")
    if not isinstance(name, str):
        raise UserError(f"bundle: tile {i} tensor {name!r:.40} is missing")
    if header["layout"] == "compact":
        noise = compact_noise(name, data, tensors, (height, width, header["coefficients"]), header["dtype"],
                              f"bundle: tile {i}", keep_unpacked)
    else:
        noise = VectorNoise(tile_tensor(tensors, name, f"bundle: tile {i}"))
    view = data.get("view")
    return Tile(rect=(x0, y0, width, height), camera=Camera.from_dict(data.get("camera")),
                sampling=SamplingConfig.from_dict(data.get("sampling")), noise=noise,
                view=None if view is None else checked_int(view, f"bundle: tile {i} view", 0, MAX_CAMERAS),
                network=None if data.get("network") is None else checked_text(data["network"], f"bundle: tile {i} network"))


def checked_text(value, what: str) -> str:
    """A short JSON string (fingerprints, digests, names)."""
    if not isinstance(value, str) or len(value) > 256:
        raise UserError(f"{what} must be a string of at most 256 characters")
    return value


def checked_format(meta: dict, path: Path) -> int:
    """The bundle's format version, refusing one this noisenerf cannot read in a line that says which."""
    version = meta.get("format_version")
    if isinstance(version, bool) or version not in READABLE_FORMATS:
        newest = max(READABLE_FORMATS)
        raise UserError(f"{path} is bundle format {version!r:.20}; noisenerf {__version__} reads formats "
                        f"{min(READABLE_FORMATS)} to {newest}"
                        + ("; a newer noisenerf is needed" if isinstance(version, int) and version > newest else ""))
    return version


def noise_header(noise: dict, layouts: tuple[str, ...]) -> dict:
    """The bundle's noise description, type- and range-checked. -> {layout, dims, dtype, coefficients}."""
    layout = checked_text(noise.get("layout"), "bundle: noise layout")
    header = {"layout": layout, "dims": checked_int(noise.get("dims"), "bundle: noise dims", 1, MAX_NOISE_DIMS),
              "dtype": checked_text(noise.get("dtype"), "bundle: noise dtype"), "coefficients": None}
    if layout == "compact":
        header["coefficients"] = checked_int(noise.get("coefficients"), "bundle: coefficients per pixel", 1,
                                             MAX_COMPACT_COEFFICIENTS)
        if noise.get("codec") != "xz-byte-planes":
            raise UserError(f"bundle: unknown coefficient codec {noise.get('codec')!r:.40} (expected 'xz-byte-planes')")
    validate_noise_header(header["layout"], header["dtype"], header["dims"], header["coefficients"], layouts)
    return header


def parse_bundle(meta, tensors: dict[str, np.ndarray], path: Path) -> Bundle:
    """The metadata as a Bundle; nothing is converted by truncation (16.9 is not a size)."""
    if not isinstance(meta, dict):
        raise UserError(f"bundle metadata must be a JSON object: {path}")
    version = checked_format(meta, path)
    secret, noise = meta.get("secret"), meta.get("noise")
    if not isinstance(secret, dict) or not isinstance(noise, dict):
        raise UserError("bundle: metadata needs 'secret' and 'noise' objects")
    width, height = checked_image_size(secret.get("width"), secret.get("height"), "bundle: secret")
    header = noise_header(noise, READABLE_FORMATS[version])
    tiles = checked_list(meta.get("tiles"), "bundle: tiles", most=MAX_TILES)
    areas = np.array([w * h for _, _, w, h in (checked_rect(i, tile) for i, tile in enumerate(tiles))], np.int64)
    if header["layout"] == "compact" and areas.sum() != width * height:  # before inflating any stream
        raise UserError(f"bundle: the tiles' areas do not add up to the {width}x{height} secret")
    if header["layout"] == "compact":
        streams = (tensors.get(tile.get("tensor")) if isinstance(tile.get("tensor"), str) else None for tile in tiles)
        checked_expansion(sum(stream.nbytes for stream in streams if stream is not None),
                          int(areas.sum()) * header["coefficients"] * np.dtype(DTYPES[header["dtype"]]).itemsize,
                          "bundle")
    extra = meta.get("extra", {})
    return Bundle(model_fingerprint=checked_text(meta.get("model_fingerprint"), "bundle: model_fingerprint"),
                  width=width, height=height, secret_sha256=checked_text(secret.get("sha256"), "bundle: sha256"),
                  layout=header["layout"], noise_dims=header["dims"], dtype=header["dtype"],
                  tiles=tuple(parse_tile(i, tile, tensors, header, keep) for i, (tile, keep)
                              in enumerate(zip(tiles, kept_unpacked(areas, header)))),
                  extra=extra if isinstance(extra, dict) else {}, coefficients=header["coefficients"],
                  payload=None if meta.get("payload") is None else checked_payload(meta["payload"]))


def kept_unpacked(areas: np.ndarray, header: dict) -> np.ndarray:
    """Which compact tiles of these areas (pixels) load_bundle keeps unpacked: the first, in order, whose
    coefficients fit in KEPT_UNPACKED_BYTES together. (tiles,) bool; all False for the other layouts."""
    if header["layout"] != "compact":
        return np.zeros(len(areas), dtype=bool)
    per_pixel = header["coefficients"] * np.dtype(DTYPES[header["dtype"]]).itemsize
    return np.cumsum(areas) * per_pixel <= KEPT_UNPACKED_BYTES


def checked_rect(i: int, data) -> tuple[int, int, int, int]:
    """A tile's rectangle (x0, y0, width, height) from its metadata object."""
    if not isinstance(data, dict):
        raise UserError(f"bundle: tile {i} must be a JSON object")
    rect = checked_list(data.get("rect"), f"bundle: tile {i} rect", length=4)
    x0, y0 = (checked_int(v, f"bundle: tile {i} rect origin", 0, MAX_IMAGE_SIDE) for v in rect[:2])
    return (x0, y0, *checked_image_size(rect[2], rect[3], f"bundle: tile {i} rect"))


def bundle_bytes(source: str | Path | bytes) -> tuple[bytes, str]:
    """A bundle's bytes and the name its refusals give it: a path's contents, or the bytes themselves."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), "the bundle"
    path = Path(source)
    if not path.is_file():
        raise UserError(f"bundle not found: {path}")
    try:
        return path.read_bytes(), str(path)
    except OSError as error:
        raise os_failure("read bundle", path, error) from None


def load_bundle(source: str | Path | bytes) -> Bundle:
    """Read and validate a bundle (a path, or its bytes); anything malformed is one UserError."""
    return parse_bundle_bytes(*bundle_bytes(source))


def parse_bundle_bytes(data: bytes, name: str) -> Bundle:
    """A bundle from its bytes, validated; refusals name it `name` (its path)."""
    header, _ = split_safetensors(data, name)
    raw = header.get("__metadata__", {}).get(METADATA_KEY)
    if not isinstance(raw, str):
        raise UserError(f"not a noisenerf bundle (no '{METADATA_KEY}' metadata): {name}")
    meta = parse_json(raw, "bundle metadata", name)
    bundle = parse_bundle(meta, read_tensors(header, data, name), Path(name))
    validate(bundle)
    return bundle
