"""`noisenerf import-nerfstudio`: a nerfstudio `nerfacto` or `instant-ngp` run directory -> a scene directory.

Read without nerfstudio and without running anything a file says:
- `config.yml` through a safe YAML loader whose Python tags become plain data (objects → mappings, paths
  → strings, names → their dotted text), so `!!python/object/apply:os.system` is a string, never a call;
- `dataparser_transforms.json` (the pose transform and scale nerfstudio applied);
- the latest `nerfstudio_models/step-*.ckpt`, with torch.load(weights_only=True) and only the numpy scalar
  globals real checkpoints hold (their learning rates) allowed; the pipeline's `_model.field.*` and
  `_model.proposal_networks.*` tensors are used (`module.` prefixes of multi-GPU runs stripped), the rest
  (LPIPS, camera optimizer, optimizer state) ignored;
- the dataset's `transforms.json` (from --data, or the run's recorded data path), read and checked by
  train.scene.captures as the fit reads it: frames sorted by file name as nerfstudio sorts them, each pose
  mapped by the dataparser transform, intrinsics scaled by the downscale nerfstudio chose.

Both implementations are reproduced as trained (runtime.fields.nerfacto): `torch` runs map tensor for
tensor; `tcnn` runs hold flat parameter vectors (each MLP before its grid, row-major matrices without
biases, outputs padded to 16, inputs padded to 16 with ones that act as a bias, read here as that bias)
and render with the parameters rounded to float16, so the import rounds them too. Every length is
checked against the layout the config implies before anything is built. The mean appearance embedding
nerfacto uses at eval is folded into the colour MLP's first bias.

nerfstudio's `instant-ngp` method is the same field without proposal networks (NerfactoField's defaults but for
the grid's size, density scale 1, its appearance embedding zero at eval) rendered by nerfacc's occupancy-grid
marcher: the checkpoint's `occupancy_grid.binaries` and boxes, the config's cone angle and planes, its step or
nerfstudio's default (the scene box's diagonal / 1000) become the field's grid sampler (runtime.grid_marching).

Refused in one line, because they would not be reproduced: other methods, nerfstudio runs older than
1.0 (their key layout), scene contraction off, proposal networks that share weights or use a linear
head, an initial sampler other than the piecewise one, backgrounds other than `last_sample` (nerfacto) or
over black (instant-ngp), an instant-ngp collider, and camera models other than the perspective ones and
OPENCV_FISHEYE (train.scene.captures).
"""

from __future__ import annotations

import base64
import math
import pickle
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import yaml

from noisenerf.runtime.camera import Camera
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.fields.nerfacto import grid_layout
from noisenerf.runtime.files import parse_json
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.scene.captures import read_capture
from noisenerf.train.scene.nerfacto import (
    GridSamplerConfig, NerfactoConfig, NerfactoField, ProposalConfig, SamplerConfig, grid_scales,
)
from noisenerf.train.scene.scene import Scene, check_scene_output, own_sampler_scene

MAX_CONFIG_BYTES = 1 << 20
TCNN_ALIGNMENT = 16  # tiny-cuda-nn pads MLP inputs and outputs to multiples of this
# secret views sample uniformly along depth (runtime.sampling): from nerfacto's training near plane to a
# depth that leaves nerfstudio's auto-scaled scene (cameras within the unit cube) behind
SECRET_NEAR, SECRET_FAR = 0.05, 4.0
NUMPY_SCALAR_GLOBALS = ("numpy._core.multiarray.scalar", "numpy.core.multiarray.scalar")
COLMAP_APPLIED = [[0, 1, 0, 0], [1, 0, 0, 0], [0, 0, -1, 0]]  # nerfstudio's applied_transform for COLMAP data


class PlainLoader(yaml.SafeLoader):
    """YAML's safe loader, with every `!!python/…` tag read as plain data instead of refused or run."""


