"""The secret bundle: the key a recipient gets. safetensors (never pickle): noise tensors + JSON metadata.

    tensors   tile_0000, tile_0001, …   noise per tile, in one of three layouts (runtime/layouts.py): "ray"
              and "sample" store float noise under tile_NNNN; "compact" (format 2 on, the exact method's default)
              stores tile_NNNN, the xz stream of its coefficients, with tile_NNNN_basis, _offset, _escapes,
              _escape_noise (and from format 3 _branch_escapes, _branch_escape_noise), and the tile's "scale"
              in the metadata.
    metadata  {"noisenerf_bundle": JSON}: format version, model fingerprint, secret size and the SHA-256
              of its 8-bit RGB pixels, noise layout and dtype, per tile its rectangle in the final image,
              camera, sampling and network ("coarse" or "fine": the network the noise was trained
              through; a tile without it, as bundles made before the field existed, means the scene's
              render network, the fine one where there is one), and for a payload (a file, or a sealed
              secret) the optional "payload" object, the payload marker that runtime.payload defines and validates.

Versions: noisenerf writes format 5 and reads formats 1 to 5. Format 5 is format 4 with every tensor masked
with the model (runtime.masking: the metadata's "mask" object; without the model the tensors are random bytes);
a format 4 bundle is what a format 5 one is unmasked, and reveals as it always did. Format 1 (every bundle written before the
compact layout) holds only the ray and sample layouts, which formats 2 to 4 keep unchanged, so it reveals
as it always did; format 3's compact tiles add branch escapes (tile_NNNN_branch_escapes and
_branch_escape_noise), which a format 2 tile has none of; format 4's store their coefficients as differences
from an interlaced prediction (codec "xz-interlaced-residuals", runtime/interlaced.py) where formats 2 and 3
store them as they are ("xz-byte-planes"). A format this version does not know (a newer
writer's) is refused in one line naming it.

The bundle holds noise and metadata only: without the model's exact weights it renders nothing, and from
format 5 its noise reads as random bytes.

Checks, in this order (web/src/bundle.js keeps the same, so both refuse any input with the same code and params):

  1. the file: a path that is no regular file (bundle.not_found), one that cannot be read (bundle.read_failed);
  2. framing, from the first 8 bytes and the size alone (checked_framing): the header length they state is
     0 < n <= min(MAX_HEADER_BYTES, size - 8) (bundle.not_safetensors). A file of zeros or random bytes is refused
     here whatever its size, and a path's file before the rest of it is read (bundle_bytes);
  3. the header (runtime/sealing.split_safetensors): UTF-8 JSON as parse_json reads it, an object, its
     "__metadata__" (where present) an object (bundle.not_safetensors);
  4. "__metadata__"["noisenerf_bundle"] a string (bundle.not_noisenerf);
  5. that string parsed as JSON (json.invalid, json.too_deep);
  6. every tensor's dtype, in the header's order, one of SAFETENSORS_DTYPES (bundle.tensor_dtype);
  7. the safetensors structure, as the safetensors library checks it (bundle.not_safetensors): JSON it reads (no
     NaN, Infinity or out-of-range numbers, no lone surrogates, no byte order mark), "__metadata__"'s values
     strings, each tensor's shape and data_offsets whole numbers, the offsets tiling the data exactly, each the size
     its shape states;
  7½. where the metadata states a mask (read_bundle_file): the mask object (mask.malformed); then (BundleFile.bundle)
     the model's mask secret given (bundle.masked: a reveal opens the model first, and refuses a model other than
     the one the bundle names before unmasking), the tensors unmasked;
  8. the metadata (parse_bundle): an object, format_version (format 5 masked, earlier ones not: bundle.mask_format), the secret and noise objects, the secret's size, the
     noise header (layout, dims, dtype as text, the layout's own: compact's coefficients and codec, then the dtype
     one of the layout's), tiles a list, every tile's rect,
     the layout's streams against what they state (compact: the areas, then the expansion ratio),
     model_fingerprint, the digest; then tile by tile: rect, tensor name, the layout's tensors (compact:
     [branch escapes, branch escape noise,] basis, offset, scale, escapes, escape noise, band rows, the stream
     tensor, its decoding: corrupt (compact.xz_corrupt), or not exactly one xz stream holding the stated bytes with
     nothing after it (compact.xz_size)), camera, sampling, view, network; then the payload;
  9. the whole (validate): empty, tile by tile (network, inside the secret, camera, samples, noise shape and
     dtype, the layout's noise checks), the areas, overlaps.

A sealed bundle's tag is checked after these (runtime/api.py), before the model is read; for a masked bundle,
after check 7½'s mask object and before its model is read and its tensors unmasked.
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors import SafetensorError
from safetensors.numpy import load, save

from noisenerf import __version__
from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import os_failure, parse_json, write_bytes
from noisenerf.runtime.layouts import DTYPES, LAYOUTS, TileNoise, layout_named
from noisenerf.runtime.limits import (MAX_CAMERAS, MAX_HEADER_BYTES, MAX_IMAGE_SIDE, MAX_NOISE_DIMS, MAX_TILES,
                                      checked_image_size, checked_int, checked_list, is_finite)
from noisenerf.runtime.networks import NETWORKS
from noisenerf.runtime.masking import checked_mask, mask_key, mask_metadata, xor_masked
from noisenerf.runtime.payload import checked_marker
from noisenerf.runtime.sealing import split_safetensors
from noisenerf.runtime.sampling import SamplingConfig

BUNDLE_FORMAT_VERSION = 5
MASKED_FROM = 5  # the format from which every tensor is masked with the model (runtime.masking)
METADATA_KEY = "noisenerf_bundle"
# format -> the layouts it may hold (format 3: compact tiles add branch escapes; format 4: their coefficients are
# stored as interlaced differences; runtime/layouts.py; format 5: format 4 masked)
READABLE_FORMATS = {1: ("ray", "sample"), 2: ("ray", "sample", "compact"), 3: ("ray", "sample", "compact"),
                    4: ("ray", "sample", "compact"), 5: ("ray", "sample", "compact")}
SAFETENSORS_DTYPES = ("F16", "F32", "U8", "I32")  # float noise, bases and offsets, compressed coefficients, escapes
def secret_digest(pixels: np.ndarray) -> str:
    """SHA-256 of an 8-bit RGB image's bytes, (height, width, 3) uint8 row-major."""
    pixels = np.ascontiguousarray(pixels)
    if pixels.dtype != np.uint8 or pixels.ndim != 3 or pixels.shape[2] != 3:
        raise ValueError(f"secret digest needs (h, w, 3) uint8 pixels, got {pixels.dtype} {pixels.shape}")
    return hashlib.sha256(pixels.data).hexdigest()  # the buffer itself: no copy of a big secret


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
    payload_marker: dict | None = None  # runtime.payload's marker of a file or sealed payload; None: an image
    coefficients: int | None = None  # compact layout: k per pixel
    mask_salt: bytes | None = None  # format 5's (runtime.masking); None: written as format 4, unmasked

    def metadata(self) -> dict:
        layout = LAYOUTS[self.layout]
        return {
            "format_version": MASKED_FROM - 1 if self.mask_salt is None else BUNDLE_FORMAT_VERSION,
            "model_fingerprint": self.model_fingerprint,
            "secret": {"width": self.width, "height": self.height, "sha256": self.secret_sha256},
            "noise": {"layout": self.layout, "dims": self.noise_dims, "dtype": self.dtype,
                      **layout.header(self.coefficients)},
            "tiles": [{**tile.metadata(f"tile_{i:04d}"), **layout.tile_metadata(tile.noise)}
                      for i, tile in enumerate(self.tiles)],
            "extra": self.extra,
            **({"payload": self.payload_marker} if self.payload_marker is not None else {}),
            **({"mask": mask_metadata(self.mask_salt)} if self.mask_salt is not None else {}),
        }

    def to_bytes(self, mask_secret: bytes | None = None) -> bytes:
        """Validated, the safetensors file's bytes; a bundle with a mask salt is masked with `mask_secret`, its
        model's (runtime.fingerprint.weights_digests)."""
        validate(self)
        tensors = {name: value for i, tile in enumerate(self.tiles)
                   for name, value in tile.noise.tensors(f"tile_{i:04d}").items()}
        if self.mask_salt is not None:
            if mask_secret is None:
                raise ValueError("a masked bundle is written with its model's mask secret")
            tensors = xor_masked(tensors, mask_key(mask_secret, self.mask_salt))
        return save(tensors, metadata={METADATA_KEY: json.dumps(self.metadata(), sort_keys=True)})

    def save(self, path: str | Path, replace: bool = False, mask_secret: bytes | None = None) -> None:
        """Validate, then write atomically (replace: whether an existing file may be replaced, --force)."""
        write_bytes(path, self.to_bytes(mask_secret), replace=replace)


