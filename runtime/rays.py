"""Rays in the space the field lives in: a camera's pixels → world rays (runtime.camera) → view directions,
then NDC for forward-facing scenes (nerf-pytorch's order)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from noisenerf.runtime.camera import Camera, camera_rays, ndc_rays, normalize_directions, pixel_rays

if TYPE_CHECKING:
    from noisenerf.runtime.render import RenderConfig


@dataclass(frozen=True)
class RayBatch:
    """Rays in the space the field lives in (NDC for forward-facing scenes). All (n_rays, 3) float32."""

    origins: np.ndarray
    directions: np.ndarray
    viewdirs: np.ndarray

    def __len__(self) -> int:
        return self.origins.shape[0]

    def rows(self, start: int, stop: int) -> "RayBatch":
        """Rays start..stop of the batch."""
        return RayBatch(self.origins[start:stop], self.directions[start:stop], self.viewdirs[start:stop])


def field_space_rays(config: RenderConfig, rays_o: np.ndarray, rays_d: np.ndarray) -> RayBatch:
    """View directions from the world rays, then NDC if the scene is forward-facing (nerf-pytorch order)."""
    viewdirs = normalize_directions(rays_d)
    if config.ndc is not None:
        rays_o, rays_d = ndc_rays(config.ndc, rays_o, rays_d)
    return RayBatch(rays_o.astype(np.float32), rays_d.astype(np.float32), viewdirs)


def camera_ray_batch(camera: Camera, config: RenderConfig) -> RayBatch:
    """Every pixel's ray, row-major, computed at once: the rays a hide solves its noise on, and so the
    rays a reveal renders a tile with (a tile's size is capped; a ray computed in another batch may
    differ in its last bit)."""
    return field_space_rays(config, *camera_rays(camera, config.pixel_center))


def pixel_range_rays(camera: Camera, config: RenderConfig, start: int, stop: int) -> RayBatch:
    """Rays of pixels start..stop (row-major), so that a large camera never holds all its rays at once."""
    index = np.arange(start, stop)
    px = (index % camera.width).astype(np.float32) + config.pixel_center
    py = (index // camera.width).astype(np.float32) + config.pixel_center
    return field_space_rays(config, *pixel_rays(camera, px, py))
