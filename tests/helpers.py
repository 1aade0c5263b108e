"""Helpers the test modules share (no test module imports another's); fixtures live in conftest.py.

Only the standard library, numpy and the base install's packages at the top: tests/runtime_only imports
this where torch is not installed, so the torch side is imported inside the helpers that need it.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
import pytest


# ---- running the command lines --------------------------------------------------------------------

@dataclass(frozen=True)
class Result:
    code: int
    out: str
    err: str


def run_main(main, args, capfd) -> Result:
    """A CLI's main in-process, its exit code and what reached file descriptors 1 and 2."""
    capfd.readouterr()
    try:
        code = main([str(a) for a in args])
    except SystemExit as exit_:
        code = exit_.code
    out, err = capfd.readouterr()
    return Result(code, out, err)


def run_reveal(*args, cwd: Path | None = None, passphrase: bytes | None = None) -> subprocess.CompletedProcess:
    """`noisenerf-reveal ARGS` as a subprocess (python -m), stdin closed; NOISENERF_PASSPHRASE is `passphrase`
    or unset."""
    env = {key: value for key, value in os.environ.items() if key != "NOISENERF_PASSPHRASE"}
    if passphrase is not None:
        env["NOISENERF_PASSPHRASE"] = passphrase.decode()
    return subprocess.run([sys.executable, "-m", "noisenerf.cli.reveal", *map(str, args)], capture_output=True,
                          text=True, timeout=120, cwd=cwd, env=env, stdin=subprocess.DEVNULL)


def assert_refused(result: Result | subprocess.CompletedProcess, output: Path | None, message: str,
                   exact: bool = False, any_case: bool = False) -> None:
    """A refusal: exit code 2, nothing on stdout, exactly one stderr line `PROG: error: TEXT` and no traceback,
    TEXT holding `message` (being it, `exact`; in any case, `any_case`), and no `output` written (None: not
    checked). PROG is noisenerf-reveal for a reveal subprocess, noisenerf[ COMMAND] or noisenerf-reveal for a
    `Result`."""
    progs = ("noisenerf", "noisenerf-reveal")
    if isinstance(result, subprocess.CompletedProcess):
        progs = ("noisenerf-reveal",) if "noisenerf.cli.reveal" in result.args else ("noisenerf",)
        result = Result(result.returncode, result.stdout, result.stderr)
    lines = result.err.splitlines()
    assert result.code == 2, result
    assert len(lines) == 1 and "Traceback" not in result.err, result.err
    prog, _, text = lines[0].partition(": error: ")
    assert prog.split(" ")[0] in progs and text, lines[0]
    if any_case:
        message, text = message.lower(), text.lower()
    assert text == message if exact else message in text, lines[0]
    assert result.out == ""
    assert output is None or not os.path.lexists(output), output


def readme_python(heading: str) -> list[str]:
    """The ```python blocks of the README section under `heading`, in order."""
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = text.split(f"\n## {heading}\n", 1)[1].split("\n## ", 1)[0]
    return [block.split("```", 1)[0] for block in section.split("```python\n")[1:]]


def flip_first_float32(data: bytes) -> bytes:
    """A bundle's bytes with the lowest byte of its first float32 tensor flipped: still a readable bundle
    (a sealed one's tag fails)."""
    size = int.from_bytes(data[:8], "little")
    header = json.loads(data[8:8 + size])
    name = next(name for name, info in header.items() if name != "__metadata__" and info["dtype"] == "F32")
    at = 8 + size + header[name]["data_offsets"][0]
    return data[:at] + bytes([data[at] ^ 1]) + data[at + 1:]


# ---- tiny scenes and the reveal's inputs ----------------------------------------------------------

def tiny_fit(kind: str):
    """A fit config of `kind` ("mlp": the small preset, "hashgrid": its preset with the tiny random scenes'
    SMALL_HASHGRID, "nerfacto": its CPU preset with small tables, levels and sample counts) cut down for tests:
    few rays and samples, a 16³ occupancy grid."""
    from noisenerf.train.scene.fit import PRESETS, ProposalTraining, nerfacto_preset
    from noisenerf.train.scene.occupancy import OccupancyConfig
    from noisenerf.train.scene.random_scene import SMALL_HASHGRID

    if kind == "nerfacto":
        preset = nerfacto_preset("nerfacto", 12, 128, (32, 16), 16, 256)
        return dataclasses.replace(preset, proposal=ProposalTraining(anneal_steps=50, update_warmup=50))

    preset = PRESETS["small"] if kind == "mlp" else dataclasses.replace(PRESETS["hashgrid"], field=SMALL_HASHGRID)
    return dataclasses.replace(preset, batch_rays=256, n_samples=32, render_samples=None, warmup_rays=128,
                               warmup_samples=16, empty_points=256, precrop_steps=10,
                               occupancy=OccupancyConfig(resolution=16, warmup_steps=20, update_every=8))


def fitted_tiny_scene(folder: Path, kind: str, iters: int = 150):
    """A scene of `kind` fitted for `iters` steps (tiny_fit) on a 24 px procedural dataset in `folder`."""
    import torch

    from noisenerf.train.scene.datasets import load_dataset
    from noisenerf.train.scene.fit import Budget, fit
    from noisenerf.train.scene.procedural import write_procedural_dataset
    from noisenerf.train.scene.scene import load_scene

    data = write_procedural_dataset(folder / "data", size=24, n_train=12, n_val=0, n_test=2)
    fit(load_dataset(data), folder / "fitted", tiny_fit(kind), Budget(iters=iters), torch.device("cpu"),
        curve_seconds=0)
    return load_scene(folder / "fitted")