def expected_noise_shape(tile: Tile, bundle: "Bundle") -> tuple[int, ...]:
    per_vector = bundle.noise_dims if bundle.coefficients is None else bundle.coefficients
    return LAYOUTS[bundle.layout].stored_shape(tile.rect[3], tile.rect[2], tile.sampling.n_samples, per_vector)


def validate_tile(i: int, tile: Tile, bundle: Bundle) -> None:
    """One tile against the secret's size and the bundle's noise layout. Where one stored vector serves every
    sample of its ray, n_samples is capped (NoiseLayout.max_samples): the render's work stays tied to the noise
    the bundle actually holds."""
    layout = LAYOUTS[bundle.layout]
    x0, y0, w, h = tile.rect
    if tile.network is not None and tile.network not in NETWORKS:
        raise UserError(f"bundle: tile {i} names network {tile.network!r:.40} (expected one of {NETWORKS})",
                        code="bundle.tile_network", tile=i, network=tile.network[:60], expected=list(NETWORKS))
    if w < 1 or h < 1 or x0 < 0 or y0 < 0 or x0 + w > bundle.width or y0 + h > bundle.height:
        raise UserError(f"bundle: tile {i} rectangle {tile.rect} lies outside the "
                        f"{bundle.width}x{bundle.height} image", code="bundle.tile_outside", tile=i, rect=tile.rect,
                        width=bundle.width, height=bundle.height)
    if (tile.camera.width, tile.camera.height) != (w, h):
        raise UserError(f"bundle: tile {i} camera is {tile.camera.width}x{tile.camera.height}, "
                        f"its rectangle {w}x{h}", code="bundle.tile_camera", tile=i,
                        camera=[tile.camera.width, tile.camera.height], size=[w, h])
    if tile.sampling.n_samples > layout.max_samples:
        raise UserError(f"bundle: tile {i} asks for {tile.sampling.n_samples} samples per ray; the {bundle.layout} "
                        f"layout allows at most {layout.max_samples}", code="bundle.tile_samples", tile=i,
                        samples=tile.sampling.n_samples, layout=bundle.layout, most=layout.max_samples)
    kind = layout.noise_type
    if not isinstance(tile.noise, kind):
        raise UserError(f"bundle: tile {i} noise is {type(tile.noise).__name__}; the {bundle.layout} layout "
                        f"stores {kind.__name__}", code="bundle.tile_noise_type", tile=i, layout=bundle.layout)
    shape, noise = expected_noise_shape(tile, bundle), tile.noise
    if noise.shape != shape or noise.dtype != DTYPES[bundle.dtype]:
        raise UserError(f"bundle: tile {i} noise is {noise.dtype} {noise.shape}, "
                        f"expected {bundle.dtype} {shape}", code="bundle.tile_noise_shape", tile=i,
                        dtype=str(noise.dtype), shape=noise.shape, expected_dtype=bundle.dtype, expected_shape=shape)
    layout.check_noise(i, noise, w * h, bundle.noise_dims, bundle.coefficients)


