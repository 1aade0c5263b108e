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
    SMALL_HASHGRID) cut down for tests: few rays and samples, a 16³ occupancy grid."""
    from noisenerf.train.scene.fit import PRESETS
    from noisenerf.train.scene.occupancy import OccupancyConfig
    from noisenerf.train.scene.random_scene import SMALL_HASHGRID

    preset = PRESETS["small"] if kind == "mlp" else dataclasses.replace(PRESETS["hashgrid"], field=SMALL_HASHGRID)
    return dataclasses.replace(preset, batch_rays=256, n_samples=32, warmup_rays=128, warmup_samples=16,
                               empty_points=256, precrop_steps=10,
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
    """Inside, a hide is interrupted (KeyboardInterrupt) right after its n-th saved chunk or block."""
    from noisenerf.train.hide import progress as progress_module

    original, saved = progress_module.Progress.save, []

    def save_then_die(self, *args):
        original(self, *args)
        saved.append(args[:2])
        if len(saved) == n:
            raise KeyboardInterrupt

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(progress_module.Progress, "save", save_then_die)
        yield


def two_tile_bundle(scene, layout: str = "ray", seed: int = 0, network: str | None = None):
    """Random noise in two views side by side, for `network` (None: no network field, as bundles made
    before it existed); the digest is that of torch's render of this very noise."""
    from noisenerf.runtime.bundle import Bundle, Tile, secret_digest
    from noisenerf.runtime.layouts import VectorNoise
    from noisenerf.runtime.reveal import reveal
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
    pixels = reveal(bundle, config, numpy_fields(scene.fields())).pixels
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

def bundle_contents(path: Path) -> tuple[dict, dict[str, np.ndarray]]:
    """A bundle file's metadata (parsed JSON) and its tensors as stored, without any validation."""
    from safetensors import safe_open

    from noisenerf.runtime.bundle import METADATA_KEY

    with safe_open(str(path), framework="numpy") as handle:
        meta = json.loads(handle.metadata()[METADATA_KEY])
        tensors = {name: handle.get_tensor(name) for name in handle.keys()}
    return meta, tensors


def rewrite_bundle(source: Path, target: Path, edit) -> Path:
    """`source` written to `target` after edit(meta, tensors) changed its metadata and tensors in place,
    bypassing validation."""
    from safetensors.numpy import save_file

    from noisenerf.runtime.bundle import METADATA_KEY

    meta, tensors = bundle_contents(source)
    edit(meta, tensors)
    save_file(tensors, str(target), metadata={METADATA_KEY: json.dumps(meta)})
    return target


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