def make_tiny_scene(seed: int = 0, **kwargs):
    """A tiny scene with seeded random weights and a full occupancy grid (train/scene/random_scene.py)."""
    from noisenerf.train.scene.random_scene import random_scene

    return random_scene(seed, **kwargs)


@contextlib.contextmanager
def interrupted_after_saves(n: int):
    """Inside, a hide is interrupted (KeyboardInterrupt) right after its n-th saved part or block."""
    from noisenerf.train.hide import resume as resume_module

    original, saved = resume_module.ResumeStore.save, []

    def save_then_die(self, *args):
        original(self, *args)
        saved.append(args[:2])
        if len(saved) == n:
            raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(resume_module.ResumeStore, "save", save_then_die)
        yield


def lens_scene(model: str, seed: int = 0):
    """A random ring scene whose every camera has a lens: a phone's barrel distortion with all six terms ("opencv"),
    or a fisheye ("fisheye")."""
    import dataclasses

    from noisenerf.runtime.lens import Lens
    from noisenerf.train.scene.random_scene import random_scene

    lens = Lens("opencv", (-0.12, 0.03, -0.004, 0.0005, 0.001, -0.0008)) if model == "opencv" else \
        Lens("fisheye", (0.05, -0.01, 0.002, -0.0003, 0.0, 0.0))
    scene = random_scene(seed=seed)
    scene.config = dataclasses.replace(scene.config, cameras=tuple(dataclasses.replace(camera, lens=lens)
                                                                   for camera in scene.config.cameras))
    return scene


def two_tile_bundle(scene, layout: str = "ray", seed: int = 0, network: str | None = None):
    """Random noise in two views side by side, for `network` (None: no network field, as bundles made
    before it existed); the digest is that of torch's render of this very noise."""
    from noisenerf.runtime.bundle import Bundle, Tile, secret_digest
    from noisenerf.runtime.layouts import VectorNoise
    from noisenerf.runtime.reveal import reveal_tiles
    from noisenerf.train.scene.render import numpy_fields

    config, dims = scene.config.render, scene.render_field.config.noise_dims
    rng = np.random.default_rng(seed)
    tiles = []
    for i, camera in enumerate(scene.config.cameras[:2]):
        shape = (camera.height, camera.width) + ((config.sampling.n_samples,) if layout == "sample" else ())
        noise = rng.normal(size=shape + (dims,)).astype(np.float32)
        tiles.append(Tile((i * camera.width, 0, camera.width, camera.height), camera, config.sampling, VectorNoise(noise), i,
                          network))
    width, height = sum(t.rect[2] for t in tiles), tiles[0].rect[3]
    bundle = Bundle(scene.fingerprint(), width, height, "0" * 64, layout, dims, "float32", tuple(tiles), {})
    pixels = reveal_tiles(bundle, config, numpy_fields(scene.fields())).pixels
    return dataclasses.replace(bundle, secret_sha256=secret_digest(pixels))


def write_reveal_inputs(directory: Path) -> tuple[Path, Path]:
    """A tiny exported model and a two-tile bundle for it, in `directory` (its scene in directory/scene)."""
    from noisenerf.export.onnx_export import export_scene

    scene = make_tiny_scene(seed=4)
    scene.save(directory / "scene")
    export_scene(directory / "scene", directory / "model.onnx")
    two_tile_bundle(scene).save(directory / "secret.bundle")
    return directory / "model.onnx", directory / "secret.bundle"


# ---- bundle files as an attacker writes them ------------------------------------------------------

def mask_secret_of(owner) -> bytes:
    """The mask secret (runtime.masking) of a Scene, a loaded Model, or a model file's path."""
    from noisenerf.runtime.model import Model, load_model

    if isinstance(owner, Model):
        return owner.mask_secret
    if hasattr(owner, "digests"):
        return owner.digests().mask_secret
    return load_model(owner).mask_secret


def hidden_bundle(path: Path, owner):
    """The bundle at `path` hidden in `owner` (mask_secret_of's), read and checked, unmasked with it."""
    from noisenerf.runtime.bundle import load_bundle

    return load_bundle(path, mask_secret_of(owner))


def xor_masked_bytes(data: bytes, owner) -> bytes:
    """A bundle file's bytes with each tensor's data XORed with its keystream (runtime.masking) under the mask its
    metadata states and `owner`'s (mask_secret_of's) secret: a masked bundle unmasked, or an unmasked one with a mask
    stated masked. Bytes whose header or mask does not parse come back as they are."""
    from noisenerf.runtime.bundle import METADATA_KEY
    from noisenerf.runtime.errors import UserError
    from noisenerf.runtime.masking import checked_mask, keystream, mask_key

    try:
        size = int.from_bytes(data[:8], "little")
        header = json.loads(data[8:8 + size])
        salt = checked_mask(json.loads(header["__metadata__"][METADATA_KEY])["mask"])
    except (ValueError, KeyError, TypeError, UserError):
        return data
    key, body = mask_key(mask_secret_of(owner), salt), bytearray(data[8 + size:])
    for name, info in header.items():
        if name != "__metadata__":
            start, stop = info["data_offsets"]
            body[start:stop] = (np.frombuffer(bytes(body[start:stop]), np.uint8) ^ keystream(key, name, stop - start)).tobytes()
    return data[:8 + size] + bytes(body)