def _python_tag(loader: PlainLoader, suffix: str, node: yaml.Node):
    if isinstance(node, yaml.MappingNode):
        value = loader.construct_mapping(node, deep=True)
    elif isinstance(node, yaml.SequenceNode):
        value = loader.construct_sequence(node, deep=True)
    else:
        value = loader.construct_scalar(node)
    if suffix.startswith("name:"):
        return suffix[len("name:"):]
    if suffix.startswith(("object/apply:pathlib.", "object/new:pathlib.")):
        parts = value.get("args", []) if isinstance(value, dict) else value
        return str(Path(*map(str, parts))) if isinstance(parts, list) else str(parts)
    if suffix.startswith(("object/apply:", "object/new:")):  # enums and other reconstructed values: their arguments
        parts = value.get("args", value) if isinstance(value, dict) else value
        return parts[0] if isinstance(parts, list) and len(parts) == 1 else parts
    return value  # objects → their attribute mapping, tuples → lists


PlainLoader.add_multi_constructor("tag:yaml.org,2002:python/", _python_tag)


def read_config_yml(path: Path) -> dict:
    """nerfstudio's config.yml as plain data."""
    if not path.is_file():
        raise UserError(f"not a nerfstudio run: {path} not found")
    if path.stat().st_size > MAX_CONFIG_BYTES:
        raise UserError(f"{path}: {path.stat().st_size} bytes, more than a nerfstudio config ({MAX_CONFIG_BYTES})")
    try:
        data = yaml.load(path.read_text(encoding="utf-8"), Loader=PlainLoader)  # noqa: S506 - PlainLoader is safe
    except (yaml.YAMLError, UnicodeDecodeError, RecursionError) as error:
        raise UserError(f"{path}: not a readable nerfstudio config ({type(error).__name__})") from None
    if not isinstance(data, dict) or not isinstance(data.get("pipeline"), dict):
        raise UserError(f"{path}: not a nerfstudio config (no pipeline)")
    return data


@dataclass(frozen=True)
class NerfactoSettings:
    """What nerfacto's config says about its networks and eval render."""

    implementation: str
    hidden_dim: int
    hidden_dim_color: int
    num_levels: int
    base_res: int
    max_res: int
    log2_hashmap_size: int
    features_per_level: int
    proposal_samples: tuple[int, ...]
    nerf_samples: int
    proposals: tuple[dict, ...]  # num_levels, max_res, log2_hashmap_size, hidden_dim
    appearance_dim: int
    average_appearance: bool
    average_init_density: float
    marcher: dict | None = None  # instant-ngp: cone_angle, near, far, levels, resolution, step (None: diagonal/1000)


MODEL_DEFAULTS = {  # nerfstudio 1.x NerfactoModelConfig / HashMLPDensityField defaults
    "hidden_dim": 64, "hidden_dim_color": 64, "num_levels": 16, "base_res": 16, "max_res": 2048,
    "log2_hashmap_size": 19, "features_per_level": 2, "num_proposal_samples_per_ray": [256, 96],
    "num_nerf_samples_per_ray": 48, "num_proposal_iterations": 2, "use_same_proposal_network": False,
    "proposal_initial_sampler": "piecewise", "background_color": "last_sample",
    "disable_scene_contraction": False, "use_appearance_embedding": True, "use_average_appearance_embedding": True,
    "appearance_embed_dim": 32, "average_init_density": 1.0, "implementation": "tcnn",
}


NGP_DEFAULTS = {  # nerfstudio 1.1.5 InstantNGPModelConfig (models/instant_ngp.py:40–80, research/ngp-method.md §1)
    "enable_collider": False, "grid_resolution": 128, "grid_levels": 4, "max_res": 2048, "log2_hashmap_size": 19,
    "cone_angle": 0.004, "render_step_size": None, "near_plane": 0.05, "far_plane": 1000.0,
    "use_appearance_embedding": False, "background_color": "random", "disable_scene_contraction": False,
}