def validate_noise_header(layout: str, dtype: str, dims: int, coefficients: int | None) -> None:
    """A bundle's noise description as it would be written must read back (noise_header) as itself."""
    written = {"layout": layout, "dims": dims, "dtype": dtype,
               **(LAYOUTS[layout].header(coefficients) if layout in LAYOUTS else {})}
    if noise_header(written, tuple(LAYOUTS), BUNDLE_FORMAT_VERSION)["coefficients"] != coefficients:
        raise UserError("bundle: coefficients per pixel are given for, and only for, the compact layout",
                        code="bundle.coefficients_layout", layout=layout)


def validate(bundle: Bundle) -> None:
    """Refuse anything a reveal could not render faithfully, with one clear message. Sizes are checked
    against the tiles' noise before the coverage mask is built, so the mask is never larger than the
    noise the bundle holds."""
    validate_noise_header(bundle.layout, bundle.dtype, bundle.noise_dims, bundle.coefficients)
    if bundle.width < 1 or bundle.height < 1 or not bundle.tiles:
        raise UserError(f"bundle: empty secret ({bundle.width}x{bundle.height}, {len(bundle.tiles)} tiles)",
                        code="bundle.empty", width=bundle.width, height=bundle.height, tiles=len(bundle.tiles))
    if len(bundle.tiles) > MAX_TILES:
        raise UserError(f"bundle: {len(bundle.tiles)} tiles, at most {MAX_TILES} allowed", code="bundle.too_many_tiles",
                        tiles=len(bundle.tiles), most=MAX_TILES)
    for i, tile in enumerate(bundle.tiles):
        validate_tile(i, tile, bundle)
    if sum(tile.rect[2] * tile.rect[3] for tile in bundle.tiles) != bundle.width * bundle.height:
        raise UserError(f"bundle: the tiles' areas do not add up to the {bundle.width}x{bundle.height} secret",
                        code="bundle.tile_areas", width=bundle.width, height=bundle.height)
    covered = np.zeros((bundle.height, bundle.width), dtype=np.uint8)
    for x0, y0, w, h in (tile.rect for tile in bundle.tiles):
        if covered[y0:y0 + h, x0:x0 + w].any():
            raise UserError("bundle: tile rectangles overlap", code="bundle.tiles_overlap")
        covered[y0:y0 + h, x0:x0 + w] = 1


