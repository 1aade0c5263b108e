"""Small scenes with seeded random weights: what the stress checks (`noisenerf bench --stress`) and the
tests run on when a fitted scene would only cost time. Six 16×12 cameras on a ring of radius 4 look at
the origin; the occupancy grid is full."""

from __future__ import annotations

import numpy as np
import torch

from noisenerf.runtime.camera import Camera, NDCSpace
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.render import RenderConfig
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.scene.field import MlpConfig
from noisenerf.train.scene.hashgrid import HashGridConfig
from noisenerf.train.scene.procedural import look_at_origin
from noisenerf.train.scene.scene import Scene, SceneConfig, build_fields


# a small hash grid: 4 levels of 2 features, resolutions 4 to 32 (the first two dense), 2^10 rows a level
SMALL_HASHGRID = HashGridConfig(levels=4, features=2, log2_table=10, base_resolution=4, per_level_scale=2.0,
                                density_hidden=32, geo_features=15, colour_hidden=64, colour_layers=2)
TABLE_SPREAD = 1.0  # a random scene's tables are uniform in ±this: Instant-NGP's ±1e-4 would leave it featureless


def ring_scene_config(ndc: bool = False, fine: bool = False, width: int = 32, depth: int = 3,
                      kind: str = "mlp") -> SceneConfig:
    """The config: a `depth`-layer field `width` wide (and a fine one like it) or for kind "hashgrid" the
    SMALL_HASHGRID, 24 samples in [2, 6], or for `ndc` a forward-facing scene's 16 samples in NDC [0, 1]."""
    cameras = tuple(Camera.from_fov(look_at_origin(np.array([4 * np.sin(angle), -4 * np.cos(angle), 1.0])), 16, 12, 0.7)
                    for angle in np.linspace(0, 2 * np.pi, 6, endpoint=False))
    field = SMALL_HASHGRID if kind == "hashgrid" else MlpConfig(depth=depth, width=width, skips=(1,))
    sampling = SamplingConfig(0.0, 1.0, 16) if ndc else SamplingConfig(2.0, 6.0, 24)
    render = RenderConfig(sampling=sampling, background=(1.0, 1.0, 1.0),
                          ndc=NDCSpace(0.4, 0.3) if ndc else None, pixel_center=0.5)
    return SceneConfig(coarse=field, fine=field if fine else None, n_coarse=16 if fine else 0,
                       n_importance=16 if fine else 0, render=render, aabb=(-1.5, -1.5, -1.5, 1.5, 1.5, 1.5),
                       grid_resolution=16, cameras=cameras)


def random_scene(seed: int = 0, **config) -> Scene:
    """A ring scene (ring_scene_config's keywords) with weights drawn from `seed`, frozen for evaluation;
    the caller's torch random state is left as it was."""
    scene_config = ring_scene_config(**config)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        coarse, fine = build_fields(scene_config)
        for network in (coarse, fine):
            for name, values in network.named_parameters() if network is not None else ():
                if name == "table":
                    values.data.uniform_(-TABLE_SPREAD, TABLE_SPREAD)
    grid = OccupancyGrid(scene_config.aabb, np.ones((scene_config.grid_resolution,) * 3, dtype=bool))
    scene = Scene(scene_config, coarse, fine, grid)
    for network in scene.fields().values():
        network.eval().requires_grad_(False)
    return scene
