"""What a hide will do: its settings (HideConfig), its tiles, and the key its resumable parts belong to.
Torch-free, as the settings and methods it reads (settings.py, methods.py): a HideConfig travels to workers
with every job, and the CLI builds one before torch is imported."""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from noisenerf import __version__
from noisenerf.runtime.bundle import Tile, secret_digest
from noisenerf.runtime.layouts import LAYOUTS
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.networks import NETWORKS, render_network
from noisenerf.runtime.sampling import SamplingConfig
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.settings import CPU_PART_PIXELS
from noisenerf.train.hide.tiling import DEFAULT_TILE_SIZE, tile_camera, tile_rects

if TYPE_CHECKING:
    from noisenerf.train.scene.scene import Scene


@dataclass(frozen=True)
class HideConfig:
    """Everything that decides a bundle's bytes (saved in the bundle, and keyed for resume).

    The method (methods.py) supplies the defaults left as None: its layout (the first it writes), its
    samples per ray and its network (None: the scene's render network, the fine one where there is one);
    the dtype defaults to the layout's first (runtime/bundle.py). `settings` holds settings dataclasses that
    replace a method's defaults, e.g. `settings=(PaperSettings(iters=50),)`; after construction it holds
    every registered method's settings; the bundle records those of the method that ran (to_dict).
    """

    method: str = "exact"
    layout: str | None = None  # compact | ray | sample
    dtype: str | None = None
    n_samples: int | None = None  # samples per ray of the secret view
    tile_size: int = DEFAULT_TILE_SIZE
    view: int = 0
    seed: int = 0
    part_pixels: int = CPU_PART_PIXELS  # exact method: pixels per solved (and resumable) part; CLI: part_pixels_for
    network: str | None = None  # coarse | fine
    settings: tuple = ()

    def __post_init__(self):
        if self.method not in METHODS:
            raise UserError(f"unknown method {self.method!r} ({' or '.join(METHODS)})")
        method = METHODS[self.method]
        defaults = {kind.key: kind() for each in METHODS.values() for kind in each.settings_types}
        given = {type(settings).key: settings for settings in self.settings}
        if set(given) - set(defaults) or len(given) != len(self.settings):
            raise UserError("settings must be one of each kind the methods define")
        object.__setattr__(self, "settings", tuple({**defaults, **given}.values()))
        if self.layout is None:
            object.__setattr__(self, "layout", method.layouts[0])
        if self.layout not in LAYOUTS:
            raise UserError(f"unknown noise layout {self.layout!r} (one of {', '.join(LAYOUTS)})")
        if self.layout not in method.layouts:
            raise UserError(f"the {self.method} method stores its noise as {' or '.join(method.layouts)}, "
                            f"not {self.layout}")
        dtypes = LAYOUTS[self.layout].dtypes
        if self.dtype is None:
            object.__setattr__(self, "dtype", dtypes[0])
        if self.dtype not in dtypes:
            raise UserError(f"the {self.layout} layout stores {' or '.join(dtypes)}, not {self.dtype!r}")
        if self.n_samples is None:
            object.__setattr__(self, "n_samples", method.default_samples)
        if self.network is None:
            object.__setattr__(self, "network", method.default_network)
        if self.network not in (None, *NETWORKS):
            raise UserError(f"unknown network {self.network!r} (coarse or fine)")
        if self.n_samples < 1:
            raise UserError("the secret view needs at least one sample per ray")
        method.check(self)

    def get(self, kind: type):
        """The settings of one kind (ExactSettings, PaperSettings, CompactSettings, ...)."""
        return next(settings for settings in self.settings if isinstance(settings, kind))

    def to_dict(self) -> dict:
        """As bundles record it: the common fields, then each settings dataclass of the method that runs
        under its key (another method's settings would only cost bytes: ~0.9 KB for the paper's)."""
        common = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "settings"}
        own = METHODS[self.method].settings_types
        return {**common, **{type(s).key: dataclasses.asdict(s) for s in self.settings if isinstance(s, own)}}


@dataclass(frozen=True)
class HidePlan:
    """The tiles to solve: rectangles, cameras and the secret's pixels for each."""

    tiles: tuple[Tile, ...]  # noise still empty
    secret: np.ndarray  # (H, W, 3) uint8


def plan(scene: Scene, secret: np.ndarray, config: HideConfig) -> HidePlan:
    height, width = secret.shape[:2]
    if height < 1 or width < 1:
        raise UserError("the secret image is empty")
    n_cameras = len(scene.config.cameras)
    if not 0 <= config.view < n_cameras:
        raise UserError(f"--view {config.view} is out of range: the scene has {n_cameras} cameras (0..{n_cameras - 1})")
    network = config.network or render_network(scene.fields())
    if network not in scene.fields():
        raise UserError(f"the scene has no {network} network")
    sampling = SamplingConfig(scene.config.render.sampling.near, scene.config.render.sampling.far, config.n_samples)
    tiles = tuple(Tile(rect=rect, camera=tile_camera(scene.config.cameras, config.view, k, rect), sampling=sampling,
                       noise=None, view=(config.view + k) % n_cameras, network=network)
                  for k, rect in enumerate(tile_rects(width, height, config.tile_size)))
    return HidePlan(tiles, secret)


def run_key(scene: Scene, secret: np.ndarray, config: HideConfig) -> str:
    """What a resumable partial result belongs to: scene, secret, every setting and the noisenerf version
    (saved parts are only valid in the compact basis the version that solved them computes)."""
    identity = json.dumps({"scene": scene.fingerprint(), "secret": secret_digest(secret), "shape": secret.shape,
                          "config": config.to_dict(), "noisenerf": __version__}, sort_keys=True)
    return hashlib.sha256(identity.encode()).hexdigest()
