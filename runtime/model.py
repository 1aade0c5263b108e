"""The model file a recipient holds: the ONNX fields plus the metadata that says how to render them.

    metadata_props
      noisenerf_format_version   "2"
      noisenerf                  JSON: format_version, fingerprint, architecture ({"coarse": a field kind's
                                 architecture, "fine": … | null}), noise_dims, render (RenderConfig),
                                 hierarchy ({n_coarse, n_importance} | null: set iff there is a fine
                                 network), cameras, grid (aabb, resolution, occupancy bits: np.packbits
                                 of the C-order cube, base64)
    initializers                 the weights, named and laid out as in the scene directory
                                 (coarse.pts_linears.0.weight, ...; nn.Linear's (out, in))

The model is its weights and its graph: load_model rebuilds the graph the architecture exports and
refuses a model whose graph differs in any node, attribute, constant, port or opset (runtime.graph), then
recomputes the scene fingerprint from the initializers and the architecture and refuses a model whose
weights were changed after export, even if its metadata kept the original fingerprint (and with it, a
bundle's). Both happen before onnxruntime sees the bytes. Models exported before the graph was written
from runtime.graph (traced by torch) are refused with the re-export line; their bundles keep revealing
with a fresh export, being tied to the scene. Version 1 models named their weights otherwise and
are refused with a request to re-export; bundles are tied to the scene, so they keep revealing.

The export writes this metadata (noisenerf.export.onnx_export) and this module reads it back, both
through ModelMetadata, so the two sides cannot drift apart.
"""

from __future__ import annotations

import base64
import binascii
import dataclasses
import json
import os
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.bundle import Bundle
from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import parse_json
from noisenerf.runtime.fingerprint import weights_digests
from noisenerf.runtime.fields import field_graph, grid_sampler, proposal_sampler
from noisenerf.runtime.grid_marching import GridMarching, GridMarchingSampler
from noisenerf.runtime.graph import FieldGraph, check_graph
from noisenerf.runtime.limits import (
    MAX_CAMERAS, MAX_GRID_RESOLUTION, MAX_NOISE_DIMS, checked_float, checked_int, checked_list,
)
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.onnx_file import check_model_file
from noisenerf.runtime.pdf import Hierarchy
from noisenerf.runtime.proposal import ProposalSampler, ProposalSampling
from noisenerf.runtime.render import HierarchicalSampler, MarchingSampler, RenderConfig, Sampler
from noisenerf.runtime.session import OnnxField, read_model_file

MODEL_FORMAT_VERSION = 2
METADATA_KEY = "noisenerf"
VERSION_KEY = "noisenerf_format_version"


def grid_to_dict(grid: OccupancyGrid) -> dict:
    """The occupancy cube as JSON: one bit per cell, C order, base64."""
    bits = np.packbits(grid.occupied.ravel())
    return {"aabb": [float(v) for v in grid.aabb], "resolution": grid.resolution,
            "occupancy": base64.b64encode(bits.tobytes()).decode("ascii")}


def malformed(why: str, code: str, **params) -> ValueError:
    """A ValueError that ModelMetadata.from_metadata_props reports as malformed metadata (the message quotes its
    repr), carrying the code and params of that refusal."""
    error = ValueError(why)
    error.refusal = code, params
    return error