def bundle_contents(path: Path, owner=None) -> tuple[dict, dict[str, np.ndarray]]:
    """A bundle file's metadata (parsed JSON) and its tensors, without any validation: as stored, or unmasked with
    `owner` (mask_secret_of's) where the bundle is masked."""
    from safetensors import safe_open

    from noisenerf.runtime.bundle import METADATA_KEY
    from noisenerf.runtime.masking import checked_mask, mask_key, xor_masked

    with safe_open(str(path), framework="numpy") as handle:
        meta = json.loads(handle.metadata()[METADATA_KEY])
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    if owner is not None and meta.get("mask") is not None:
        tensors = xor_masked(tensors, mask_key(mask_secret_of(owner), checked_mask(meta["mask"])))
    return meta, tensors


def rewrite_bundle(source: Path, target: Path, edit, owner=None) -> Path:
    """`source` written to `target` after edit(meta, tensors) changed its metadata and tensors in place, bypassing
    validation. With `owner` (mask_secret_of's), a masked bundle's tensors are edited unmasked, and masked again
    under the salt its edited metadata states (none: left unmasked)."""
    from safetensors.numpy import save_file

    from noisenerf.runtime.bundle import METADATA_KEY
    from noisenerf.runtime.masking import checked_mask, mask_key, xor_masked

    meta, tensors = bundle_contents(source, owner)
    edit(meta, tensors)
    if owner is not None and meta.get("mask") is not None:
        tensors = xor_masked(tensors, mask_key(mask_secret_of(owner), checked_mask(meta["mask"])))
    save_file(tensors, str(target), metadata={METADATA_KEY: json.dumps(meta)})
    return target


def as_older_compact_format(version: int):
    """An edit for rewrite_bundle: a compact bundle as format `version` (2 or 3) stored it, its coefficients as
    plain byte planes (codec xz-byte-planes) and, for format 2, no branch escape tensors."""
    from noisenerf.runtime import interlaced
    from noisenerf.runtime.layouts import DTYPES, PLANES_CODEC, pack_coefficients, unpack_coefficients

    def edit(meta, tensors):
        noise = meta["noise"]
        meta.pop("mask", None)  # written unmasked, as formats before 5
        for tile in meta["tiles"]:
            name, (_, _, width, height) = tile["tensor"], tile["rect"]
            dtype = DTYPES[noise["dtype"]]
            codes = unpack_coefficients(tensors[name], (height, width, noise["coefficients"]), noise["dtype"], "test")
            tensors[name] = pack_coefficients(interlaced.decode(codes, tile.pop("band_rows")).astype(dtype))
            if version < 3:
                del tensors[f"{name}_branch_escapes"], tensors[f"{name}_branch_escape_noise"]
        meta.update(format_version=version)
        noise.update(codec=PLANES_CODEC)
    return edit


# ---- images and dataset folders -------------------------------------------------------------------

def write_raw(path: Path, pixels: np.ndarray, pixel_type: str = "uint8", unassociated: bool = False) -> Path:
    """Pixels written with OpenImageIO directly, independent of write_image (`unassociated`: straight alpha)."""
    spec = oiio.ImageSpec(pixels.shape[1], pixels.shape[0], pixels.shape[2], pixel_type)
    if unassociated:
        spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(pixels)
    out.close()
    return path


def read_raw(path: Path) -> np.ndarray:
    """Pixels as stored (alpha not premultiplied), read with OpenImageIO directly."""
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)
    image = oiio.ImageInput.open(str(path), config)
    pixels = image.read_image(oiio.UNKNOWN)
    image.close()
    return pixels


def write_png(path: Path, pixels: np.ndarray) -> Path:
    """An 8-bit straight-alpha PNG, its folder made as needed."""
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_raw(path, pixels, "uint8", unassociated=True)


def write_blender(folder: Path, frames: dict[str, list], camera_angle_x: float, file_suffix: str = "") -> Path:
    """A NeRF-Synthetic folder: per split, transforms_{split}.json and {split}/r_{k}.png for each
    (pixels, c2w) frame; `file_suffix` is the extension the JSON's file paths carry (nerf-pytorch's have none)."""
    for split, split_frames in frames.items():
        entries = []
        for k, (pixels, c2w) in enumerate(split_frames):
            write_png(folder / split / f"r_{k}{file_suffix or '.png'}", pixels)
            entries.append({"file_path": f"./{split}/r_{k}{file_suffix}", "rotation": 0.0,
                            "transform_matrix": np.asarray(c2w).tolist()})
        (folder / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": camera_angle_x,
                                                                     "frames": entries}))
    return folder


def write_llff(folder: Path, c2ws, hwf, bounds, factors, shade: int, extra_images: int = 0) -> np.ndarray:
    """An LLFF folder: poses_bounds.npy (LLFF's [down, right, back, t | h, w, f] columns, then near and far)
    for OpenGL camera-to-worlds `c2ws`, and per factor images_F/imageNNN.png, image k flat grey shade·k,
    `extra_images` more than there are poses. Returns the poses_bounds array."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = [np.concatenate([np.stack([-c2w[:3, 1], c2w[:3, 0], c2w[:3, 2], c2w[:3, 3], hwf], axis=1).ravel(), near_far])
            for c2w, near_far in zip(c2ws, bounds)]
    poses_bounds = np.asarray(rows)
    np.save(folder / "poses_bounds.npy", poses_bounds)
    height, width = int(hwf[0]), int(hwf[1])
    for factor in factors:
        for k in range(len(rows) + extra_images):
            write_png(folder / f"images_{factor}" / f"image{k:03d}.png",
                      np.full((height // factor, width // factor, 3), shade * k, np.uint8))
    return poses_bounds


def turning_llff(folder: Path, n: int = 9, full=(60, 80, 70.0), factors=(2, 4), extra_images: int = 0) -> np.ndarray:
    """A small LLFF folder: n cameras turning 0.1 rad apart about y at seeded random centres, images 10·k grey."""
    rng = np.random.default_rng(3)
    c2ws = []
    for k in range(n):
        angle = 0.1 * k
        right, up = np.array([math.cos(angle), 0.0, -math.sin(angle)]), np.array([0.0, 1.0, 0.0])
        c2ws.append(np.stack([right, up, np.cross(right, up), rng.normal(size=3)], axis=1))
    return write_llff(folder, c2ws, full, [[2.0 + 0.1 * k, 20.0] for k in range(n)], factors, 10, extra_images)


# ---- nerfstudio run directories --------------------------------------------------------------------

NERFSTUDIO_CONFIG = """!!python/object:nerfstudio.engine.trainer.TrainerConfig
_target: !!python/name:nerfstudio.engine.trainer.Trainer ''
data: null
method_name: {method}
output_dir: !!python/object/apply:pathlib.PosixPath
- outputs
machine: !!python/object:nerfstudio.configs.base_config.MachineConfig
  device_type: cpu
  seed: 42
