"""Noise layouts: how a tile's noise is stored in a bundle and expanded into the vectors a render adds. Each
layout is a class that owns its name, storage dtypes, the stored array's shape, how many samples one stored
vector serves, its part of the bundle's metadata, and how a tile's tensors are read and checked; the noise
types (what a tile holds) live here too. runtime/bundle.py keeps the file format and asks the layout.

    ray      (h, w, dims) floats: one vector per ray, added at every one of its samples
    sample   (h, w, n_samples, dims) floats: one vector per sample (the paper's)
    compact  per pixel k integer coefficients of a per-tile basis, stored as an xz stream of byte planes
             (coefficient-major, then byte, then row-major pixels, little-endian: planes of like bytes compress
             best; from format 4 the planes hold each coefficient's zigzag difference from its interlaced
             prediction, runtime/interlaced.py) with the basis (dims, k), offset (dims,) and scale: noise =
             offset + (coefficients · scale) basisᵀ in float32; pixels the basis could not reach "escape":
             with their full float16 noise, or (format 3) as "branch escapes" with float16 values for the
             noise's trailing w dims alone (the direction segment the view branch takes), the leading ones
             being the offset's
"""

from __future__ import annotations

import dataclasses
import lzma
import zlib
from dataclasses import dataclass
from typing import Callable

import numpy as np

from noisenerf.runtime import interlaced
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import (MAX_COMPACT_COEFFICIENTS, MAX_RAY_LAYOUT_SAMPLES, MAX_SAMPLES_PER_RAY,
                                      MAX_XZ_MEMORY, checked_expansion, checked_float, checked_int)

DTYPES = {"float16": np.float16, "float32": np.float32, "int8": np.int8, "int16": np.int16}
XZ_PRESET = 6  # xz level of the coefficient planes (9 saved under 1 % more on photos, at twice the time)
PLANES_CODEC, INTERLACED_CODEC = "xz-byte-planes", "xz-interlaced-residuals"
INTERLACED_FROM = 4  # the bundle format from which compact tiles store interlaced differences (INTERLACED_CODEC)
# a compact bundle's coefficients, up to this many bytes unpacked, stay unpacked from the load's check to the render
# (one xz decode for ordinary secrets); beyond, tiles are unpacked again one at a time, so memory stays bounded
KEPT_UNPACKED_BYTES = 1 << 26
BRANCH_ESCAPES_FROM = 3  # the bundle format from which compact tiles store branch escapes
TensorGetter = Callable[..., np.ndarray]  # (name, dtype=None, ndim=None) -> a tile's tensor, or a UserError


def codec_of(version: int) -> str:
    """The coefficient codec a compact tile of bundle format `version` states and is read with."""
    return INTERLACED_CODEC if version >= INTERLACED_FROM else PLANES_CODEC


@dataclass(frozen=True)
class CompactBasis:
    """A compact tile's basis: a pixel's noise is offset + (coefficients · scale) basisᵀ."""

    basis: np.ndarray  # (dims, k) float32
    offset: np.ndarray  # (dims,) float32
    scale: float  # one integer step of a coefficient (a float32 value)
    escapes: np.ndarray  # (e,) int32, strictly increasing row-major pixel indices with full noise
    escape_noise: np.ndarray  # (e, dims) float16
    # (b,) int32, strictly increasing, none an escape: pixels whose noise is the offset but for its trailing w
    # values, branch_escape_noise (b, w) float16 (format 2: none, (0,) and (0, 0))
    branch_escapes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, np.int32))
    branch_escape_noise: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 0), np.float16))


def expand_coefficients(coefficients: np.ndarray, basis: CompactBasis, start: int = 0) -> np.ndarray:
    """Noise of compact pixels start.. start+m in float32, as the solver computed it
    (train/hide/exact.NoiseSpace.expand: one float32 multiply by the scale, then the matmul), with the
    escaped pixels' stored noise. coefficients: (m, k) int -> (m, dims) float32."""
    params = coefficients.astype(np.float32) * np.float32(basis.scale)
    noise = basis.offset + params @ basis.basis.T
    stop = start + len(coefficients)
    first, last = np.searchsorted(basis.escapes, [start, stop])
    noise[basis.escapes[first:last] - start] = basis.escape_noise[first:last]
    first, last = np.searchsorted(basis.branch_escapes, [start, stop])
    rows, lead = basis.branch_escapes[first:last] - start, noise.shape[1] - basis.branch_escape_noise.shape[1]
    noise[rows, :lead] = basis.offset[:lead]
    noise[rows, lead:] = basis.branch_escape_noise[first:last]
    return noise