def read_tensors(header: dict, data: bytes, source: str) -> dict[str, np.ndarray]:
    """Every tensor, refusing any dtype but SAFETENSORS_DTYPES (bfloat16 has no numpy type) before reading."""
    for name, info in header.items():
        dtype = info.get("dtype") if isinstance(info, dict) else None
        if name != "__metadata__" and dtype not in SAFETENSORS_DTYPES:
            raise UserError(f"bundle tensor {name!r:.60} is {dtype!r:.20}; noise is stored as "
                            f"{' or '.join(SAFETENSORS_DTYPES)}: {source}", code="bundle.tensor_dtype",
                            tensor=name[:60], dtype=dtype[:60] if isinstance(dtype, str) else None)
    try:
        return load(data)
    except (SafetensorError, ValueError, TypeError) as error:
        raise UserError(f"not a readable safetensors bundle: {source} ({error})",
                        code="bundle.not_safetensors") from None


def tile_tensor(tensors: dict[str, np.ndarray], name: str, tile: int, dtype=None,
                ndim: int | None = None) -> np.ndarray:
    """A named tensor of tile number `tile` that must exist (with this dtype and rank, when given)."""
    if name not in tensors:
        raise UserError(f"bundle: tile {tile} tensor {name!r:.60} is missing", code="bundle.tensor_missing", tile=tile,
                        tensor=name[:60])
    value = tensors[name]
    if (dtype is not None and value.dtype != dtype) or (ndim is not None and value.ndim != ndim):
        raise UserError(f"bundle: tile {tile} tensor {name!r:.60} is {value.dtype} {value.shape}",
                        code="bundle.tensor_shape", tile=tile, tensor=name[:60], dtype=str(value.dtype),
                        shape=value.shape)
    return value