pipeline: !!python/object:nerfstudio.pipelines.base_pipeline.VanillaPipelineConfig
  _target: !!python/name:nerfstudio.pipelines.base_pipeline.VanillaPipeline ''
  datamanager: !!python/object:nerfstudio.data.datamanagers.parallel_datamanager.ParallelDataManagerConfig
    data: null
    dataparser: !!python/object:nerfstudio.data.dataparsers.nerfstudio_dataparser.NerfstudioDataParserConfig
      _target: !!python/name:nerfstudio.data.dataparsers.nerfstudio_dataparser.Nerfstudio ''
      data: !!python/object/apply:pathlib.PosixPath
      - data
      downscale_factor: {downscale}
    eval_image_indices: !!python/tuple
    - 0
  model: !!python/object:nerfstudio.models.nerfacto.NerfactoModelConfig
    _target: !!python/name:nerfstudio.models.{model} ''
    appearance_embed_dim: 32
    average_init_density: 0.01
    background_color: last_sample
    base_res: 16
    disable_scene_contraction: false
    far_plane: 1000.0
    features_per_level: 2
    hidden_dim: 64
    hidden_dim_color: 64
    implementation: {implementation}
    log2_hashmap_size: 10
    max_res: 256
    near_plane: 0.05
    num_levels: 8
    num_nerf_samples_per_ray: 48
    num_proposal_iterations: 2
    num_proposal_samples_per_ray: !!python/tuple
    - 256
    - 96
    proposal_initial_sampler: piecewise
    proposal_net_args_list:
    - hidden_dim: 16
      log2_hashmap_size: 8
      max_res: 64
      num_levels: 5
      use_linear: false
    - hidden_dim: 16
      log2_hashmap_size: 8
      max_res: 128
      num_levels: 5
      use_linear: false
    use_appearance_embedding: true
    use_average_appearance_embedding: true
    use_same_proposal_network: false
