"""`noisenerf import-nerf-pytorch`: a nerf-pytorch checkpoint + its config file -> a scene directory.

The checkpoint is read with `torch.load(weights_only=True)`: tensors and plain containers only, so a
file carrying arbitrary Python objects is refused without running any of it. Module names equal
nerf-pytorch's, so its state dicts map onto MlpField one to one; the only exception is a net without
view directions, where nerf-pytorch also stores a never-used `views_linears` layer and, with a fine
net, a fifth `output_linear` channel that nothing reads: both are dropped.

The scene reproduces nerf-pytorch's test-time renders (perturb 0, raw_noise_std 0): rays through
integer pixel coordinates (pixel_center 0.0), NDC for LLFF unless no_ndc, near/far and background by
its rules, and — with a fine net — the hierarchical render with n_coarse = N_samples and n_importance
= N_importance. Ordinary renders (skipping, ONNX) use the fine net alone with N_samples + N_importance
uniform samples, as a fitted "paper" scene does.

Refused because we would not reproduce them: i_embed != 0 (no or another encoding), lindisp where it
applies (nerf-pytorch ignores it under NDC), spherify for LLFF, dataset types other than blender/llff.
"""

from __future__ import annotations

import dataclasses
import pickle
import re
import warnings
import zipfile
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from noisenerf.runtime.camera import Camera, NDCSpace, pixel_rays
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.scene.datasets import LLFF_BD_FACTOR, load_dataset, read_poses_bounds
from noisenerf.train.scene.field import MlpConfig, MlpField
from noisenerf.train.scene.occupancy import build_occupancy_grid
from noisenerf.train.scene.scene import Scene, SceneConfig, check_scene_output, render_field

# nerf-pytorch's run_nerf.config_parser: every option it knows, with its type and default (bool: a flag).
OPTIONS: dict[str, tuple[type, object]] = {
    "expname": (str, None), "basedir": (str, "./logs/"), "datadir": (str, "./data/llff/fern"),
    "netdepth": (int, 8), "netwidth": (int, 256), "netdepth_fine": (int, 8), "netwidth_fine": (int, 256),
    "N_rand": (int, 32 * 32 * 4), "lrate": (float, 5e-4), "lrate_decay": (int, 250),
    "chunk": (int, 1024 * 32), "netchunk": (int, 1024 * 64), "no_batching": (bool, False),
    "no_reload": (bool, False), "ft_path": (str, None),
    "N_samples": (int, 64), "N_importance": (int, 0), "perturb": (float, 1.0), "use_viewdirs": (bool, False),
    "i_embed": (int, 0), "multires": (int, 10), "multires_views": (int, 4), "raw_noise_std": (float, 0.0),
    "render_only": (bool, False), "render_test": (bool, False), "render_factor": (int, 0),
    "precrop_iters": (int, 0), "precrop_frac": (float, 0.5),
    "dataset_type": (str, "llff"), "testskip": (int, 8), "shape": (str, "greek"),
    "white_bkgd": (bool, False), "half_res": (bool, False),
    "factor": (int, 8), "no_ndc": (bool, False), "lindisp": (bool, False), "spherify": (bool, False),
    "llffhold": (int, 8),
    "i_print": (int, 100), "i_img": (int, 500), "i_weights": (int, 10000), "i_testset": (int, 50000),
    "i_video": (int, 50000),
}

# configargparse's DefaultConfigFileParser line grammar: `key value`, `key = value`, `key: value`,
# an optional quoted value, and an inline comment only after whitespace.
_LINE = re.compile(r"^(?P<key>[^:=;#\s]+)\s*(?:(?P<sep>[:=\s])\s*(?P<quote>['\"]?)(?P<value>.+?)?(?P=quote))?"
                   r"\s*(?:\s[;#].*)?$")
_TRUE, _FALSE = ("true", "yes", "1"), ("false", "no", "0")