def parse_tile(i: int, data, tensors: dict[str, np.ndarray], header: dict, keep_unpacked: bool) -> Tile:
    """One tile's metadata, every number type- and range-checked, joined to its tensors. header: the
    bundle's checked format, layout, dtype and coefficients; keep_unpacked: the layout's read_tile's."""
    x0, y0, width, height = checked_rect(i, data)
    name = data.get("tensor")
    if not isinstance(name, str):
        raise UserError(f"bundle: tile {i} tensor {name!r:.40} is missing", code="bundle.tile_no_tensor", tile=i)
    layout = LAYOUTS[header["layout"]]
    shape = (height, width, header["coefficients"])  # what a layout with coefficients stores per pixel
    noise = layout.read_tile(name, data, lambda key, **kind: tile_tensor(tensors, key, i, **kind), shape,
                             header["dtype"], i, keep_unpacked, header["format"])
    view = data.get("view")
    return Tile(rect=(x0, y0, width, height), camera=Camera.from_dict(data.get("camera")),
                sampling=SamplingConfig.from_dict(data.get("sampling")), noise=noise,
                view=None if view is None else checked_int(view, f"bundle: tile {i} view", 0, MAX_CAMERAS,
                                                           code="bundle.tile_view", tile=i),
                network=None if data.get("network") is None else checked_text(
                    data["network"], f"bundle: tile {i} network", "bundle.tile_network", tile=i))


def checked_text(value, what: str, code: str, **params) -> str:
    """A short JSON string (fingerprints, digests, names); code and params: its refusal's."""
    if not isinstance(value, str) or len(value) > 256:
        raise UserError(f"{what} must be a string of at most 256 characters", code=code, most=256, **params)
    return value


def checked_format(meta: dict, path: Path) -> int:
    """The bundle's format version, refusing one this noisenerf cannot read in a line that says which."""
    version = meta.get("format_version")
    if isinstance(version, bool) or not isinstance(version, (int, float)) or version not in READABLE_FORMATS:
        newest = max(READABLE_FORMATS)
        number = isinstance(version, (int, float)) and not isinstance(version, bool) and is_finite(version)
        raise UserError(f"{path} is bundle format {version!r:.20}; noisenerf {__version__} reads formats "
                        f"{min(READABLE_FORMATS)} to {newest}"
                        + ("; a newer noisenerf is needed" if isinstance(version, int) and version > newest else ""),
                        code="bundle.format", **({"format": version} if number else {}), oldest=min(READABLE_FORMATS),
                        newest=newest)
    return version


def noise_header(noise: dict, layouts: tuple[str, ...], version: int) -> dict:
    """The noise description of a bundle of format `version`, type- and range-checked. -> {layout, dims, dtype,
    coefficients}."""
    layout = layout_named(checked_text(noise.get("layout"), "bundle: noise layout", "bundle.noise_layout"), layouts)
    dims = checked_int(noise.get("dims"), "bundle: noise dims", 1, MAX_NOISE_DIMS, code="bundle.noise_dims")
    dtype = checked_text(noise.get("dtype"), "bundle: noise dtype", "bundle.noise_dtype")
    coefficients = layout.read_header(noise, dims, version)
    if dtype not in layout.dtypes:
        raise UserError(f"bundle: unknown noise dtype {dtype!r:.40} for the {layout.name} layout (expected one of "
                        f"{layout.dtypes})", code="bundle.noise_dtype", dtype=dtype[:60], layout=layout.name,
                        expected=list(layout.dtypes))
    return {"layout": layout.name, "dims": dims, "dtype": dtype, "coefficients": coefficients}