def ngp_settings(model: dict, source: str) -> NerfactoSettings:
    """The model section of an instant-ngp config: nerfacto's field with NerfactoField's defaults but for the
    grid's size (instant_ngp.py:105–112; its appearance flag is inverted: 32 wide unless asked for, zeros at
    eval), nerfacc's grid marcher with the config's step, cone angle and planes."""
    get = lambda key: model.get(key, NGP_DEFAULTS[key])  # noqa: E731
    if get("disable_scene_contraction"):
        raise UserError(f"{source}: an instant-ngp run without scene contraction is not reproduced")
    if get("enable_collider"):
        raise UserError(f"{source}: an instant-ngp run with a collider is not reproduced (its planes move the march)")
    if get("background_color") not in ("random", "black"):
        raise UserError(f"{source}: background {get('background_color')!r} is not reproduced (at eval 'random' and "
                        "'black' composite over black)")
    resolution = get("grid_resolution")
    if isinstance(resolution, list) and len(set(resolution)) == 1:
        resolution = resolution[0]
    step = get("render_step_size")
    try:
        marcher = {"cone_angle": float(get("cone_angle")), "near": float(get("near_plane")),
                   "far": float(get("far_plane")), "levels": int(get("grid_levels")), "resolution": int(resolution),
                   "step": None if step is None else float(step)}
        return NerfactoSettings(
            implementation="tcnn", hidden_dim=64, hidden_dim_color=64, num_levels=16, base_res=16,
            max_res=int(get("max_res")), log2_hashmap_size=int(get("log2_hashmap_size")), features_per_level=2,
            proposal_samples=(), nerf_samples=0, proposals=(),
            appearance_dim=0 if get("use_appearance_embedding") else 32, average_appearance=False,
            average_init_density=1.0, marcher=marcher)
    except (TypeError, ValueError) as error:
        raise UserError(f"{source}: malformed instant-ngp settings ({error})") from None


def nerfacto_settings(config: dict, source: str) -> NerfactoSettings:
    """The model section of a nerfacto (or instant-ngp) config, refusing what would not be reproduced."""
    model = config["pipeline"].get("model")
    target = str(model.get("_target", "")) if isinstance(model, dict) else ""
    if target.endswith("NGPModel"):
        return ngp_settings(model, source)
    if not target.endswith("NerfactoModel"):
        name = config.get("method_name") or target or "unknown"
        raise UserError(f"{source}: a {name} run; only nerfacto and instant-ngp runs can be imported")
    get = lambda key: model.get(key, MODEL_DEFAULTS.get(key))  # noqa: E731
    refusals = {
        "use_same_proposal_network": (True, "one proposal network shared by every stage"),
        "disable_scene_contraction": (True, "scene contraction turned off"),
    }
    for key, (bad, what) in refusals.items():
        if get(key) == bad:
            raise UserError(f"{source}: {what} is not reproduced; only nerfacto's defaults for it import")
    if get("proposal_initial_sampler") != "piecewise":
        raise UserError(f"{source}: initial sampler {get('proposal_initial_sampler')!r} is not reproduced (only 'piecewise')")
    if get("background_color") != "last_sample":
        raise UserError(f"{source}: background {get('background_color')!r} is not reproduced (only 'last_sample')")
    implementation = get("implementation")
    if implementation not in ("tcnn", "torch"):
        raise UserError(f"{source}: implementation {implementation!r} is neither tcnn nor torch")
    iterations = int(get("num_proposal_iterations"))
    args = model.get("proposal_net_args_list")
    if not isinstance(args, list) or len(args) != iterations or len(get("num_proposal_samples_per_ray")) != iterations:
        raise UserError(f"{source}: {iterations} proposal iterations need as many proposal networks and sample counts")
    proposals = []
    for arg in args:
        if not isinstance(arg, dict) or arg.get("use_linear", False):
            raise UserError(f"{source}: a proposal network with a linear head is not reproduced")
        proposals.append({key: int(arg.get(key, default)) for key, default in
                          (("num_levels", 8), ("max_res", 1024), ("log2_hashmap_size", 18), ("hidden_dim", 64))})
    try:
        return NerfactoSettings(
            implementation=implementation, hidden_dim=int(get("hidden_dim")), hidden_dim_color=int(get("hidden_dim_color")),
            num_levels=int(get("num_levels")), base_res=int(get("base_res")), max_res=int(get("max_res")),
            log2_hashmap_size=int(get("log2_hashmap_size")), features_per_level=int(get("features_per_level")),
            proposal_samples=tuple(int(n) for n in get("num_proposal_samples_per_ray")),
            nerf_samples=int(get("num_nerf_samples_per_ray")), proposals=tuple(proposals),
            appearance_dim=int(get("appearance_embed_dim")) if get("use_appearance_embedding") else 0,
            average_appearance=bool(get("use_average_appearance_embedding")),
            average_init_density=float(get("average_init_density")))
    except (TypeError, ValueError) as error:
        raise UserError(f"{source}: malformed nerfacto settings ({error})") from None