relative_model_dir: !!python/object/apply:pathlib.PosixPath
- nerfstudio_models
{extra}"""


def nerfstudio_layout(implementation: str) -> dict[str, tuple[int, ...]]:
    """The pipeline tensors (under `_model.`) of NERFSTUDIO_CONFIG's nerfacto, by the research notes' layout:
    torch runs per module, tcnn runs as flat parameter vectors (MLP matrices padded to 16, then the grid)."""
    def grid_rows(levels, log2, max_res):
        b = math.exp((math.log(max_res) - math.log(16)) / (levels - 1))
        if implementation == "torch":
            return levels << log2
        rows = 0
        for level in range(levels):
            res = math.ceil(16 * b ** level - 1) + 1
            rows += min(-(-res ** 3 // 8) * 8, 1 << log2)
        return rows
    shapes = {"field.embedding_appearance.embedding.weight": (7, 32)}
    proposals = ((5, 8, 64), (5, 8, 128))
    if implementation == "torch":
        shapes.update({"field.mlp_base.model.0.hash_table": (grid_rows(8, 10, 256), 2),
                       "field.mlp_base.model.1.layers.0.weight": (64, 16), "field.mlp_base.model.1.layers.0.bias": (64,),
                       "field.mlp_base.model.1.layers.1.weight": (16, 64), "field.mlp_base.model.1.layers.1.bias": (16,)})
        for i, (a, b) in enumerate(((63, 64), (64, 64), (64, 3))):
            shapes[f"field.mlp_head.layers.{i}.weight"], shapes[f"field.mlp_head.layers.{i}.bias"] = (b, a), (b,)
        for i, grid in enumerate(proposals):
            net = f"proposal_networks.{i}"
            shapes[f"{net}.encoding.hash_table"] = shapes[f"{net}.mlp_base.0.hash_table"] = (grid_rows(*grid), 2)
            for j, (a, b) in enumerate(((10, 16), (16, 1))):
                shapes[f"{net}.mlp_base.1.layers.{j}.weight"], shapes[f"{net}.mlp_base.1.layers.{j}.bias"] = (b, a), (b,)
        return shapes
    shapes["field.mlp_base.model.params"] = (64 * 16 + 16 * 64 + grid_rows(8, 10, 256) * 2,)
    shapes["field.mlp_head.tcnn_encoding.params"] = (64 * 64 + 64 * 64 + 16 * 64,)
    shapes["field.direction_encoding.tcnn_encoding.params"] = (0,)
    for i, grid in enumerate(proposals):
        net = f"proposal_networks.{i}"
        shapes[f"{net}.encoding.tcnn_encoding.params"] = shapes[f"{net}.mlp_base.0.tcnn_encoding.params"] = (
            grid_rows(*grid) * 2,)
        shapes[f"{net}.mlp_base.1.tcnn_encoding.params"] = (16 * 16 + 16 * 16,)
    return shapes


def write_nerfstudio_run(folder: Path, implementation: str, seed: int = 0, prefix: str = "_model.",
                         config_extra: str = "", method: str = "nerfacto", model: str = "nerfacto.NerfactoModel",
                         shapes: dict | None = None, downscale: str = "null") -> tuple[Path, Path]:
    """A nerfstudio run directory as nerfstudio 1.x writes one (a tagged config.yml, dataparser_transforms.json,
    nerfstudio_models/step-*.ckpt whose optimizer state holds numpy scalars, LPIPS and camera-optimizer keys
    beside the model's) with random weights in the nerfacto layout, and its dataset (transforms.json, 7
    frames listed out of name order). -> (run directory, data directory)."""
    import torch

    rng = np.random.default_rng(seed)
    data, run = folder / "data", folder / "outputs" / "scene" / "nerfacto" / "2026-01-01_000000"
    (run / "nerfstudio_models").mkdir(parents=True)
    data.mkdir()
    frames = []
    for k in rng.permutation(7):  # around the origin, looking at it, OpenGL axes (nerfstudio's)
        angle = 2 * math.pi * k / 7
        eye = np.array([3 * math.cos(angle), 3 * math.sin(angle), 1.0])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(right, forward), -forward], 1)
        pose[:3, 3] = eye
        frames.append({"file_path": f"images/frame_{k:05d}.png", "transform_matrix": pose.tolist()})
    meta = {"camera_model": "OPENCV", "fl_x": 11.0, "fl_y": 10.5, "cx": 6.2, "cy": 4.9, "w": 12, "h": 10,
            "k1": 0.0, "k2": 0.0, "p1": 0.0, "p2": 0.0, "frames": frames}
    (data / "transforms.json").write_text(json.dumps(meta))
    angle = 0.3
    transform = [[math.cos(angle), -math.sin(angle), 0.0, 0.1], [math.sin(angle), math.cos(angle), 0.0, -0.2],
                 [0.0, 0.0, 1.0, 0.05]]
    (run / "dataparser_transforms.json").write_text(json.dumps({"transform": transform, "scale": 0.3}))
    (run / "config.yml").write_text(NERFSTUDIO_CONFIG.format(implementation=implementation, method=method,
                                                             model=model, extra=config_extra, downscale=downscale))
    pipeline = {}
    for name, shape in (shapes or nerfstudio_layout(implementation)).items():
        scale = 0.3 if "table" in name or "encoding.tcnn" in name or "model.params" in name else 0.4
        pipeline[prefix + name] = torch.from_numpy(rng.uniform(-scale, scale, shape).astype(np.float32))
    pipeline[prefix + "lpips.net.slice1.0.weight"] = torch.zeros(4, 3, 3, 3)
    pipeline[prefix + "camera_optimizer.pose_adjustment"] = torch.zeros(7, 6)
    pipeline[prefix + "field.aabb"] = torch.tensor([[-1.0, -1.0, -1.0], [1.0, 1.0, 1.0]])
    checkpoint = {"step": 99, "pipeline": pipeline,
                  "optimizers": {"fields": {"param_groups": [{"lr": np.float64(0.01), "eps": 1e-15}]}},
                  "schedulers": {"fields": {"_last_lr": [np.float64(0.0099)]}}, "scalers": {}}
    torch.save(checkpoint, run / "nerfstudio_models" / "step-000000099.ckpt")
    torch.save({"step": 9}, run / "nerfstudio_models" / "step-000000009.ckpt")  # an older one: not loaded
    return run, data


HASH_PRIMES = (1, 2654435761, 805459861)  # tiny-cuda-nn's, written here as the spec


def spec_grid(unit, values, levels, log2, max_res, implementation, features=2, base=16, per_level_scale=None):
    """Interpolated features (n, levels·F): tcnn §2.1 (params laid out level, entry, feature) or nerfstudio's
    torch grid §2.2 (table (levels·T, F), every level hashed, ceil/floor corners, no +0.5). The growth per level:
    per_level_scale, else from max_res (research/nerfacto-import.md)."""
    import torch

    b = per_level_scale or math.exp((math.log(max_res) - math.log(base)) / (levels - 1))
    size, out, offset = 1 << log2, [], 0
    for level in range(levels):
        if implementation == "tcnn":
            scale = base * b ** level - 1
            res = math.ceil(scale) + 1
            rows = min(-(-res ** 3 // 8) * 8, size)
            position = unit * scale + 0.5
            lower = np.floor(position)
            upper = lower + 1
        else:
            scale = float(torch.floor(base * b ** torch.arange(levels))[level])  # nerfstudio's expression: float32
            res, rows = None, size
            position = unit * scale
            lower, upper = np.floor(position), np.ceil(position)
        fraction = position - lower
        total = np.zeros((len(unit), features))
        for corner in range(8):
            bits = [(corner >> d) & 1 for d in range(3)]
            vertex = np.stack([np.where(bit, upper[:, d], lower[:, d]) for d, bit in enumerate(bits)], 1).astype(np.int64)
            weight = np.prod([np.where(bit, fraction[:, d], 1 - fraction[:, d]) for d, bit in enumerate(bits)], 0)
            if res is not None and res ** 3 <= rows:
                index = (vertex[:, 0] + vertex[:, 1] * res + vertex[:, 2] * res * res) % rows
            else:
                index = (vertex[:, 0] * HASH_PRIMES[0] ^ vertex[:, 1] * HASH_PRIMES[1] ^ vertex[:, 2] * HASH_PRIMES[2]) % rows
            total += weight[:, None] * values[offset + index]
        out.append(total)
        offset += rows
    return np.concatenate(out, 1)


def tcnn_mlp(params, x, widths, pad_value):
    """tiny-cuda-nn: input padded to 16 with `pad_value`, row-major matrices without bias, outputs padded."""
    pad = lambda n: -(-n // 16) * 16  # noqa: E731
    h = np.concatenate([x, np.full((len(x), pad(x.shape[1]) - x.shape[1]), pad_value)], 1)
    at = 0
    for i, out in enumerate(widths):
        rows = pad(out) if i == len(widths) - 1 else out
        matrix = params[at:at + rows * h.shape[1]].reshape(rows, h.shape[1])
        at += matrix.size
        h = h @ matrix.T
        if i < len(widths) - 1:
            h = np.maximum(h, 0)
    return h[:, :widths[-1]], at


def tcnn_sh(d: np.ndarray) -> np.ndarray:
    """tiny-cuda-nn's real spherical harmonics of degree 4 of unit directions, written out (the spec the
    field kinds' SH matrix is checked against). (n, 3) -> (n, 16)."""
    x, y, z = d.T
    return np.stack([
        np.full_like(x, 0.28209479177387814), -0.48860251190291987 * y, 0.48860251190291987 * z,
        -0.48860251190291987 * x, 1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
        0.94617469575755997 * z * z - 0.31539156525251999, -1.0925484305920792 * x * z,
        0.54627421529603959 * (x * x - y * y), 0.59004358992664352 * y * (-3 * x * x + y * y),
        2.8906114426405538 * x * y * z, 0.45704579946446572 * y * (1 - 5 * z * z),
        0.3731763325901154 * z * (5 * z * z - 3), 0.45704579946446572 * x * (1 - 5 * z * z),
        1.4453057213202769 * z * (x * x - y * y), 0.59004358992664352 * x * (-x * x + 3 * y * y)], 1)


