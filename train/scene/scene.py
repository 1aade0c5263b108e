"""A scene directory: the frozen NeRF's weights (safetensors), its JSON config and occupancy grid.

    SCENE_DIR/scene.json              SceneConfig + fingerprint
    SCENE_DIR/weights.safetensors     coarse.* and fine.* parameters (nerf-pytorch module names)
    SCENE_DIR/occupancy.safetensors   the binary occupancy grid used for empty-space skipping

The fingerprint is SHA-256 over every weight (name, dtype, shape, bytes; names sorted) and the
architecture config: a bundle hidden in one scene is refused by any other.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors import SafetensorError
from safetensors.numpy import load_file, save

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.files import (atomic_folder, check_output_directory, check_output_folder, read_json, write_bytes,
                                     write_json)
from noisenerf.runtime.fingerprint import WeightsDigests, weights_digests
from noisenerf.runtime.networks import render_network
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.pdf import Hierarchy
from noisenerf.runtime.fields import grid_sampler, proposal_sampler
from noisenerf.runtime.grid_marching import GridMarching, GridMarchingSampler
from noisenerf.runtime.proposal import ProposalSampler, ProposalSampling
from noisenerf.runtime.render import HierarchicalSampler, MarchingSampler, RenderConfig, Sampler
from noisenerf.train.scene.field_kinds import Field, FieldConfigs, build_field, config_from_dict
from noisenerf.train.scene.render import numpy_density, numpy_field

SCENE_FORMAT_VERSION = 1
SCENE_FOLDER = {"marker": "scene.json", "what": "scene"}  # how an import's output folder is checked and replaced


def check_scene_output(directory: str | Path, force: bool) -> Path:
    """An import's output folder, checked before any work (Scene.publish checks it again when it writes)."""
    return check_output_folder(directory, replace=force, **SCENE_FOLDER)


