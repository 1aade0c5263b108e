"""Revealing a secret: render every tile's view with its noise, stitch, quantise, check the digest.

A secret view is rendered densely (no skipping: noise can put matter anywhere) at the bundle's own
sampling, with the model's ray convention, NDC space and background, through the network the tile
names (the paper's method trains through the coarse network, as its authors do): one pass, uniform
samples, never hierarchical, since the noise was trained on exactly those samples.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from noisenerf.runtime.bundle import Bundle, Tile, secret_digest
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.field_callbacks import NoisyFieldFn, noisy
from noisenerf.runtime.images import to_uint8
from noisenerf.runtime.networks import render_network
from noisenerf.runtime.rays import camera_ray_batch
from noisenerf.runtime.render import RenderConfig, rays_per_chunk, render_in_chunks, render_rays


def render_tile(tile: Tile, config: RenderConfig, field: NoisyFieldFn, progress=None) -> np.ndarray:
    """A tile's secret view: (height, width, 3) float32. The render pipeline's, at the tile's sampling, every
    sample evaluated (no grid; early_stop 0 passes over only what is fully behind opaque matter, where
    weights are 0), on the rays the hide solved on (runtime.rays.camera_ray_batch)."""
    rays = camera_ray_batch(tile.camera, config)
    tile_config = dataclasses.replace(config, sampling=tile.sampling)
    stored = tile.noise.loaded()

    def render_chunk(start: int, stop: int):
        noise = noisy(field, stored.rows(start, stop))
        return render_rays(tile_config, rays.rows(start, stop), noise, None, early_stop=0.0)

    colors, _ = render_in_chunks(len(rays), rays_per_chunk(tile.sampling.n_samples), render_chunk, progress)
    return colors.reshape(tile.camera.height, tile.camera.width, 3)


@dataclass(frozen=True)
class Revealed:
    image: np.ndarray | None  # (height, width, 3) float32 when asked for (keep_float), else None
    pixels: np.ndarray  # (height, width, 3) uint8
    exact: bool  # the 8-bit pixels hash to the bundle's secret digest


def tile_field(tile: Tile, fields: Mapping[str, NoisyFieldFn]) -> NoisyFieldFn:
    """The network a tile's noise was trained through; fields: network name -> noisy field."""
    name = tile.network or render_network(fields)
    if name not in fields:
        raise UserError(f"bundle tile at {tile.rect[:2]} needs the {name} network; this model has only "
                        f"{' and '.join(fields)}", code="reveal.missing_network", at=tile.rect[:2],
                        network=name, networks=list(fields))
    return fields[name]


def reveal_tiles(bundle: Bundle, config: RenderConfig, fields: Mapping[str, NoisyFieldFn], progress=None,
           keep_float: bool = False) -> Revealed:
    """Render and stitch all tiles of a bundle. fields: network name ("coarse", and "fine" where the
    scene has one) -> noisy field; every tile's network is checked before anything is rendered.
    Each tile is quantised as it is rendered, so a reveal holds the 8-bit secret (3 bytes a pixel) and
    one tile's work; keep_float also keeps the float render (12 bytes a pixel, for 16-bit and float outputs)."""
    chosen = [tile_field(tile, fields) for tile in bundle.tiles]
    pixels = np.zeros((bundle.height, bundle.width, 3), dtype=np.uint8)
    image = np.zeros((bundle.height, bundle.width, 3), dtype=np.float32) if keep_float else None
    for tile, field in zip(bundle.tiles, chosen):
        x0, y0, w, h = tile.rect
        colors = render_tile(tile, config, field, progress=progress)
        pixels[y0:y0 + h, x0:x0 + w] = to_uint8(colors)
        if keep_float:
            image[y0:y0 + h, x0:x0 + w] = colors
    return Revealed(image, pixels, secret_digest(pixels) == bundle.secret_sha256)
