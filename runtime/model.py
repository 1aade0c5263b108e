"""The model file a recipient holds: the ONNX field plus the metadata that says how to render it.

    metadata_props
      noisenerf_format_version   "1"
      noisenerf                  JSON: format_version, fingerprint, field (architecture, noise_dims),
                                 render (RenderConfig), cameras, grid (aabb, resolution, occupancy bits:
                                 np.packbits of the C-order cube, base64)

The export writes this metadata (noisenerf.export.onnx_export) and this module reads it back, both
through ModelMetadata, so the two sides cannot drift apart.
"""

from __future__ import annotations

import base64
import binascii
import json
import os
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.bundle import Bundle
from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import parse_json
from noisenerf.runtime.limits import (
    MAX_CAMERAS, MAX_GRID_RESOLUTION, MAX_NOISE_DIMS, checked_float, checked_int, checked_list,
)
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import OccupancyGrid
from noisenerf.runtime.session import OnnxField

MODEL_FORMAT_VERSION = 1
METADATA_KEY = "noisenerf"
VERSION_KEY = "noisenerf_format_version"


def grid_to_dict(grid: OccupancyGrid) -> dict:
    """The occupancy cube as JSON: one bit per cell, C order, base64."""
    bits = np.packbits(grid.occupied.ravel())
    return {"aabb": [float(v) for v in grid.aabb], "resolution": grid.resolution,
            "occupancy": base64.b64encode(bits.tobytes()).decode("ascii")}


def grid_from_dict(data) -> OccupancyGrid:
    """Inverse of grid_to_dict; the resolution is capped and the bit string must have exactly its length,
    so the unpacked cube is never more than 8x the metadata that carried it."""
    if not isinstance(data, dict) or not isinstance(data.get("occupancy"), str):
        raise UserError("grid must be an object with aabb, resolution and occupancy")
    resolution = checked_int(data.get("resolution"), "grid resolution", 1, MAX_GRID_RESOLUTION)
    aabb = [checked_float(v, "grid aabb", -1e9, 1e9) for v in checked_list(data.get("aabb"), "grid aabb", length=6)]
    if not all(lo < hi for lo, hi in zip(aabb[:3], aabb[3:])):
        raise UserError(f"grid aabb must have min < max on every axis, got {aabb}")
    packed = np.frombuffer(base64.b64decode(data["occupancy"], validate=True), dtype=np.uint8)
    n_cells = resolution ** 3
    if packed.size != (n_cells + 7) // 8:
        raise ValueError(f"occupancy holds {packed.size} bytes, a {resolution}^3 grid needs {(n_cells + 7) // 8}")
    occupied = np.unpackbits(packed, count=n_cells).astype(bool).reshape((resolution,) * 3)
    return OccupancyGrid(aabb, occupied)


@dataclass(frozen=True, eq=False)
class ModelMetadata:
    """Everything a model file says about its field besides the graph itself."""

    fingerprint: str
    field: dict  # the architecture (FieldConfig as a dict); informative, the graph is authoritative
    noise_dims: int
    render_config: RenderConfig
    cameras: tuple[Camera, ...]
    grid: OccupancyGrid

    def to_dict(self) -> dict:
        return {"format_version": MODEL_FORMAT_VERSION, "fingerprint": self.fingerprint,
                "field": {**self.field, "noise_dims": self.noise_dims}, "render": self.render_config.to_dict(),
                "cameras": [camera.to_dict() for camera in self.cameras], "grid": grid_to_dict(self.grid)}

    def metadata_props(self) -> dict[str, str]:
        """The key/value strings stored in the ONNX file."""
        return {VERSION_KEY: str(MODEL_FORMAT_VERSION), METADATA_KEY: json.dumps(self.to_dict(), sort_keys=True)}

    @staticmethod
    def from_metadata_props(props: dict[str, str], source: str) -> "ModelMetadata":
        """Parse and check a model's metadata_props; anything missing or malformed is one UserError."""
        if METADATA_KEY not in props or VERSION_KEY not in props:
            raise UserError(f"{source} is not a noisenerf model (no '{METADATA_KEY}' metadata)")
        if props[VERSION_KEY] != str(MODEL_FORMAT_VERSION):
            raise UserError(f"{source} has model format version {props[VERSION_KEY]!r}; "
                            f"this noisenerf reads version {MODEL_FORMAT_VERSION}")
        data = parse_json(props[METADATA_KEY], f"{source}: noisenerf metadata")
        try:
            if not isinstance(data, dict) or data["format_version"] != MODEL_FORMAT_VERSION:
                raise ValueError(f"format_version disagrees with {VERSION_KEY}")
            field = dict(data["field"])
            cameras = checked_list(data["cameras"], "cameras", most=MAX_CAMERAS)
            return ModelMetadata(
                fingerprint=str(data["fingerprint"]),
                field={k: v for k, v in field.items() if k != "noise_dims"},
                noise_dims=checked_int(field.get("noise_dims"), "noise_dims", 1, MAX_NOISE_DIMS),
                render_config=RenderConfig.from_dict(data["render"]),
                cameras=tuple(Camera.from_dict(camera) for camera in cameras),
                grid=grid_from_dict(data["grid"]),
            )
        except (KeyError, TypeError, ValueError, binascii.Error) as error:
            raise UserError(f"{source}: malformed noisenerf metadata ({error!r})") from None
        except UserError as error:
            raise UserError(f"{source}: {error}") from None


@dataclass(frozen=True, eq=False)
class Model:
    """A loaded model: its metadata and the onnxruntime field."""

    metadata: ModelMetadata
    field: OnnxField

    @property
    def fingerprint(self) -> str:
        return self.metadata.fingerprint

    @property
    def render_config(self) -> RenderConfig:
        return self.metadata.render_config

    @property
    def grid(self) -> OccupancyGrid:
        return self.metadata.grid

    @property
    def cameras(self) -> tuple[Camera, ...]:
        return self.metadata.cameras

    @property
    def noise_dims(self) -> int:
        return self.metadata.noise_dims

    def camera(self, view: int) -> Camera:
        """The dataset camera of a view index, refusing one out of range."""
        if not 0 <= view < len(self.cameras):
            raise UserError(f"view {view} is out of range: this model has {len(self.cameras)} cameras "
                            f"(0..{len(self.cameras) - 1})")
        return self.cameras[view]


def load_model(path: str | os.PathLike, device: str = "cpu", threads: int | None = None) -> Model:
    """Load a model file for rendering; refuses non-ONNX, truncated, external-data or foreign files."""
    field = OnnxField(path, device=device, threads=threads)
    metadata = ModelMetadata.from_metadata_props(field.metadata(), field.source)
    if metadata.noise_dims != field.noise_dims:
        raise UserError(f"{field.source}: metadata says {metadata.noise_dims} noise dims, "
                        f"the graph takes {field.noise_dims}")
    return Model(metadata, field)


def short_fingerprint(fingerprint: str) -> str:
    return f"{fingerprint[:12]}…"


def check_bundle(model: Model, bundle: Bundle) -> None:
    """Refuse a bundle hidden in another model, or with noise the field cannot take."""
    if bundle.model_fingerprint != model.fingerprint:
        raise UserError(f"bundle was made for model {short_fingerprint(bundle.model_fingerprint)}, "
                        f"this model is {short_fingerprint(model.fingerprint)}")
    if bundle.noise_dims != model.noise_dims:
        raise UserError(f"bundle noise has {bundle.noise_dims} dims, this model takes {model.noise_dims}")