def parse_bundle(meta, tensors: dict[str, np.ndarray], path: Path, mask_salt: bytes | None = None) -> Bundle:
    """The metadata as a Bundle (its tensors unmasked where it was masked with `mask_salt`); nothing is converted by
    truncation (16.9 is not a size)."""
    if not isinstance(meta, dict):
        raise UserError(f"bundle metadata must be a JSON object: {path}", code="bundle.metadata_not_object")
    version = checked_format(meta, path)
    if (version >= MASKED_FROM) != (mask_salt is not None):
        raise UserError(f"bundle: format {version} bundles are {'' if version >= MASKED_FROM else 'not '}masked",
                        code="bundle.mask_format", format=version)
    secret, noise = meta.get("secret"), meta.get("noise")
    if not isinstance(secret, dict) or not isinstance(noise, dict):
        raise UserError("bundle: metadata needs 'secret' and 'noise' objects", code="bundle.no_secret_or_noise")
    width, height = checked_image_size(secret.get("width"), secret.get("height"), "bundle: secret",
                                       code="bundle.secret_size")
    header = {**noise_header(noise, READABLE_FORMATS[version], version), "format": version}
    tiles = checked_list(meta.get("tiles"), "bundle: tiles", most=MAX_TILES, code="bundle.tiles")
    areas = np.array([w * h for _, _, w, h in (checked_rect(i, tile) for i, tile in enumerate(tiles))], np.int64)
    layout = LAYOUTS[header["layout"]]
    layout.check_streams([tensors.get(tile.get("tensor")) if isinstance(tile.get("tensor"), str) else None
                          for tile in tiles], (width, height), int(areas.sum()), header["coefficients"],
                         header["dtype"])
    extra = meta.get("extra", {})
    return Bundle(model_fingerprint=checked_text(meta.get("model_fingerprint"), "bundle: model_fingerprint",
                                                 "bundle.model_fingerprint"),
                  width=width, height=height,
                  secret_sha256=checked_text(secret.get("sha256"), "bundle: sha256", "bundle.secret_sha256"),
                  layout=header["layout"], noise_dims=header["dims"], dtype=header["dtype"],
                  tiles=tuple(parse_tile(i, tile, tensors, header, keep) for i, (tile, keep) in
                              enumerate(zip(tiles, layout.kept_unpacked(areas, header["coefficients"],
                                                                        header["dtype"])))),
                  extra=extra if isinstance(extra, dict) else {}, coefficients=header["coefficients"],
                  payload_marker=payload_marker_of(meta), mask_salt=mask_salt)


def payload_marker_of(meta: dict) -> dict | None:
    """The metadata's payload marker, checked; None for an image."""
    return None if meta.get("payload") is None else checked_marker(meta["payload"])


def checked_rect(i: int, data) -> tuple[int, int, int, int]:
    """A tile's rectangle (x0, y0, width, height) from its metadata object."""
    if not isinstance(data, dict):
        raise UserError(f"bundle: tile {i} must be a JSON object", code="bundle.tile_not_object", tile=i)
    rect = checked_list(data.get("rect"), f"bundle: tile {i} rect", length=4, code="bundle.tile_rect", tile=i)
    x0, y0 = (checked_int(v, f"bundle: tile {i} rect origin", 0, MAX_IMAGE_SIDE, code="bundle.tile_rect", tile=i)
              for v in rect[:2])
    return (x0, y0, *checked_image_size(rect[2], rect[3], f"bundle: tile {i} rect", code="bundle.tile_rect", tile=i))


def checked_framing(data: bytes, size: int, name: str) -> int:
    """Check 2 (the module docstring) from a bundle's first 8 bytes and its size alone: the header length they state
    is positive, at most MAX_HEADER_BYTES and inside the file. A file of zeros or random bytes is refused here,
    whatever its size, before the rest of it is read. Where `data` holds the header too, it must be UTF-8 (check 3:
    json would read UTF-16 and UTF-32 too, safetensors and the browser read UTF-8 alone). -> the header length."""
    length = int.from_bytes(data[:8], "little") if len(data) >= 8 and size >= 8 else 0
    if not 0 < length <= min(size - 8, MAX_HEADER_BYTES) or (
            len(data) >= 8 + length and json.detect_encoding(data[8:8 + length]) not in ("utf-8", "utf-8-sig")):
        raise UserError(f"not a readable safetensors bundle: {name}", code="bundle.not_safetensors")
    return length