NERFSTUDIO_GOLDENS = Path(__file__).parent / "goldens" / "nerfacto_torch"
# runs nerfstudio 1.1.5 trained (tools/nerfstudio_train_tiny.py): a pinhole capture, an OPENCV one, an OPENCV_FISHEYE one
NERFSTUDIO_RUNS = tuple(NERFSTUDIO_GOLDENS.parent / name for name in ("nerfacto_torch", "nerfacto_opencv", "nerfacto_fisheye"))
# an instant-ngp run made by nerfstudio's own classes on the CPU (tools/nerfstudio_ngp_goldens.py: not trained)
NGP_GOLDENS = NERFSTUDIO_GOLDENS.parent / "ngp_torch"


def assert_hides_exactly(folder: Path, secret: Path, view: int, capfd) -> Path:
    """`noisenerf hide` of the image `secret` in folder/scene at `view` succeeds, and `noisenerf-reveal` of its
    bundle through folder/model.onnx says it is exact. -> the bundle (beside the secret)."""
    from noisenerf.cli.main import main

    bundle = secret.with_suffix(".bundle")
    result = run_main(main, ["hide", folder / "scene", secret, "-o", bundle, "--view", view], capfd)
    assert result.code in (0, None), result.err
    revealed = run_reveal(folder / "model.onnx", bundle, "-o", secret.with_name(f"{secret.stem}_out.png"))
    assert revealed.returncode == 0 and "exact" in revealed.stdout, revealed.stdout + revealed.stderr
    return bundle