CHECKPOINT_FIELDS = {"coarse": "network_fn_state_dict", "fine": "network_fine_state_dict"}
LEGACY_TORCH_MAGIC = b"\x80\x02\x8a\x0al\xfc\x9cF\xf9 j\xa8"  # pickle.dumps(0x1950a86a20f9469cfc6c, 2)
BLENDER_BOUNDS = (2.0, 6.0)  # run_nerf.train: near, far for dataset_type blender
NDC_BOUNDS = (0.0, 1.0)


@dataclass(frozen=True)
class NerfPytorchConfig:
    """The nerf-pytorch options that decide its test-time render."""

    datadir: str
    dataset_type: str
    netdepth: int
    netwidth: int
    netdepth_fine: int
    netwidth_fine: int
    multires: int
    multires_views: int
    use_viewdirs: bool
    i_embed: int
    n_samples: int
    n_importance: int
    white_bkgd: bool
    half_res: bool
    factor: int
    no_ndc: bool
    lindisp: bool
    spherify: bool

    @property
    def uses_ndc(self) -> bool:
        return self.dataset_type == "llff" and not self.no_ndc

    @property
    def background(self) -> tuple[float, float, float]:
        """raw2outputs adds (1 − acc) only with white_bkgd: otherwise the background is black."""
        return (1.0, 1.0, 1.0) if self.white_bkgd else (0.0, 0.0, 0.0)


def parse_config_text(text: str, source: str) -> dict[str, str]:
    """configargparse's key/value lines -> {key: raw value}; the last setting of a key wins.

    A bare key is a flag set to "true"; `#`, `;`, `[section]` and `---` lines are comments.
    """
    settings = {}
    for number, raw_line in enumerate(text.splitlines(), start=1):
        line = raw_line.strip()
        if not line or line[0] in "#;[" or line.startswith("---"):
            continue
        match = _LINE.match(line)
        if match is None:
            raise UserError(f"{source}:{number}: cannot read config line {raw_line.strip()!r}")
        value = match["value"]
        if value is None:  # `key` alone sets a flag; `key =` sets an empty value
            value = "" if match["sep"] and not match["sep"].isspace() else "true"
        settings[match["key"].lstrip("-")] = value
    return settings


def typed_options(settings: Mapping[str, str], source: str) -> dict[str, object]:
    """Every nerf-pytorch option, typed, with its default where the file does not set it."""
    unknown = sorted(set(settings) - set(OPTIONS))
    if unknown:
        raise UserError(f"{source}: unknown option {unknown[0]!r} (not a nerf-pytorch run_nerf.py option)")
    options = {}
    for name, (kind, default) in OPTIONS.items():
        options[name] = default if name not in settings else _convert(name, kind, settings[name], source)
    return options


def _convert(name: str, kind: type, value: str, source: str) -> object:
    if kind is bool:
        if value.lower() in _TRUE + _FALSE:
            return value.lower() in _TRUE
        raise UserError(f"{source}: {name} = {value!r} is not a boolean (True or False)")
    try:
        return kind(value)
    except ValueError:
        raise UserError(f"{source}: {name} = {value!r} is not a valid {kind.__name__}") from None