def pack_coefficients(coefficients: np.ndarray) -> np.ndarray:
    """The xz stream of (h, w, k) integer coefficients as byte planes (see the module docstring). -> (n,) uint8."""
    planes = np.ascontiguousarray(coefficients.astype(coefficients.dtype.newbyteorder("<")).transpose(2, 0, 1))
    split = planes.view(np.uint8).reshape(*planes.shape, -1).transpose(0, 3, 1, 2)
    return np.frombuffer(lzma.compress(np.ascontiguousarray(split).tobytes(), preset=XZ_PRESET), dtype=np.uint8)


XZ_MAGIC = b"\xfd7zXZ\x00"
XZ_CHECKS = (None, lzma.CHECK_NONE, lzma.CHECK_CRC32, lzma.CHECK_CRC64)  # what the browser's decoder (xz-embedded) checks


def stream_check(header: bytes) -> int | None:
    """The integrity check an xz stream's header states, None if these 12 bytes are no whole, intact stream header
    (the decoder refuses or waits for those itself). Streams stating a check the browser's decoder cannot verify
    (SHA-256, the reserved ones) are refused as corrupt, as it refuses them: noisenerf writes CRC64."""
    if len(header) < 12 or header[:6] != XZ_MAGIC or zlib.crc32(header[6:8]) != int.from_bytes(header[8:12], "little"):
        return None
    return header[7] if header[6] == 0 and header[7] < 16 else None


def unpack_coefficients(packed: np.ndarray, shape: tuple[int, int, int], dtype: str, what: str,
                        tile: int | None = None) -> np.ndarray:
    """pack_coefficients undone, refusing a stream that is corrupt or does not hold exactly shape's bytes
    (at most that many are ever decompressed, within MAX_XZ_MEMORY). tile: the tile's number, for the refusal.
    -> (h, w, k) of dtype."""
    kind = np.dtype(DTYPES[dtype]).newbyteorder("<")
    expected = int(np.prod(shape)) * kind.itemsize
    check = stream_check(packed[:12].tobytes())
    if check not in XZ_CHECKS:
        raise UserError(f"{what}: compressed coefficients are corrupt (integrity check {check} unsupported)",
                        code="compact.xz_corrupt", tile=tile)
    decompressor = lzma.LZMADecompressor(format=lzma.FORMAT_XZ, memlimit=MAX_XZ_MEMORY)
    try:
        data = decompressor.decompress(packed.tobytes(), max_length=expected + 1)
    except lzma.LZMAError as error:
        raise UserError(f"{what}: compressed coefficients are corrupt ({error})", code="compact.xz_corrupt",
                        tile=tile) from None
    if len(data) != expected or not decompressor.eof or decompressor.unused_data:
        raise UserError(f"{what}: compressed coefficients do not hold exactly {shape} {dtype} values",
                        code="compact.xz_size", tile=tile, shape=shape, dtype=dtype)
    height, width, k = shape
    split = np.frombuffer(data, dtype=np.uint8).reshape(k, kind.itemsize, height, width)
    planes = np.ascontiguousarray(split.transpose(0, 2, 3, 1)).view(kind)[..., 0]
    return planes.transpose(1, 2, 0).astype(DTYPES[dtype])