def field_config(settings: NerfactoSettings, sampler: GridSamplerConfig | None = None) -> NerfactoConfig:
    """The field's config; an instant-ngp run's grid sampler (`grid_sampler`) comes from its checkpoint."""
    implementation = settings.implementation
    proposals = tuple(ProposalConfig(
        features=2, log2_table=p["log2_hashmap_size"], hidden=p["hidden_dim"],
        scales=grid_scales(implementation, p["num_levels"], 16, p["max_res"])) for p in settings.proposals)
    return NerfactoConfig(
        implementation=implementation, features=settings.features_per_level, log2_table=settings.log2_hashmap_size,
        scales=grid_scales(implementation, settings.num_levels, settings.base_res, settings.max_res),
        density_hidden=settings.hidden_dim, geo_features=15, sh_degree=4, colour_hidden=settings.hidden_dim_color,
        colour_layers=2, density_scale=settings.average_init_density, proposals=proposals,
        sampler=sampler or SamplerConfig(settings.proposal_samples, settings.nerf_samples, 0.01, 0.0, 1000.0))


def grid_sampler(state: dict, settings: NerfactoSettings, source: str) -> GridSamplerConfig:
    """An instant-ngp run's nerfacc grid from its checkpoint (occupancy_grid.binaries [levels, x, y, z] and aabbs,
    level 0 the scene box), its step nerfstudio's default where the config leaves it None: the box's diagonal
    / 1000 (float32 norm, then a Python division: instant_ngp.py:116–118)."""
    marcher = settings.marcher
    levels, resolution = marcher["levels"], marcher["resolution"]
    binaries = tensor(state, "occupancy_grid.binaries", (levels, resolution, resolution, resolution), source)
    box = tensor(state, "occupancy_grid.aabbs", (levels, 6), source)[0]
    step = marcher["step"]
    if step is None:
        step = float(((box[3:] - box[:3]) ** 2).sum().sqrt().item()) / 1000
    occupancy = base64.b64encode(np.packbits(binaries.numpy().reshape(-1) > 0.5).tobytes()).decode("ascii")
    return GridSamplerConfig(step=float(np.float32(step)), cone_angle=marcher["cone_angle"], near=marcher["near"],
                             far=marcher["far"], levels=levels, resolution=resolution,
                             aabb=tuple(float(v) for v in box.tolist()), occupancy=occupancy)


def latest_checkpoint(run_dir: Path) -> Path:
    """The checkpoint nerfstudio would load: the highest step in nerfstudio_models/."""
    steps = {int(m.group(1)): path for path in (run_dir / "nerfstudio_models").glob("step-*.ckpt")
             if (m := re.fullmatch(r"step-(\d+)\.ckpt", path.name))}
    if not steps:
        raise UserError(f"not a nerfstudio run: no nerfstudio_models/step-*.ckpt in {run_dir}")
    return steps[max(steps)]