def assert_photos_hide_exactly(folder: Path, photos, views, tmp_path: Path, capfd) -> None:
    """Each photo (40 px wide) hidden with `noisenerf hide` in folder/scene at its view reveals exactly through
    folder/model.onnx: `noisenerf-reveal` says so, and `noisenerf.reveal` gives the photo's pixels."""
    import noisenerf
    from noisenerf.runtime.images import load_secret

    for photo, view in zip(photos, views, strict=True):
        pixels = load_secret(photo)[0]
        step = max(1, pixels.shape[1] // 40)
        secret = write_png(tmp_path / f"{view}.png", np.ascontiguousarray(pixels[::step, ::step][:40, :40]))
        through_api = noisenerf.reveal(folder / "model.onnx", assert_hides_exactly(folder, secret, view, capfd))
        assert through_api.exact and np.array_equal(through_api.pixels, load_secret(secret)[0])


def nerfstudio_run_from_goldens(folder: Path, goldens: Path = NERFSTUDIO_GOLDENS) -> tuple[Path, Path]:
    """The goldens' run (tests/goldens/nerfacto_*, a run nerfstudio trained: `goldens`) rebuilt as nerfstudio wrote it:
    its config.yml and dataparser_transforms.json as they are, the checkpoint's model tensors in a step-*.ckpt
    with numpy-scalar optimizer state, its transforms.json. -> (run directory, data directory)."""
    import shutil

    import torch
    from safetensors.numpy import load_file

    run, data = folder / "run", folder / "data"
    (run / "nerfstudio_models").mkdir(parents=True)
    data.mkdir()
    for name in ("config.yml", "dataparser_transforms.json"):
        shutil.copy(goldens / name, run / name)
    shutil.copy(goldens / "transforms.json", data / "transforms.json")
    pipeline = {k: torch.from_numpy(v) for k, v in load_file(goldens / "weights.safetensors").items()}
    torch.save({"step": 549, "pipeline": pipeline, "optimizers": {"fields": {"param_groups": [{"lr": np.float64(1e-2)}]}},
                "scalers": {}}, run / "nerfstudio_models" / "step-000000549.ckpt")
    return run, data


# ---- Instant-NGP snapshots, written from the documented format (train/scene/import_ingp.py's docstring) ---

@dataclass(frozen=True)
class IngpNetwork:
    """An Instant-NGP NeRF network config: configs/nerf/base.json's shape (8 levels x 4 features, 2^19, density MLP
    64 x 1 hidden, colour MLP 64 x 2 hidden) unless told otherwise."""

    levels: int = 8
    features: int = 4
    log2_table: int = 19
    base_resolution: int = 16
    aabb_scale: int = 1
    width: int = 64
    colour_layers: int = 2
    stated_scale: float | None = None  # the config's per_level_scale, where it states one

    @property
    def per_level_scale(self) -> float:
        """The stated one, else testbed.cu:4245–4252's, in float32."""
        if self.stated_scale is not None:
            return self.stated_scale
        ratio = np.float32(2048.0 * self.aabb_scale / self.base_resolution)
        return float(np.exp(np.float32(np.log(ratio)) / np.float32(self.levels - 1)))

    def grid_rows(self) -> int:
        rows = 0
        for level in range(self.levels):
            scale = np.float32(np.exp2(np.float32(level * np.log2(np.float32(self.per_level_scale))))
                               * self.base_resolution - 1)
            res = int(math.ceil(scale)) + 1
            rows += min(-(-res ** 3 // 8) * 8, 1 << self.log2_table)
        return rows

    def matrices(self) -> list[tuple[int, int]]:
        """(rows, columns) of each tiny-cuda-nn matrix in the snapshot's order: density, then colour."""
        pad = lambda n: -(-n // 16) * 16  # noqa: E731
        w = self.width
        return ([(w, pad(self.levels * self.features)), (16, w), (w, 32)]
                + [(w, w)] * (self.colour_layers - 1) + [(16, w)])


def ngp_parameters(network: IngpNetwork, seed: int) -> np.ndarray:
    """Random parameters of `network`, as float16 values: MLPs ~ N(0, 2/fan_in), grid features ±0.5 (wider
    than tiny-cuda-nn's ±1e-4 init, so renders show structure). -> (n_params,) float16."""
    rng = np.random.default_rng(seed)
    parts = [rng.normal(0, math.sqrt(2 / columns), rows * columns) for rows, columns in network.matrices()]
    parts.append(rng.uniform(-0.5, 0.5, network.grid_rows() * network.features))
    return np.concatenate(parts).astype(np.float16)


def look_at_cameras(n: int, radius: float, centre, size: int, seed: int) -> list[np.ndarray]:
    """n OpenGL camera-to-world (4, 4) matrices on a sphere around `centre`, looking at it, up +y."""
    rng = np.random.default_rng(seed)
    poses = []
    for _ in range(n):
        direction = rng.normal(size=3)
        direction[1] = abs(direction[1]) + 0.3
        position = np.asarray(centre, np.float64) + radius * direction / np.linalg.norm(direction)
        back = (position - centre) / np.linalg.norm(position - centre)
        right = np.cross([0.0, 1.0, 0.0], back)
        right /= np.linalg.norm(right)
        pose = np.eye(4)
        pose[:3, :3] = np.stack([right, np.cross(back, right), back], 1)
        pose[:3, 3] = position
        poses.append(pose)
    return poses


def ngp_snapshot(network: IngpNetwork, params: np.ndarray, poses_ngp: list[np.ndarray], size: int, *,
                 params_type: str = "__half", mode: str = "nerf", lens: dict | None = None,
                 state_per_level_scale: bool = True, focal: float | None = None) -> dict:
    """The msgpack object Instant-NGP's save_snapshot writes (src/testbed.cu:5288–5345): base.json's config and the
    snapshot; `poses_ngp`: cameras in Instant-NGP's frame, OpenGL axes (turned into its own, y and z flipped)."""
    encoding = {"otype": "HashGrid", "n_levels": network.levels, "n_features_per_level": network.features,
                "log2_hashmap_size": network.log2_table, "base_resolution": network.base_resolution}
    if state_per_level_scale:
        encoding["per_level_scale"] = network.per_level_scale
    binary = params.astype(np.float16 if params_type == "__half" else np.float32).astype("<f2" if params_type ==
                                                                                        "__half" else "<f4").tobytes()
    half = 0.5 * min(network.aabb_scale, 128)
    xforms = [{"start": (pose[:3] * np.array([1.0, -1.0, -1.0, 1.0])).tolist(),
               "end": (pose[:3] * np.array([1.0, -1.0, -1.0, 1.0])).tolist()} for pose in poses_ngp]
    focal = focal or size * 1.1
    metadata = [{"focal_length": [focal, focal], "principal_point": [0.5, 0.5], "resolution": [size, size],
                 "rolling_shutter": [0.0, 0.0, 0.0, 0.0], "lens": lens} for _ in poses_ngp]
    return {
        "loss": {"otype": "Huber"}, "optimizer": {"otype": "Ema", "decay": 0.95},
        "encoding": encoding,
        "network": {"otype": "FullyFusedMLP", "activation": "ReLU", "output_activation": "None",
                    "n_neurons": network.width, "n_hidden_layers": 1},
        "dir_encoding": {"otype": "Composite", "nested": [{"n_dims_to_encode": 3, "otype": "SphericalHarmonics",
                                                           "degree": 4}, {"otype": "Identity"}]},
        "rgb_network": {"otype": "FullyFusedMLP", "activation": "ReLU", "output_activation": "None",
                        "n_neurons": network.width, "n_hidden_layers": network.colour_layers},
        "snapshot": {
            "n_params": int(params.size), "params_type": params_type, "params_binary": binary,
            "version": 1, "mode": mode, "density_grid_size": 128,
            "density_grid_binary": np.zeros(128 ** 3, np.float16).tobytes(),
            "nerf": {"aabb_scale": network.aabb_scale, "cam_pos_offset": [], "cam_rot_offset": [],
                     "extra_dims_opt": [], "rgb": {"rays_per_batch": 4096, "measured_batch_size": 0,
                                                   "measured_batch_size_before_compaction": 0},
                     "dataset": {"n_images": len(poses_ngp), "paths": [f"images/{k}.png" for k in range(len(poses_ngp))],
                                 "metadata": metadata, "xforms": xforms,
                                 "render_aabb": {"min": [0.5 - half] * 3, "max": [0.5 + half] * 3},
                                 "render_aabb_to_local": [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
                                 "up": [0.0, 1.0, 0.0], "offset": [0.5, 0.5, 0.5], "envmap_resolution": [0, 0],
                                 "scale": 0.33, "aabb_scale": network.aabb_scale, "from_mitsuba": False,
                                 "is_hdr": False, "wants_importance_sampling": True, "n_extra_learnable_dims": 0}},
            "training_step": 1000, "loss": 0.01,
            "aabb": {"min": [0.5 - half] * 3, "max": [0.5 + half] * 3}, "bounding_radius": 1.0,
            "background_color": [0.0, 0.0, 0.0, 1.0], "exposure": 0.0,
            "camera": {"matrix": [[1.0, 0.0, 0.0, 0.5], [0.0, -1.0, 0.0, 0.5], [0.0, 0.0, -1.0, 0.5]]},
        },
    }


def write_ingp(path: Path, snapshot: dict) -> Path:
    """msgpack, then gzip as zstr deflates a `.ingp` (window bits 15 + 16); a `.msgpack` raw."""
    import gzip

    import msgpack

    data = msgpack.packb(snapshot, use_bin_type=True)
    path.write_bytes(gzip.compress(data, 6) if path.suffix == ".ingp" else data)
    return path


def ngp_spec_field(network: IngpNetwork, params: np.ndarray, points: np.ndarray, directions: np.ndarray,
                   aabb) -> tuple[np.ndarray, np.ndarray]:
    """Instant-NGP's field written from its code's description (nerf_network.h, nerf_device.cuh), float64, on the
    snapshot's flat parameters: grid of (p − min)/(max − min), density MLP → 16 outputs, σ = exp(out[0]); colour
    MLP on [16 outputs ‖ SH(d)], logistic. -> rgb (n, 3), σ (n,)."""
    flat = params.astype(np.float64)
    mlp_sizes = sum(rows * columns for rows, columns in network.matrices())
    lo, hi = np.asarray(aabb[:3], np.float64), np.asarray(aabb[3:], np.float64)
    unit = np.clip((points - lo) / (hi - lo), 0, 1)
    features = spec_grid(unit, flat[mlp_sizes:].reshape(-1, network.features), network.levels, network.log2_table,
                         None, "tcnn", network.features, network.base_resolution, network.per_level_scale)
    density, used = tcnn_mlp(flat, features, (network.width, 16), 0.0)
    colour_in = np.concatenate([density, tcnn_sh(directions.astype(np.float64))], 1)
    widths = (network.width,) * network.colour_layers + (3,)
    raw_rgb, _ = tcnn_mlp(flat[used:], colour_in, widths, 1.0)
    return 1 / (1 + np.exp(-raw_rgb)), np.exp(density[:, 0])


def scene_snapshot(scene) -> tuple[dict, IngpNetwork, np.ndarray]:
    """A hash-grid scene fitted with FitConfig.tcnn_layout (Instant-NGP's own network) written as Instant-NGP's
    snapshot: its box [−h, h]³ as Instant-NGP's with aabb_scale 2h (scale 1, offset 0.5), its MLPs as tiny-cuda-nn's
    matrices (the density MLP's copy of the raw density dropped, the colour MLP's columns as [density outputs ‖
    SH], outputs padded to 16), its table as the grid; its cameras (square, centred). -> (snapshot, network,
    params)."""
    config = scene.config.coarse
    weights = {name.split(".", 1)[1]: value for name, value in scene.weight_arrays().items()}
    half = config.aabb[3]
    assert config.aabb == (-half,) * 3 + (half,) * 3 and float(2 * half).is_integer() and config.geo_features == 16
    network = IngpNetwork(config.levels, config.features, config.log2_table, config.base_resolution, int(2 * half),
                          config.density_hidden, config.colour_layers, np.float32(config.per_level_scale).item())
    density1 = weights["density_linears.1.weight"]
    assert np.array_equal(density1[0], density1[1])
    colour0 = weights["colour_linears.0.weight"]
    last = weights[f"colour_linears.{config.colour_layers}.weight"]
    matrices = [weights["density_linears.0.weight"], density1[1:], np.concatenate([colour0[:, 16:], colour0[:, :16]], 1),
                *(weights[f"colour_linears.{i}.weight"] for i in range(1, config.colour_layers)),
                np.concatenate([last, np.zeros((13, last.shape[1]), np.float32)])]
    params = np.concatenate([m.ravel() for m in matrices] + [weights["table"].ravel()]).astype(np.float16)
    poses = []
    for camera in scene.config.cameras:
        pose = camera.matrix().astype(np.float64)
        pose[:3, 3] += 0.5  # Instant-NGP's offset
        poses.append(pose)
    first = scene.config.cameras[0]
    assert first.width == first.height and first.cx == first.width / 2
    return ngp_snapshot(network, params, poses, first.width, focal=first.fx), network, params