def bundle_bytes(source: str | Path | bytes) -> tuple[bytes, str]:
    """A bundle's bytes and the name its refusals give it: a path's contents, or the bytes themselves. A path's
    file is read in steps, its framing and header checked (checks 2 and 3) before its tensor data is read."""
    if isinstance(source, (bytes, bytearray, memoryview)):
        return bytes(source), "the bundle"
    path = Path(source)
    if not path.is_file():
        raise UserError(f"bundle not found: {path}", code="bundle.not_found")
    try:
        with path.open("rb") as file:
            size = os.fstat(file.fileno()).st_size
            prefix = file.read(8)
            prefix += file.read(checked_framing(prefix, size, str(path)))
            checked_framing(prefix, size, str(path))
            split_safetensors(prefix, str(path))
            return prefix + file.read(), str(path)
    except OSError as error:
        raise os_failure("read bundle", path, error, "bundle.read_failed") from None


@dataclass(frozen=True)
class BundleFile:
    """A bundle's file checked up to its tensors and its mask (checks 1 to 7½): what a reveal knows of a masked bundle
    before its model is open: the fingerprint it names, its payload marker (a sealed one's tag is checked on it)."""

    name: str
    meta: object  # the parsed metadata, checked from check 8 on by `bundle`
    tensors: dict[str, np.ndarray]  # as stored: masked where mask_salt is set
    mask_salt: bytes | None

    @property
    def model_fingerprint(self) -> str:
        meta = self.meta if isinstance(self.meta, dict) else {}
        return checked_text(meta.get("model_fingerprint"), "bundle: model_fingerprint", "bundle.model_fingerprint")

    @property
    def payload_marker(self) -> dict | None:
        return payload_marker_of(self.meta) if isinstance(self.meta, dict) else None

    def bundle(self, mask_secret: bytes | None = None) -> Bundle:
        """Checks 8 and 9, on the tensors unmasked with the model's mask secret where the bundle is masked."""
        tensors = self.tensors
        if self.mask_salt is not None:
            if mask_secret is None:
                raise UserError(f"{self.name}: this bundle is masked with its model; it reads only with the model",
                                code="bundle.masked")
            tensors = xor_masked(tensors, mask_key(mask_secret, self.mask_salt))
        bundle = parse_bundle(self.meta, tensors, Path(self.name), self.mask_salt)
        validate(bundle)
        return bundle


def read_bundle_file(data: bytes, name: str) -> BundleFile:
    """Checks 1 to 7½ of the module docstring on a bundle's bytes; refusals name it `name` (its path)."""
    checked_framing(data, len(data), name)
    header, _ = split_safetensors(data, name)
    raw = header.get("__metadata__", {}).get(METADATA_KEY)
    if not isinstance(raw, str):
        raise UserError(f"not a noisenerf bundle (no '{METADATA_KEY}' metadata): {name}", code="bundle.not_noisenerf")
    meta = parse_json(raw, "bundle metadata", name)
    tensors = read_tensors(header, data, name)
    masked = isinstance(meta, dict) and meta.get("mask") is not None
    return BundleFile(name, meta, tensors, checked_mask(meta["mask"]) if masked else None)


def load_bundle(source: str | Path | bytes, mask_secret: bytes | None = None) -> Bundle:
    """Read and validate a bundle (a path, or its bytes; a masked one with its model's mask secret); anything
    malformed is one UserError."""
    return parse_bundle_bytes(*bundle_bytes(source), mask_secret)


def parse_bundle_bytes(data: bytes, name: str, mask_secret: bytes | None = None) -> Bundle:
    """A bundle from its bytes, validated in the module docstring's order of checks; refusals name it `name`
    (its path)."""
    return read_bundle_file(data, name).bundle(mask_secret)