def read_pipeline(path: Path) -> dict[str, torch.Tensor]:
    """The checkpoint's pipeline state dict, loaded weights-only, with the module prefixes removed."""
    if not hasattr(torch.serialization, "safe_globals"):
        raise UserError(f"{path}: reading nerfstudio checkpoints needs torch 2.5 or later (torch {torch.__version__})")
    scalar = np._core.multiarray.scalar if hasattr(np, "_core") else np.core.multiarray.scalar
    allowed = [np.dtype, type(np.dtype(np.float64)), type(np.dtype(np.float32))]
    allowed += [(scalar, name) for name in NUMPY_SCALAR_GLOBALS]
    try:
        with warnings.catch_warnings(), torch.serialization.safe_globals(allowed):
            warnings.simplefilter("ignore")
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise UserError(f"{path}: refused: it holds Python objects besides tensors, plain containers and numpy "
                        "scalars (nothing in it was run)") from None
    except Exception as error:  # torch.load fails on foreign or truncated bytes with many error types
        raise UserError(f"{path}: not a readable torch checkpoint ({type(error).__name__})") from None
    pipeline = checkpoint.get("pipeline") if isinstance(checkpoint, dict) else None
    if not isinstance(pipeline, dict) or not all(isinstance(v, torch.Tensor) for v in pipeline.values()):
        raise UserError(f"{path}: not a nerfstudio checkpoint (no pipeline state dict)")
    state = {}
    for key, value in pipeline.items():
        name = re.sub(r"^_model\.(module\.)?", "", str(key))
        if name.startswith(("field.", "proposal_networks.", "occupancy_grid.")):
            state[name] = value.detach().to(torch.float32)
    if not state:
        raise UserError(f"{path}: holds no nerfacto field (no _model.field.* tensors)")
    return state


def key_generation(state: dict[str, torch.Tensor], source: str) -> str:
    """Which implementation's v1.0+ keys the field holds; older layouts are refused naming their version."""
    if "field.mlp_base.model.params" in state:
        return "tcnn"
    if "field.mlp_base.model.0.hash_table" in state:
        return "torch"
    if "field.mlp_base_grid.tcnn_encoding.params" in state:
        raise UserError(f"{source}: a nerfstudio 0.3 checkpoint; its key layout is not read (re-save it with "
                        "nerfstudio 1.0 or later)")
    if "field.mlp_base.params" in state:
        raise UserError(f"{source}: a nerfstudio 0.1–0.2 checkpoint; its key layout is not read (re-save it with "
                        "nerfstudio 1.0 or later)")
    raise UserError(f"{source}: no nerfacto field in the checkpoint's keys (field.mlp_base.*)")


def tensor(state: dict, key: str, shape: tuple[int, ...], source: str) -> torch.Tensor:
    """A checkpoint tensor that must exist with exactly this shape."""
    if key not in state:
        raise UserError(f"{source}: the checkpoint lacks {key}")
    if tuple(state[key].shape) != shape:
        raise UserError(f"{source}: {key} has shape {list(state[key].shape)}, the config implies {list(shape)}")
    return state[key]