def grid_from_dict(data) -> OccupancyGrid:
    """Inverse of grid_to_dict; the resolution is capped and the bit string must have exactly its length,
    so the unpacked cube is never more than 8x the metadata that carried it."""
    if not isinstance(data, dict) or not isinstance(data.get("occupancy"), str):
        raise UserError("grid must be an object with aabb, resolution and occupancy", code="model.grid_malformed")
    resolution = checked_int(data.get("resolution"), "grid resolution", 1, MAX_GRID_RESOLUTION,
                             code="model.grid_resolution")
    aabb = [checked_float(v, "grid aabb", -1e9, 1e9, code="model.grid_aabb")
            for v in checked_list(data.get("aabb"), "grid aabb", length=6, code="model.grid_aabb")]
    if not all(lo < hi for lo, hi in zip(aabb[:3], aabb[3:])):
        raise UserError(f"grid aabb must have min < max on every axis, got {aabb}", code="model.grid_aabb_order",
                        aabb=aabb)
    packed = np.frombuffer(base64.b64decode(data["occupancy"], validate=True), dtype=np.uint8)
    n_cells = resolution ** 3
    if packed.size != (n_cells + 7) // 8:
        raise malformed(f"occupancy holds {packed.size} bytes, a {resolution}^3 grid needs {(n_cells + 7) // 8}",
                        "model.occupancy_size", bytes=packed.size, resolution=resolution, needed=(n_cells + 7) // 8)
    occupied = np.unpackbits(packed, count=n_cells).astype(bool).reshape((resolution,) * 3)
    return OccupancyGrid(aabb, occupied)


@dataclass(frozen=True, eq=False)
class ModelMetadata:
    """Everything a model file says about its fields besides the graph and weights."""

    fingerprint: str
    architecture: dict  # {"coarse": architecture, "fine": architecture | None} (runtime.fields): in the fingerprint
    noise_dims: int
    render_config: RenderConfig
    hierarchy: Hierarchy | None  # set iff the scene has a fine network
    cameras: tuple[Camera, ...]
    grid: OccupancyGrid

    def to_dict(self) -> dict:
        return {"format_version": MODEL_FORMAT_VERSION, "fingerprint": self.fingerprint,
                "architecture": self.architecture, "noise_dims": self.noise_dims,
                "render": self.render_config.to_dict(),
                "hierarchy": dataclasses.asdict(self.hierarchy) if self.hierarchy else None,
                "cameras": [camera.to_dict() for camera in self.cameras], "grid": grid_to_dict(self.grid)}

    def metadata_props(self) -> dict[str, str]:
        """The key/value strings stored in the ONNX file."""
        return {VERSION_KEY: str(MODEL_FORMAT_VERSION), METADATA_KEY: json.dumps(self.to_dict(), sort_keys=True)}

    @staticmethod
    def from_metadata_props(props: dict[str, str], source: str) -> "ModelMetadata":
        """Parse and check a model's metadata_props; anything missing or malformed is one UserError."""
        if METADATA_KEY not in props or VERSION_KEY not in props:
            raise UserError(f"{source} is not a noisenerf model (no '{METADATA_KEY}' metadata)",
                            code="model.not_noisenerf")
        if props[VERSION_KEY] != str(MODEL_FORMAT_VERSION):
            raise UserError(f"{source} has model format version {props[VERSION_KEY]!r}; this noisenerf reads "
                            f"version {MODEL_FORMAT_VERSION} (export the scene again with `noisenerf export`)",
                            code="model.format_version", version=props[VERSION_KEY][:60])
        data = parse_json(props[METADATA_KEY], f"{source}: noisenerf metadata")
        try:
            if not isinstance(data, dict) or data["format_version"] != MODEL_FORMAT_VERSION:
                raise malformed(f"format_version disagrees with {VERSION_KEY}", "model.metadata_version")
            architecture = {"coarse": dict(data["architecture"]["coarse"]), "fine": data["architecture"]["fine"]}
            hierarchy = Hierarchy(**data["hierarchy"]) if data["hierarchy"] is not None else None
            if (architecture["fine"] is None) != (hierarchy is None):
                raise malformed("a fine network and hierarchical sampling go together", "model.fine_hierarchy")
            cameras = checked_list(data["cameras"], "cameras", most=MAX_CAMERAS, code="model.cameras")
            return ModelMetadata(
                fingerprint=str(data["fingerprint"]),
                architecture=architecture,
                noise_dims=checked_int(data["noise_dims"], "noise_dims", 1, MAX_NOISE_DIMS,
                                       code="model.noise_dims_range"),
                render_config=RenderConfig.from_dict(data["render"]),
                hierarchy=hierarchy,
                cameras=tuple(Camera.from_dict(camera) for camera in cameras),
                grid=grid_from_dict(data["grid"]),
            )
        except (KeyError, TypeError, ValueError, binascii.Error) as error:
            code, params = getattr(error, "refusal", ("model.metadata_malformed", {}))
            raise UserError(f"{source}: malformed noisenerf metadata ({error!r})", code=code, **params) from None
        except UserError as error:
            raise error.reworded(f"{source}: {error}") from None


@dataclass(frozen=True, eq=False)
class Model:
    """A loaded model: its metadata, the onnxruntime field (the render network), and the mask secret its weights give
    (runtime.fingerprint.weights_digests: what unmasks its bundles)."""

    metadata: ModelMetadata
    field: OnnxField
    mask_secret: bytes

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

    def fields(self) -> dict[str, OnnxField]:
        """Network name ("coarse", and "fine" where the scene has one) -> its field."""
        return {name: self.field.network(name) for name in self.field.networks}

    def sampler(self, skip: bool = True) -> Sampler:
        """How an ordinary render places its samples: nerfacto's proposal sampler where the render network's
        kind has one, nerfacc's grid marcher for nerfstudio's instant-ngp, nerf-pytorch's hierarchy beside a fine
        network, else uniform samples through the grid (skipping empty space when `skip`)."""
        proposals = proposal_sampler(self.metadata.architecture)
        if proposals is not None:
            return ProposalSampler(ProposalSampling.from_architecture(proposals),
                                   tuple(self.field.proposal_density(i)
                                         for i in range(len(proposals["proposal_samples"]))))
        marching = grid_sampler(self.metadata.architecture)
        if marching is not None:
            return GridMarchingSampler(GridMarching.from_architecture(marching))
        if self.metadata.hierarchy is not None:
            return HierarchicalSampler(self.render_config, self.field.network("coarse"), self.metadata.hierarchy)
        return MarchingSampler(self.render_config, self.grid, skip)

    def camera(self, view: int) -> Camera:
        """The dataset camera of a view index, refusing one out of range."""
        if not 0 <= view < len(self.cameras):
            raise UserError(f"view {view} is out of range: this model has {len(self.cameras)} cameras "
                            f"(0..{len(self.cameras) - 1})", code="model.view_out_of_range", view=view,
                            cameras=len(self.cameras))
        return self.cameras[view]


def check_weights(weights: dict[str, np.ndarray], metadata: ModelMetadata, source: str) -> bytes:
    """Refuse a model whose initializers and architecture do not hash to its metadata's fingerprint. -> the mask
    secret they give."""
    digests = weights_digests(weights, metadata.architecture)
    if digests.fingerprint != metadata.fingerprint:
        raise UserError(f"{source}: its weights do not match its fingerprint {short_fingerprint(metadata.fingerprint)} "
                        "(the model was changed after export); export the scene again", code="model.weights_changed")
    return digests.mask_secret


def load_model(path: str | os.PathLike, device: str = "cpu", threads: int | None = None) -> Model:
    """Load a model file for rendering; refuses non-ONNX, truncated, external-data, foreign or modified
    files (external data and weights are checked before onnxruntime sees the bytes). A path's file has its framing
    checked before it is read whole (runtime.onnx_file: a file of junk is refused whatever its size)."""
    if not isinstance(path, (bytes, bytearray, memoryview)):
        check_model_file(path)
    file = read_model_file(path)
    metadata = ModelMetadata.from_metadata_props(file.metadata_props, file.source)
    mask_secret = check_weights(check_graph(file, expected_graph(metadata, file.source), file.source), metadata,
                                file.source)
    # the graph check above has made the ports, and so the noise width and the fine network, the metadata's
    return Model(metadata, OnnxField(file, device=device, threads=threads), mask_secret)


def expected_graph(metadata: ModelMetadata, source: str) -> FieldGraph:
    """The graph a model with this metadata's architecture exports (runtime.graph), or a UserError naming
    the model when the architecture is out of the caps."""
    try:
        return field_graph(metadata.architecture, metadata.noise_dims)
    except UserError as error:
        raise error.reworded(f"{source}: {error}") from None


def short_fingerprint(fingerprint: str) -> str:
    return f"{fingerprint[:12]}…"


def check_fingerprint(model: Model, fingerprint: str) -> None:
    """Refuse a bundle hidden in another model: one naming another `fingerprint`."""
    if fingerprint != model.fingerprint:
        raise UserError(f"bundle was made for model {short_fingerprint(fingerprint)}, "
                        f"this model is {short_fingerprint(model.fingerprint)}", code="model.other_model",
                        bundle=fingerprint[:12], model=model.fingerprint[:12])


def check_bundle(model: Model, bundle: Bundle) -> None:
    """Refuse a bundle hidden in another model, or with noise the field cannot take."""
    check_fingerprint(model, bundle.model_fingerprint)
    if bundle.noise_dims != model.noise_dims:
        raise UserError(f"bundle noise has {bundle.noise_dims} dims, this model takes {model.noise_dims}",
                        code="model.noise_dims", bundle=bundle.noise_dims, model=model.noise_dims)