def read_config(path: Path) -> NerfPytorchConfig:
    """A nerf-pytorch config file, checked for what we can reproduce."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        raise UserError(f"config file not found: {path}") from None
    except (OSError, UnicodeDecodeError) as error:
        raise UserError(f"cannot read config file {path}: {error}") from None
    options = typed_options(parse_config_text(text, str(path)), str(path))
    config = NerfPytorchConfig(
        datadir=options["datadir"], dataset_type=options["dataset_type"],
        netdepth=options["netdepth"], netwidth=options["netwidth"],
        netdepth_fine=options["netdepth_fine"], netwidth_fine=options["netwidth_fine"],
        multires=options["multires"], multires_views=options["multires_views"],
        use_viewdirs=options["use_viewdirs"], i_embed=options["i_embed"],
        n_samples=options["N_samples"], n_importance=options["N_importance"],
        white_bkgd=options["white_bkgd"], half_res=options["half_res"], factor=options["factor"],
        no_ndc=options["no_ndc"], lindisp=options["lindisp"], spherify=options["spherify"],
    )
    check_supported(config, str(path))
    return config


def check_supported(config: NerfPytorchConfig, source: str) -> None:
    """Refuse settings whose renders this importer would not reproduce."""
    if config.dataset_type not in ("blender", "llff"):
        raise UserError(f"{source}: dataset_type {config.dataset_type!r} is not supported (blender or llff)")
    if config.i_embed != 0:
        raise UserError(f"{source}: i_embed = {config.i_embed} is not supported (only 0, the positional "
                        f"encoding Noise-NeRF adds its noise to)")
    if config.lindisp and not config.uses_ndc:
        raise UserError(f"{source}: lindisp = True (samples linear in disparity) is not supported")
    if config.spherify and config.dataset_type == "llff":
        raise UserError(f"{source}: spherify = True (360° LLFF scenes) is not supported")
    sizes = {"netdepth": config.netdepth, "netwidth": config.netwidth, "netdepth_fine": config.netdepth_fine,
             "netwidth_fine": config.netwidth_fine, "factor": config.factor}
    for name, value in sizes.items():
        if value < 1:
            raise UserError(f"{source}: {name} must be positive, got {value}")
    if config.multires < 0 or config.multires_views < 0 or config.n_importance < 0:
        raise UserError(f"{source}: multires, multires_views and N_importance must not be negative")
    # the fine samples come from coarse weights[1:-1], which needs three coarse samples at least
    minimum = 3 if config.n_importance else 1
    if config.n_samples < minimum:
        raise UserError(f"{source}: N_samples = {config.n_samples} is too small (at least {minimum})")


def field_configs(config: NerfPytorchConfig) -> tuple[MlpConfig, MlpConfig | None]:
    """nerf-pytorch's create_nerf architectures: skip at 4, the fine net only with N_importance > 0."""
    def field(depth: int, width: int) -> MlpConfig:
        return MlpConfig(depth=depth, width=width, skips=(4,), xyz_freqs=config.multires,
                           dir_freqs=config.multires_views, use_viewdirs=config.use_viewdirs)

    fine = field(config.netdepth_fine, config.netwidth_fine) if config.n_importance > 0 else None
    return field(config.netdepth, config.netwidth), fine


def read_checkpoint(path: Path) -> dict:
    """The checkpoint's top-level dict, loaded weights-only (no arbitrary objects are ever built)."""
    if not path.is_file():
        raise UserError(f"checkpoint file not found: {path}")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # torch warns about pickle protocols; the outcome is what counts
            checkpoint = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        if not is_torch_file(path):  # foreign bytes fail as bad pickles too
            raise UserError(f"{path}: not a torch checkpoint") from None
        raise UserError(f"{path}: refused: it holds Python objects besides tensors and plain containers "
                        f"(only weights-only torch checkpoints are read; nothing in it was run)") from None
    except Exception as error:  # torch.load fails on foreign bytes with many error types (KeyError, EOFError...)
        raise UserError(f"{path}: not a torch checkpoint ({type(error).__name__})") from None
    if not isinstance(checkpoint, dict) or CHECKPOINT_FIELDS["coarse"] not in checkpoint:
        raise UserError(f"{path}: not a nerf-pytorch checkpoint (no {CHECKPOINT_FIELDS['coarse']!r})")
    return checkpoint


def is_torch_file(path: Path) -> bool:
    """torch.save's zip format, or its pre-1.6 format (a pickle that starts with torch's magic number)."""
    with path.open("rb") as file:
        head = file.read(len(LEGACY_TORCH_MAGIC))
    return head == LEGACY_TORCH_MAGIC or zipfile.is_zipfile(path)


