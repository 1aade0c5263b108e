"""Helpers the test modules share (no test module imports another's); fixtures live in conftest.py.

Only the standard library, numpy and the base install's packages at the top: tests/runtime_only imports
this where torch is not installed, so the torch side is imported inside the helpers that need it.
"""

from __future__ import annotations

import contextlib
from dataclasses import dataclass

import numpy as np
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


# ---- tiny scenes and the reveal's inputs ----------------------------------------------------------

def tiny_scene_config(ndc: bool = False, fine: bool = False, width: int = 32, depth: int = 3):
    """A small random-weight scene config looking at the origin from the sphere of radius 4."""
    from noisenerf.runtime.camera import Camera, NDCSpace
    from noisenerf.runtime.render import RenderConfig
    from noisenerf.runtime.sampling import SamplingConfig
    from noisenerf.train.scene.field import FieldConfig
    from noisenerf.train.scene.scene import SceneConfig

    cameras = []
    for angle in np.linspace(0, 2 * np.pi, 6, endpoint=False):
        eye = np.array([4 * np.sin(angle), -4 * np.cos(angle), 1.0])
        forward = -eye / np.linalg.norm(eye)
        right = np.cross(forward, [0, 0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, forward)
        c2w = np.eye(4)
        c2w[:3, 0], c2w[:3, 1], c2w[:3, 2], c2w[:3, 3] = right, up, -forward, eye
        cameras.append(Camera.from_fov(c2w, 16, 12, 0.7))
    field = FieldConfig(depth=depth, width=width, skips=(1,))
    sampling = SamplingConfig(0.0, 1.0, 16) if ndc else SamplingConfig(2.0, 6.0, 24)
    render = RenderConfig(sampling=sampling, background=(1.0, 1.0, 1.0),
                          ndc=NDCSpace(0.4, 0.3) if ndc else None, pixel_center=0.5)
    return SceneConfig(coarse=field, fine=field if fine else None, n_coarse=16 if fine else 0, n_importance=16 if fine else 0,
                       render=render, aabb=(-1.5, -1.5, -1.5, 1.5, 1.5, 1.5), grid_resolution=16,
                       cameras=tuple(cameras))


def make_tiny_scene(seed: int = 0, **kwargs):
    """A tiny scene with seeded random weights and a full occupancy grid."""
    import torch

    from noisenerf.runtime.sampling import OccupancyGrid
    from noisenerf.train.scene.scene import Scene, build_fields

    config = tiny_scene_config(**kwargs)
    torch.manual_seed(seed)
    coarse, fine = build_fields(config)
    grid = OccupancyGrid(config.aabb, np.ones((config.grid_resolution,) * 3, dtype=bool))
    scene = Scene(config, coarse, fine, grid)
    for field in scene.fields().values():
        field.eval().requires_grad_(False)
    return scene


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