def unpacked_stream(packed: np.ndarray, shape: tuple[int, int, int], dtype: str, codec: str, band_rows: int | None,
                    what: str, tile: int | None = None) -> np.ndarray:
    """A compact tile's coefficients (h, w, k) from its stream, as `codec` stored them (interlaced: in bands of
    band_rows rows)."""
    planes = unpack_coefficients(packed, shape, dtype, what, tile)
    return interlaced.decode(planes, band_rows) if codec == INTERLACED_CODEC else planes


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
    codec: str = INTERLACED_CODEC  # what the stream holds: interlaced differences, or (formats 2, 3) the planes
    band_rows: int | None = None  # interlaced: rows per band, each coded on its own (runtime/interlaced.py)

    @staticmethod
    def of(coefficients: np.ndarray, basis: CompactBasis, band_rows: int) -> CompactNoise:
        """Coefficients (h, w, k) int16 or int8, packed as the newest format stores them, in bands of band_rows."""
        return CompactNoise(pack_coefficients(interlaced.encode(coefficients, band_rows)), coefficients.shape,
                            coefficients.dtype, basis, band_rows=band_rows)

    def coefficients(self) -> np.ndarray:
        """The unpacked coefficients (h, w, k)."""
        return unpacked_stream(self.packed, self.shape, self.dtype.name, self.codec, self.band_rows,
                               "bundle: compact tile")

    def loaded(self) -> CompactCoefficients:
        unpacked = self.coefficients() if self.unpacked is None else self.unpacked
        return CompactCoefficients(unpacked, self.basis)

    def tensors(self, name: str) -> dict[str, np.ndarray]:
        if self.codec != INTERLACED_CODEC:  # a bundle is written in the newest format only
            raise ValueError(f"a compact tile read as {self.codec} cannot be written as format {INTERLACED_FROM}")
        return {name: self.packed, f"{name}_basis": np.ascontiguousarray(self.basis.basis),
                f"{name}_offset": np.ascontiguousarray(self.basis.offset),
                f"{name}_escapes": np.ascontiguousarray(self.basis.escapes),
                f"{name}_escape_noise": np.ascontiguousarray(self.basis.escape_noise),
                f"{name}_branch_escapes": np.ascontiguousarray(self.basis.branch_escapes),
                f"{name}_branch_escape_noise": np.ascontiguousarray(self.basis.branch_escape_noise)}


TileNoise = VectorNoise | CompactNoise




@dataclass(frozen=True)
class NoiseLayout:
    """What every layout answers; the three below are the only ones."""

    name: str
    dtypes: tuple[str, ...]  # storage dtypes, the default first
    max_samples: int  # samples per ray a tile of this layout may render

    def vectors_per_ray(self, n_samples: int) -> int:
        """Stored noise vectors per ray of n_samples samples."""
        return 1

    def stored_shape(self, height: int, width: int, n_samples: int, per_vector: int) -> tuple[int, ...]:
        """A tile's stored noise array: (h, w, per_vector), a vector per ray (dims values, or k coefficients)."""
        return (height, width, per_vector)

    def coefficients_of(self, noise: TileNoise) -> int | None:
        """What the bundle header states per pixel besides dims: a compact tile's k, else None."""
        return None

    def header(self, coefficients: int | None) -> dict:
        """The layout's part of the bundle's noise metadata beyond layout, dims and dtype."""
        return {}

    def read_header(self, noise: dict, dims: int, version: int) -> int | None:
        """Its part of the noise metadata of a bundle of format `version`, checked -> coefficients per pixel
        (compact) or None."""
        if noise.get("coefficients") is not None:
            raise UserError("bundle: coefficients per pixel are given for, and only for, the compact layout",
                            code="bundle.coefficients_layout", layout=self.name)
        return None

    def tile_metadata(self, noise: TileNoise) -> dict:
        return {}

    def check_streams(self, streams: list, secret_size: tuple[int, int], tile_pixels: int, coefficients: int | None,
                      dtype: str) -> None:
        """Compressed streams against what they are stated to hold, before any is inflated (compact only: the
        others store raw noise). streams: each tile's tensor, where it names one."""

    def kept_unpacked(self, areas: np.ndarray, coefficients: int | None, dtype: str) -> np.ndarray:
        """Which tiles of these areas (pixels) load_bundle keeps unpacked. (tiles,) bool."""
        return np.zeros(len(areas), dtype=bool)

    def read_tile(self, name: str, data: dict, tensor: TensorGetter, shape: tuple[int, ...], dtype: str, tile: int,
                  keep_unpacked: bool, version: int) -> TileNoise:
        """Tile number `tile`'s noise from its tensors (`tensor` refuses a missing one), of a bundle of format
        `version`."""
        return VectorNoise(tensor(name))

    def check_noise(self, tile: int, noise: TileNoise, pixels: int, dims: int, coefficients: int | None) -> None:
        """Tile number `tile`'s noise beyond its shape and dtype: finite floats."""
        if not np.isfinite(noise.values).all():
            raise UserError(f"bundle: tile {tile} noise holds NaN or Inf", code="bundle.tile_noise_not_finite",
                            tile=tile)

    @property
    def noise_type(self) -> type:
        return VectorNoise

    @property
    def shares_basis(self) -> bool:
        """Whether a tile's pixels share a solved basis (a shared job before its parts)."""
        return False