def checkpoint_shapes(field: MlpField, output_channels: int) -> dict[str, tuple[int, ...]]:
    """Parameter shapes nerf-pytorch's NeRF has for this field's architecture, in its state-dict order."""
    shapes = {name: tuple(value.shape) for name, value in field.state_dict().items()}
    if field.config.use_viewdirs:
        return shapes
    width = field.config.width
    trunk = {name: shape for name, shape in shapes.items() if name.startswith("pts_linears.")}
    return {**trunk, "views_linears.0.weight": (width // 2, width), "views_linears.0.bias": (width // 2,),
            "output_linear.weight": (output_channels, width), "output_linear.bias": (output_channels,)}


def checked_state_dict(state: object, field: MlpField, output_channels: int, label: str) -> dict[str, torch.Tensor]:
    """A checkpoint state dict checked against the field's architecture -> the field's float32 state dict.

    label names the state dict in messages; the first missing, unexpected or misshapen parameter is refused.
    """
    if not isinstance(state, Mapping):
        raise UserError(f"{label} is not a state dict")
    expected = checkpoint_shapes(field, output_channels)
    missing = [name for name in expected if name not in state]
    if missing:
        raise UserError(f"{label} lacks parameter {missing[0]!r} that the config's architecture has")
    unexpected = [name for name in state if name not in expected]
    if unexpected:
        raise UserError(f"{label} has parameter {unexpected[0]!r} that the config's architecture lacks")
    for name, shape in expected.items():
        value = state[name]
        if not isinstance(value, torch.Tensor) or not value.is_floating_point():
            raise UserError(f"{label}[{name!r}] is not a floating-point tensor")
        if tuple(value.shape) != shape:
            raise UserError(f"{label}[{name!r}] has shape {tuple(value.shape)}, the config's architecture "
                            f"needs {shape}")
        if not torch.isfinite(value).all():
            raise UserError(f"{label}[{name!r}] holds NaN or infinite values")
    # only the first four output channels are read (rgb, density); a fifth one is nerf-pytorch's unused spare
    return {name: state[name].to(torch.float32)[:4] if name.startswith("output_linear.")
            else state[name].to(torch.float32) for name in field.state_dict()}


def load_fields(checkpoint: dict, config: NerfPytorchConfig, path: Path) -> tuple[MlpField, MlpField | None]:
    """The coarse (and fine) field with the checkpoint's weights, frozen, in eval mode."""
    fine_state = checkpoint.get(CHECKPOINT_FIELDS["fine"])
    if config.n_importance > 0 and fine_state is None:
        raise UserError(f"{path}: N_importance = {config.n_importance} needs a fine network, but the checkpoint "
                        f"has no {CHECKPOINT_FIELDS['fine']!r}")
    if config.n_importance == 0 and fine_state is not None:
        raise UserError(f"{path}: the checkpoint has a fine network but the config sets N_importance = 0")
    output_channels = 5 if config.n_importance > 0 else 4  # create_nerf's output_ch
    fields = []
    for role, field_config in zip(CHECKPOINT_FIELDS, field_configs(config)):
        if field_config is None:
            fields.append(None)
            continue
        field = MlpField(field_config)
        label = f"{path}: {CHECKPOINT_FIELDS[role]}"
        field.load_state_dict(checked_state_dict(checkpoint[CHECKPOINT_FIELDS[role]], field, output_channels, label))
        fields.append(field.eval().requires_grad_(False))
    return fields[0], fields[1]


def resolve_data_dir(datadir: str, config_path: Path) -> Path:
    """The config's datadir as nerf-pytorch saw it (relative to where it ran), else beside the config."""
    path = Path(datadir).expanduser()
    if path.is_absolute() or path.is_dir():
        return path
    beside_config = config_path.parent / path
    if beside_config.is_dir():
        return beside_config
    raise UserError(f"data folder {datadir!r} (the config's datadir) not found from the current folder nor from "
                    f"{config_path.parent.resolve()}; pass --data-dir")


def llff_world_bounds(data_dir: Path) -> tuple[float, float]:
    """no_ndc near/far: 0.9·min and 1.0·max of the depth bounds after load_llff_data's rescaling
    (which brings the smallest bound to 1 / bd_factor)."""
    _, bounds = read_poses_bounds(data_dir / "poses_bounds.npy")
    bounds = bounds.astype(np.float32)
    scaled = bounds * (1.0 / (bounds.min() * LLFF_BD_FACTOR))
    return float(scaled.min() * 0.9), float(scaled.max())


def frustum_aabb(cameras: tuple[Camera, ...], far: float) -> tuple[float, ...]:
    """The box around every camera's centre and its image corners at depth `far`: (6,) min then max."""
    points = []
    for camera in cameras:
        corner_x = np.array([0, camera.width, 0, camera.width], dtype=np.float32)
        corner_y = np.array([0, 0, camera.height, camera.height], dtype=np.float32)
        rays_o, rays_d = pixel_rays(camera, corner_x, corner_y)
        points += [rays_o[:1], rays_o + far * rays_d]
    points = np.concatenate(points)
    return tuple(float(v) for v in np.concatenate([points.min(axis=0), points.max(axis=0)]))


def half_resolution(camera: Camera) -> Camera:
    """load_blender_data(half_res=True): H // 2, W // 2, focal / 2, principal point at the new centre."""
    width, height = camera.width // 2, camera.height // 2
    return dataclasses.replace(camera, width=width, height=height, fx=camera.fx / 2, fy=camera.fy / 2,
                               cx=0.5 * width, cy=0.5 * height)


def scene_geometry(config: NerfPytorchConfig, data_dir: Path
                   ) -> tuple[tuple[Camera, ...], float, float, NDCSpace | None, tuple[float, ...]]:
    """Cameras (all splits, in order), near, far, NDC space and box, by nerf-pytorch's rules."""
    factor = config.factor if config.dataset_type == "llff" else None
    dataset = load_dataset(data_dir, with_images=False, background=config.background, factor=factor)
    cameras = dataset.cameras
    if config.dataset_type == "blender":
        if config.half_res:
            cameras = tuple(half_resolution(c) for c in cameras)
        return cameras, *BLENDER_BOUNDS, None, dataset.aabb
    if config.no_ndc:
        near, far = llff_world_bounds(data_dir)
        return cameras, near, far, None, frustum_aabb(cameras, far)
    return cameras, *NDC_BOUNDS, dataset.ndc, dataset.aabb  # the loader's NDC space is ndc_rays' (H, W, focal)


def import_nerf_pytorch(checkpoint: Path, config: Path, out_dir: Path, data_dir: Path | None = None,
                        grid_resolution: int = 64, force: bool = False) -> Scene:
    """Convert a nerf-pytorch checkpoint (with the config it was trained with) into a scene directory.

    data_dir overrides the config's datadir. Everything is checked before out_dir is created, so a
    refused import leaves nothing behind; an out_dir holding files is refused unless force and they are an
    earlier scene, which the new one then replaces whole (Scene.publish).
    """
    checkpoint, config_path, out_dir = Path(checkpoint), Path(config), Path(out_dir)
    check_scene_output(out_dir, force)
    settings = read_config(config_path)
    coarse, fine = load_fields(read_checkpoint(checkpoint), settings, checkpoint)
    data_dir = Path(data_dir) if data_dir is not None else resolve_data_dir(settings.datadir, config_path)
    cameras, near, far, ndc, aabb = scene_geometry(settings, data_dir)
    n_render = settings.n_samples + settings.n_importance
    render = RenderConfig(SamplingConfig(near, far, n_render), background=settings.background, ndc=ndc,
                          pixel_center=0.0)
    scene_config = SceneConfig(
        coarse=coarse.config, fine=fine.config if fine is not None else None,
        n_coarse=settings.n_samples if fine is not None else 0, n_importance=settings.n_importance,
        render=render, aabb=aabb, grid_resolution=grid_resolution, cameras=cameras, source="nerf-pytorch",
    )
    grid = build_occupancy_grid(render_field(coarse, fine), aabb, grid_resolution, step_size=(far - near) / n_render)
    scene = Scene(scene_config, coarse, fine, grid)
    scene.publish(out_dir, source=checkpoint, force=force)
    return scene