def padded(n: int) -> int:
    return -(-n // TCNN_ALIGNMENT) * TCNN_ALIGNMENT


class FlatParams:
    """A tiny-cuda-nn flat parameter vector read front to back, every length checked."""

    def __init__(self, values: torch.Tensor, key: str, source: str):
        self.values, self.key, self.source, self.at = values.reshape(-1), key, source, 0

    def take(self, rows: int, cols: int) -> torch.Tensor:
        end = self.at + rows * cols
        if end > self.values.numel():
            raise UserError(f"{self.source}: {self.key} holds {self.values.numel()} values, fewer than the config's "
                            "layout needs")
        block, self.at = self.values[self.at:end].reshape(rows, cols), end
        return block

    def done(self) -> None:
        if self.at != self.values.numel():
            raise UserError(f"{self.source}: {self.key} holds {self.values.numel()} values, the config's layout "
                            f"{self.at}")


def tcnn_mlp(params: FlatParams, fan_in: int, width: int, layers: int, fan_out: int, ones_pad: bool
             ) -> list[tuple[torch.Tensor, torch.Tensor]]:
    """(weight, bias) of a tiny-cuda-nn MLP with `layers` matrices: inputs padded to 16 (with ones when the
    network's own input is padded, which makes those columns a bias), outputs padded to 16."""
    sizes = [fan_in] + [width] * (layers - 1) + [fan_out]
    result = []
    for i, (a, b) in enumerate(zip(sizes, sizes[1:])):
        matrix = params.take(padded(b) if i == layers - 1 else b, padded(a) if i == 0 else a)
        bias = matrix[:b, a:].sum(1) if i == 0 and ones_pad else torch.zeros(b)
        result.append((matrix[:b, :a], bias))
    return result


def grid_rows(scales, implementation: str, log2_table: int) -> int:
    return grid_layout(implementation, scales, log2_table).total_rows


def field_state(state: dict, config: NerfactoConfig, settings: NerfactoSettings, source: str
                ) -> dict[str, torch.Tensor]:
    """NerfactoField's state dict from the checkpoint's tensors, every shape checked against `config`."""
    dims, hidden, colour = config.position_dims, config.density_hidden, config.colour_hidden
    head_in = config.direction_dims + config.geo_features
    rows = grid_rows(config.scales, config.implementation, config.log2_table)
    appearance = torch.zeros(0)
    if settings.appearance_dim:
        table = state.get("field.embedding_appearance.embedding.weight")
        if table is None or table.ndim != 2 or table.shape[1] != settings.appearance_dim or table.shape[0] < 1:
            raise UserError(f"{source}: the appearance embedding is missing or not {settings.appearance_dim} wide")
        appearance = table.mean(0) if settings.average_appearance else torch.zeros(settings.appearance_dim)
    out: dict[str, torch.Tensor] = {}
    if config.implementation == "torch":
        out["table"] = tensor(state, "field.mlp_base.model.0.hash_table", (rows, config.features), source)
        base = [(tensor(state, f"field.mlp_base.model.1.layers.{i}.weight", shape, source),
                 tensor(state, f"field.mlp_base.model.1.layers.{i}.bias", shape[:1], source))
                for i, shape in enumerate(((hidden, dims), (1 + config.geo_features, hidden)))]
        widths = [head_in + settings.appearance_dim, colour, colour, 3]
        head = [(tensor(state, f"field.mlp_head.layers.{i}.weight", (b, a), source),
                 tensor(state, f"field.mlp_head.layers.{i}.bias", (b,), source))
                for i, (a, b) in enumerate(zip(widths, widths[1:]))]
    else:
        flat = FlatParams(half(tensor_1d(state, "field.mlp_base.model.params", source)), "field.mlp_base.model.params",
                          source)
        base = tcnn_mlp(flat, dims, hidden, 2, 1 + config.geo_features, ones_pad=False)  # the grid pads with zeros
        out["table"] = flat.take(rows, config.features)
        flat.done()
        flat = FlatParams(half(tensor_1d(state, "field.mlp_head.tcnn_encoding.params", source)),
                          "field.mlp_head.tcnn_encoding.params", source)
        head = tcnn_mlp(flat, head_in + settings.appearance_dim, colour, 3, 3, ones_pad=True)
        flat.done()
    (w0, b0), *rest = head
    b0 = (b0.double() + w0[:, head_in:].double() @ appearance.double()).float()  # the eval appearance, folded
    for i, (w, b) in enumerate(base):
        out[f"density_linears.{i}.weight"], out[f"density_linears.{i}.bias"] = w, b
    for i, (w, b) in enumerate([(w0[:, :head_in], b0), *rest]):
        out[f"colour_linears.{i}.weight"], out[f"colour_linears.{i}.bias"] = w, b
    for i, proposal in enumerate(config.proposals):
        out.update({f"proposals.{i}.{k}": v for k, v in proposal_state(state, i, proposal, config.implementation,
                                                                        source).items()})
    return {k: v.contiguous().clone() for k, v in out.items()}


def proposal_state(state: dict, index: int, proposal: ProposalConfig, implementation: str, source: str
                   ) -> dict[str, torch.Tensor]:
    prefix = f"proposal_networks.{index}"
    rows = grid_rows(proposal.scales, implementation, proposal.log2_table)
    if implementation == "torch":
        shapes = ((proposal.hidden, proposal.grid_dims), (1, proposal.hidden))
        layers = [(tensor(state, f"{prefix}.mlp_base.1.layers.{i}.weight", shape, source),
                   tensor(state, f"{prefix}.mlp_base.1.layers.{i}.bias", shape[:1], source)) for i, shape in enumerate(shapes)]
        table = tensor(state, f"{prefix}.encoding.hash_table", (rows, proposal.features), source)
    else:
        key = f"{prefix}.mlp_base.1.tcnn_encoding.params"
        flat = FlatParams(half(tensor_1d(state, key, source)), key, source)
        layers = tcnn_mlp(flat, proposal.grid_dims, proposal.hidden, 2, 1, ones_pad=True)
        flat.done()
        key = f"{prefix}.encoding.tcnn_encoding.params"
        flat = FlatParams(half(tensor_1d(state, key, source)), key, source)
        table = flat.take(rows, proposal.features)
        flat.done()
    return {"table": table, **{f"linears.{i}.{name}": value for i, layer in enumerate(layers)
                               for name, value in zip(("weight", "bias"), layer)}}


def tensor_1d(state: dict, key: str, source: str) -> torch.Tensor:
    if key not in state:
        raise UserError(f"{source}: the checkpoint lacks {key}")
    return state[key]


def half(values: torch.Tensor) -> torch.Tensor:
    """tiny-cuda-nn renders with its float32 master parameters rounded to float16."""
    return values.to(torch.float16).to(torch.float32)


def read_json_file(path: Path, most: int) -> object:
    if not path.is_file():
        raise UserError(f"{path} not found")
    if path.stat().st_size > most:
        raise UserError(f"{path}: {path.stat().st_size} bytes, more than {most}")
    return parse_json(path.read_text(encoding="utf-8"), str(path))


def dataparser_transform(run_dir: Path) -> tuple[np.ndarray, float]:
    """The 3×4 transform and scale nerfstudio applied to the dataset's poses."""
    path = run_dir / "dataparser_transforms.json"
    data = read_json_file(path, MAX_CONFIG_BYTES)
    try:
        transform = np.asarray(data["transform"], dtype=np.float64)
        scale = float(data["scale"])
    except (KeyError, TypeError, ValueError):
        raise UserError(f"{path}: expected a 3×4 transform and a scale") from None
    if transform.shape != (3, 4) or not np.isfinite(transform).all() or not (math.isfinite(scale) and scale > 0):
        raise UserError(f"{path}: expected a finite 3×4 transform and a positive scale")
    return transform, scale


def data_directory(config: dict, run_dir: Path, data: Path | None) -> Path:
    """Where the run's transforms.json is: --data, or the path the run recorded (as given to ns-train,
    tried as is and relative to the run's grandparent folders)."""
    if data is not None:
        return Path(data)
    datamanager = config["pipeline"].get("datamanager", {})
    recorded = [datamanager.get("dataparser", {}).get("data"), datamanager.get("data"), config.get("data")]
    stated = [value for value in recorded if value and value != "."]
    for value in stated:
        for base in (Path("."), *run_dir.resolve().parents):
            if (base / value / "transforms.json").is_file():
                return base / value
    where = f"at the path it recorded, {str(stated[0])!r:.200}, " if stated else "(it recorded no path) "
    raise UserError(f"the run's dataset (transforms.json) was not found {where}as given or under the run's parent "
                    "folders; give it with --data")


def dataset_cameras(data_dir: Path, transform: np.ndarray, scale: float, downscale: int | None
                    ) -> tuple[Camera, ...]:
    """Every frame's camera as nerfstudio builds it at eval: frames sorted by file name, the pose mapped
    into nerfstudio's frame (the transform applies to poses as saved; a transforms.json's applied_transform
    is already in them), intrinsics divided by the downscale, the lens as nerfstudio bends its rays (runtime.lens:
    its coefficients are in normalised coordinates, whatever the downscale)."""
    capture = read_capture(data_dir)
    applied = capture.applied_transform
    if applied is None and (Path(data_dir) / "colmap" / "sparse" / "0").exists():
        applied = np.asarray(COLMAP_APPLIED, np.float64)  # nerfstudio's default for COLMAP data
    saved = np.vstack([transform, [0, 0, 0, 1]])
    if applied is not None:  # dataparser_transforms.json holds transform·applied; the frames are already applied
        saved = saved @ np.linalg.inv(np.vstack([applied, [0, 0, 0, 1]]))
    pose_scale = scale / capture.applied_scale
    cameras = []
    for frame in sorted(capture.frames, key=lambda frame: Path(frame.file_path).name):
        stated, lens = frame.camera(), frame.lens()
        c2w = saved @ frame.c2w
        c2w[:3, 3] *= pose_scale
        factor = downscale or auto_downscale(Path(data_dir), frame.file_path, stated.width, stated.height)
        cameras.append(Camera.from_dict({
            "c2w": c2w.tolist(), "width": int(stated.width / factor), "height": int(stated.height / factor),
            "fx": stated.fx / factor, "fy": stated.fy / factor, "cx": stated.cx / factor, "cy": stated.cy / factor,
            **({"lens": lens.to_dict()} if lens is not None else {})}))
    return tuple(cameras)


def check_within_reach(cameras: tuple[Camera, ...], far: float, source: Path, scale: float) -> None:
    """Refuse cameras farther from the scene's centre than the sampler's far plane: no ray of theirs reaches the
    centre, so every render is empty (a dataparser scale far too large, or poses in other units)."""
    distances = [float(np.linalg.norm(np.asarray(camera.c2w, np.float64)[:3, 3])) for camera in cameras]
    worst = int(np.argmax(distances))
    if not distances[worst] < far:
        raise UserError(f"{source}: with scale {scale:.6g}, camera {worst} lies {distances[worst]:.3g} from the "
                        f"scene's centre, beyond the far plane ({far:g}): its renders would be empty")


def auto_downscale(data_dir: Path, file_path: str, width: int, height: int) -> int:
    """nerfstudio's automatic downscale: halve while the larger side exceeds 1600 px and images_<2^k> exist."""
    name, factor = Path(file_path).name, 1
    while max(width, height) / factor > 1600 and (data_dir / f"images_{factor * 2}" / name).exists():
        factor *= 2
    return factor


def import_nerfstudio(run_dir: Path, out_dir: Path, data: Path | None = None, force: bool = False) -> Scene:
    """Convert a nerfstudio nerfacto run directory into a scene directory (module docstring). Everything is
    checked before out_dir is created, so a refused import leaves nothing behind; an out_dir holding files is
    refused unless force and they are an earlier scene, which the new one then replaces whole."""
    run_dir, out_dir = Path(run_dir), Path(out_dir)
    check_scene_output(out_dir, force)
    if not run_dir.is_dir():
        raise UserError(f"not a nerfstudio run directory: {run_dir}")
    config = read_config_yml(run_dir / "config.yml")
    settings = nerfacto_settings(config, str(run_dir / "config.yml"))
    checkpoint = latest_checkpoint(run_dir)
    state = read_pipeline(checkpoint)
    generation = key_generation(state, str(checkpoint))
    if generation != settings.implementation:
        settings = NerfactoSettings(**{**settings.__dict__, "implementation": generation})  # tcnn fell back to torch
    field_settings = field_config(settings, grid_sampler(state, settings, str(checkpoint)) if settings.marcher else None)
    field = NerfactoField(field_settings)
    field.load_state_dict(field_state(state, field_settings, settings, str(checkpoint)))
    transform, scale = dataparser_transform(run_dir)
    dataparser = config["pipeline"].get("datamanager", {}).get("dataparser", {})
    downscale = dataparser.get("downscale_factor") if isinstance(dataparser, dict) else None
    cameras = dataset_cameras(data_directory(config, run_dir, data), transform, scale,
                              int(downscale) if downscale else None)
    check_within_reach(cameras, field_settings.sampler.far, run_dir / "dataparser_transforms.json", scale)
    render = RenderConfig(SamplingConfig(SECRET_NEAR, SECRET_FAR, 128), background=(1.0, 1.0, 1.0), pixel_center=0.5)
    scene = own_sampler_scene(field, cameras, render, "nerfstudio")
    scene.publish(out_dir, source=checkpoint, force=force)
    return scene