@dataclass(frozen=True)
class SceneConfig:
    """Everything about a scene but its weights.

    With a fine field, views are fitted (and nerf-pytorch renders reproduced) hierarchically with
    n_coarse + n_importance samples; `render.sampling` is the uniform sampling that ordinary renders
    with empty-space skipping use (torch or onnxruntime), on the render field alone.
    """

    coarse: FieldConfigs
    fine: FieldConfigs | None
    n_coarse: int
    n_importance: int
    render: RenderConfig
    aabb: tuple[float, ...]
    grid_resolution: int
    cameras: tuple[Camera, ...]
    source: str = "fit"

    def architecture(self) -> dict:
        return {"coarse": self.coarse.to_dict(), "fine": self.fine.to_dict() if self.fine else None}

    def to_dict(self) -> dict:
        return {
            "format_version": SCENE_FORMAT_VERSION,
            **self.architecture(),
            "n_coarse": self.n_coarse,
            "n_importance": self.n_importance,
            "render": self.render.to_dict(),
            "aabb": list(self.aabb),
            "grid_resolution": self.grid_resolution,
            "cameras": [c.to_dict() for c in self.cameras],
            "source": self.source,
        }

    @staticmethod
    def from_dict(data: dict) -> "SceneConfig":
        if data.get("format_version") != SCENE_FORMAT_VERSION:
            raise UserError(f"unsupported scene format version {data.get('format_version')!r}")
        try:
            return SceneConfig(
                coarse=config_from_dict(data["coarse"]),
                fine=config_from_dict(data["fine"]) if data.get("fine") else None,
                n_coarse=int(data["n_coarse"]),
                n_importance=int(data["n_importance"]),
                render=RenderConfig.from_dict(data["render"]),
                aabb=tuple(float(v) for v in data["aabb"]),
                grid_resolution=int(data["grid_resolution"]),
                cameras=tuple(Camera.from_dict(c) for c in data["cameras"]),
                source=str(data.get("source", "fit")),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise UserError(f"malformed scene config: {error}") from None


class Scene:
    """A loaded scene: config, the coarse (and optional fine) field, and the occupancy grid."""

    def __init__(self, config: SceneConfig, coarse: Field, fine: Field | None, grid: OccupancyGrid):
        self.config, self.coarse, self.fine, self.grid = config, coarse, fine, grid

    @property
    def render_field(self) -> Field:
        """The field views, noise and exports use: the fine network when there is one."""
        return render_field(self.coarse, self.fine)

    @property
    def hierarchy(self) -> Hierarchy | None:
        """nerf-pytorch's coarse/fine sample counts for ordinary renders, where the scene has a fine network."""
        return Hierarchy(self.config.n_coarse, self.config.n_importance) if self.fine is not None else None

    def sampler(self, skip: bool = True) -> Sampler:
        """How an ordinary render of the torch fields places its samples, as the exported model's does
        (runtime.model.Model.sampler): render the `render_field` through numpy_field with it."""
        proposals = proposal_sampler(self.config.architecture())
        if proposals is not None:
            return ProposalSampler(ProposalSampling.from_architecture(proposals),
                                   tuple(numpy_density(network) for network in self.coarse.proposals))
        marching = grid_sampler(self.config.architecture())
        if marching is not None:
            return GridMarchingSampler(GridMarching.from_architecture(marching))
        if self.hierarchy is not None:
            return HierarchicalSampler(self.config.render, numpy_field(self.coarse), self.hierarchy)
        return MarchingSampler(self.config.render, self.grid, skip)

    def fields(self) -> dict[str, Field]:
        return named_fields(self.coarse, self.fine)

    def weight_arrays(self) -> dict[str, np.ndarray]:
        return {name: value.detach().cpu().numpy() for name, value in field_weights(self.fields()).items()}

    def fingerprint(self) -> str:
        return self.digests().fingerprint

    def digests(self) -> WeightsDigests:
        """The fingerprint and the mask secret (runtime.fingerprint) of the weights as they are now."""
        return weights_digests(self.weight_arrays(), self.config.architecture())

    def to(self, device: torch.device | str) -> "Scene":
        for field in self.fields().values():
            field.to(device)
        return self

    def save(self, directory: str | Path) -> Path:
        directory = check_output_directory(directory)
        directory.mkdir(exist_ok=True)
        write_bytes(directory / "weights.safetensors", save(self.weight_arrays()), replace=True)
        write_bytes(directory / "occupancy.safetensors", save({"occupied": self.grid.occupied.astype(np.uint8)}),
                    replace=True)
        write_json(directory / "scene.json", {**self.config.to_dict(), "fingerprint": self.fingerprint()})
        return directory

    def publish(self, directory: str | Path, *, source: str | Path, force: bool = False) -> Path:
        """Write an imported scene as the folder `directory`, whole (runtime.files.atomic_folder): refused where
        that folder holds files, unless force and they are an earlier scene, which is then replaced; and refused
        where a weight read from `source` is NaN or infinite (such a scene renders nothing but NaN)."""
        for name, array in self.weight_arrays().items():
            if not np.isfinite(array).all():
                raise UserError(f"{source}: weight {name} holds {np.count_nonzero(~np.isfinite(array))} NaN or "
                                f"infinite values; a scene with it cannot render")
        with atomic_folder(directory, replace=force, **SCENE_FOLDER) as tmp:
            self.save(tmp)
        return Path(directory)


# a scene whose field kind brings its own sampler (nerfacto's proposals or grid) carries an occupancy grid that rules
# nothing out: one occupied cell over a box no camera leaves
OWN_SAMPLER_BOX = (-1e6,) * 3 + (1e6,) * 3


def own_sampler_scene(field: Field, cameras: tuple[Camera, ...], render: RenderConfig, source: str) -> Scene:
    """A scene of one network (a nerfacto field, imported or fitted) rendered by its own sampler; `render` holds
    only what secret views use (their uniform sampling, the background, pixel centres)."""
    config = SceneConfig(coarse=field.config, fine=None, n_coarse=0, n_importance=0, render=render,
                         aabb=OWN_SAMPLER_BOX, grid_resolution=1, cameras=cameras, source=source)
    return Scene(config, field, None, OccupancyGrid(OWN_SAMPLER_BOX, np.ones((1, 1, 1), bool)))


def build_fields(config: SceneConfig) -> tuple[Field, Field | None]:
    return build_field(config.coarse), build_field(config.fine) if config.fine is not None else None


def render_field(coarse: Field, fine: Field | None) -> Field:
    """The network a scene renders (and hides, and exports as `rgb`/`sigma`) with (runtime.networks)."""
    fields = named_fields(coarse, fine)
    return fields[render_network(fields)]


def named_fields(coarse: Field, fine: Field | None) -> dict[str, Field]:
    """The scene's networks by name ("coarse", and "fine" where there is one)."""
    return {"coarse": coarse, **({"fine": fine} if fine is not None else {})}


def field_weights(fields: dict[str, Field]) -> dict[str, torch.Tensor]:
    """Every weight under the scene's names: NETWORK.MODULE (nerf-pytorch's module names), e.g.
    `coarse.pts_linears.0.weight`, as weights.safetensors, fit checkpoints and the ONNX initializers hold them."""
    return {f"{network}.{name}": value for network, field in fields.items() for name, value in field.state_dict().items()}


def weights_of(network: str, tensors: dict) -> dict:
    """One network's entries of a name -> tensor mapping written by field_weights, under module names."""
    return {k[len(network) + 1:]: v for k, v in tensors.items() if k.startswith(network + ".")}


def _load_field_weights(field: Field, tensors: dict[str, np.ndarray], prefix: str, path: Path) -> None:
    expected = field.state_dict()
    found = weights_of(prefix, tensors)
    if set(found) != set(expected):
        missing, extra = sorted(set(expected) - set(found)), sorted(set(found) - set(expected))
        raise UserError(f"{path}: {prefix} weights do not match the config (missing {missing[:3]}, "
                        f"unexpected {extra[:3]})")
    for name, value in found.items():
        if tuple(value.shape) != tuple(expected[name].shape):
            raise UserError(f"{path}: {prefix}.{name} has shape {tuple(value.shape)}, "
                            f"the config needs {tuple(expected[name].shape)}")
        if not np.isfinite(value).all():  # a fit that diverged: hiding in it would solve for minutes in vain
            raise UserError(f"{path}: {prefix}.{name} holds NaN or infinite weights")
    field.load_state_dict({k: torch.from_numpy(np.asarray(v, dtype=np.float32)) for k, v in found.items()})


def load_scene(directory: str | Path) -> Scene:
    """Load a scene directory written by `noisenerf fit` or `import-nerf-pytorch`, fields in eval mode."""
    directory = Path(directory)
    if not directory.is_dir() or not (directory / "scene.json").is_file():
        raise UserError(f"not a scene directory (no scene.json): {directory}")
    config = SceneConfig.from_dict(read_json(directory / "scene.json", "scene config"))
    tensors = _read_safetensors(directory / "weights.safetensors")
    coarse, fine = build_fields(config)
    _load_field_weights(coarse, tensors, "coarse", directory / "weights.safetensors")
    if fine is not None:
        _load_field_weights(fine, tensors, "fine", directory / "weights.safetensors")
    occupied = _read_safetensors(directory / "occupancy.safetensors").get("occupied")
    if occupied is None or occupied.shape != (config.grid_resolution,) * 3:
        raise UserError(f"{directory / 'occupancy.safetensors'}: no {config.grid_resolution}^3 'occupied' grid")
    scene = Scene(config, coarse, fine, OccupancyGrid(config.aabb, occupied.astype(bool)))
    for field in scene.fields().values():
        field.eval().requires_grad_(False)
    return scene


def _read_safetensors(path: Path) -> dict[str, np.ndarray]:
    try:
        return load_file(str(path))
    except FileNotFoundError:
        raise UserError(f"missing file: {path}") from None
    except (SafetensorError, OSError, ValueError) as error:
        raise UserError(f"not a readable safetensors file: {path} ({error})") from None