class RayLayout(NoiseLayout):
    pass


class SampleLayout(NoiseLayout):
    def vectors_per_ray(self, n_samples: int) -> int:
        return n_samples

    def stored_shape(self, height: int, width: int, n_samples: int, per_vector: int) -> tuple[int, ...]:
        return (height, width, n_samples, per_vector)


class CompactLayout(NoiseLayout):
    def coefficients_of(self, noise: TileNoise) -> int:
        return noise.shape[-1]

    def header(self, coefficients: int | None) -> dict:
        return {"coefficients": coefficients, "codec": INTERLACED_CODEC}

    def read_header(self, noise: dict, dims: int, version: int) -> int:
        coefficients = checked_int(noise.get("coefficients"), "bundle: coefficients per pixel", 1,
                                   MAX_COMPACT_COEFFICIENTS, code="compact.coefficients")
        codec, expected = noise.get("codec"), codec_of(version)
        if codec != expected:
            raise UserError(f"bundle: unknown coefficient codec {codec!r:.40} (expected {expected!r})",
                            code="compact.codec", **({"codec": codec[:60]} if isinstance(codec, str) else {}),
                            expected=expected)
        if coefficients > min(dims, MAX_COMPACT_COEFFICIENTS):
            raise UserError(f"bundle: {coefficients} coefficients per pixel, expected 1 to "
                            f"{min(dims, MAX_COMPACT_COEFFICIENTS)}", code="compact.coefficients", value=coefficients,
                            low=1, high=min(dims, MAX_COMPACT_COEFFICIENTS))
        return coefficients

    def tile_metadata(self, noise: TileNoise) -> dict:
        return {"scale": noise.basis.scale, "band_rows": noise.band_rows}

    def check_streams(self, streams: list, secret_size: tuple[int, int], tile_pixels: int, coefficients: int | None,
                      dtype: str) -> None:
        width, height = secret_size
        if tile_pixels != width * height:
            raise UserError(f"bundle: the tiles' areas do not add up to the {width}x{height} secret",
                            code="bundle.tile_areas", width=width, height=height)
        checked_expansion(sum(stream.nbytes for stream in streams if stream is not None),
                          tile_pixels * coefficients * np.dtype(DTYPES[dtype]).itemsize, "bundle")

    def kept_unpacked(self, areas: np.ndarray, coefficients: int | None, dtype: str) -> np.ndarray:
        per_pixel = coefficients * np.dtype(DTYPES[dtype]).itemsize
        return np.cumsum(areas) * per_pixel <= KEPT_UNPACKED_BYTES

    def read_tile(self, name: str, data: dict, tensor: TensorGetter, shape: tuple[int, ...], dtype: str, tile: int,
                  keep_unpacked: bool, version: int) -> CompactNoise:
        """The coefficients (h, w, k) and the basis. The stream is decompressed here to check it holds exactly
        that (only once the header and rect are known good, so at most h·w·k values); the coefficients are
        kept if keep_unpacked, else dropped (a reveal unpacks the tile again when it renders). Branch escapes
        from format 3 on."""
        what = f"bundle: tile {tile}"
        branch = ({"branch_escapes": tensor(f"{name}_branch_escapes"),
                   "branch_escape_noise": tensor(f"{name}_branch_escape_noise")} if version >= BRANCH_ESCAPES_FROM
                  else {})
        basis = CompactBasis(basis=tensor(f"{name}_basis"), offset=tensor(f"{name}_offset"),
                             scale=checked_float(data.get("scale"), f"{what} scale",
                                                 low=float(np.finfo(np.float32).tiny),
                                                 high=float(np.finfo(np.float32).max), code="compact.scale",
                                                 tile=tile),
                             escapes=tensor(f"{name}_escapes"), escape_noise=tensor(f"{name}_escape_noise"), **branch)
        band_rows = (checked_int(data.get("band_rows"), f"{what} band rows", 1, shape[0], code="compact.band_rows",
                                 tile=tile) if codec_of(version) == INTERLACED_CODEC else None)
        packed = tensor(name, dtype=np.uint8, ndim=1)
        unpacked = unpacked_stream(packed, shape, dtype, codec_of(version), band_rows, what, tile)
        return CompactNoise(packed, shape, np.dtype(DTYPES[dtype]), basis, unpacked if keep_unpacked else None,
                            codec_of(version), band_rows)

    def check_noise(self, tile: int, noise: TileNoise, pixels: int, dims: int, coefficients: int | None) -> None:
        """The basis (dims, k), offset (dims,) float32, escape noise (e, dims) and branch escape noise (b, w),
        w ≤ dims, float16, all finite; the scale > 0; the escapes (e,) and branch escapes (b,) int32, each
        strictly increasing inside the tile, none in both (integers are finite by type)."""
        what = f"bundle: tile {tile}"
        basis = noise.basis
        escapes, branch_escapes = basis.escapes, basis.branch_escapes
        for name, indices in (("escapes", escapes), ("branch escapes", branch_escapes)):
            if indices.ndim != 1 or indices.dtype != np.int32:
                raise UserError(f"{what} {name} are {indices.dtype} {indices.shape}, expected int32 (e,)",
                                code="compact.escapes_type", tile=tile, part=name, dtype=str(indices.dtype),
                                shape=indices.shape)
            if len(indices) and (indices[0] < 0 or indices[-1] >= pixels or (np.diff(indices) <= 0).any()):
                raise UserError(f"{what} {name} must be strictly increasing pixel indices inside the tile",
                                code="compact.escapes_order", tile=tile, part=name)
        if np.intersect1d(escapes, branch_escapes).size:
            raise UserError(f"{what}: a pixel is both an escape and a branch escape", code="compact.escape_twice",
                            tile=tile)
        branch_width = basis.branch_escape_noise.shape[-1] if basis.branch_escape_noise.ndim == 2 else -1
        if not 0 <= branch_width <= dims:
            raise UserError(f"{what} branch escape noise is {basis.branch_escape_noise.shape}, expected (b, w), w ≤ "
                            f"{dims}", code="compact.branch_width", tile=tile, shape=basis.branch_escape_noise.shape,
                            dims=dims)
        for name, value, shape, dtype in (("basis", basis.basis, (dims, coefficients), np.float32),
                                          ("offset", basis.offset, (dims,), np.float32),
                                          ("escape noise", basis.escape_noise, (len(escapes), dims), np.float16),
                                          ("branch escape noise", basis.branch_escape_noise,
                                           (len(branch_escapes), branch_width), np.float16)):
            if value.shape != shape or value.dtype != dtype:
                raise UserError(f"{what} {name} is {value.dtype} {value.shape}, expected {np.dtype(dtype)} {shape}",
                                code="compact.tensor_shape", tile=tile, part=name, dtype=str(value.dtype),
                                shape=value.shape, expected_dtype=np.dtype(dtype).name, expected_shape=shape)
            if not np.isfinite(value).all():
                raise UserError(f"{what} {name} holds NaN or Inf", code="compact.not_finite", tile=tile, part=name)
        checked_float(basis.scale, f"{what} scale", low=np.finfo(np.float32).tiny,
                      high=float(np.finfo(np.float32).max), code="compact.scale", tile=tile)

    @property
    def noise_type(self) -> type:
        return CompactNoise

    @property
    def shares_basis(self) -> bool:
        return True


LAYOUTS = {layout.name: layout for layout in (
    RayLayout("ray", ("float16", "float32"), MAX_RAY_LAYOUT_SAMPLES),
    SampleLayout("sample", ("float32", "float16"), MAX_SAMPLES_PER_RAY),
    CompactLayout("compact", ("int16", "int8"), MAX_RAY_LAYOUT_SAMPLES),
)}


def layout_named(name: str, among: tuple[str, ...] = tuple(LAYOUTS)) -> NoiseLayout:
    """The layout of this name, refusing one not `among` those allowed (a bundle format's)."""
    if name not in among:
        raise UserError(f"bundle: unknown noise layout {name!r:.40} (expected one of {among})",
                        code="bundle.noise_layout", layout=name[:60], expected=list(among))
    return LAYOUTS[name]
