"""Rendering a view from any field backend (onnxruntime, or torch behind a numpy callback).

The field is a callback `field(points (m, 3), viewdirs (m, 3)) -> rgb (m, 3), sigma (m,)`; everything
around it — rays, NDC, sample positions, skipping, compositing — is this module's, so two backends
rendering the same view differ only by their field evaluation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.camera import Camera, NDCSpace, camera_rays, ndc_rays, normalize_directions
from noisenerf.runtime.compositing import composite, render_weights
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.sampling import (
    FieldFn, OccupancyGrid, SamplingConfig, march_rays, sample_deltas, sample_positions,
)


@dataclass(frozen=True)
class RenderConfig:
    """How a scene's views are rendered; saved in the scene directory and the ONNX metadata."""

    sampling: SamplingConfig
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    ndc: NDCSpace | None = None
    pixel_center: float = 0.5
    early_stop: float = 1e-4

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    @staticmethod
    def from_dict(data: dict) -> "RenderConfig":
        try:
            return RenderConfig(
                sampling=SamplingConfig(**data["sampling"]),
                background=tuple(float(v) for v in data["background"]),
                ndc=NDCSpace(**data["ndc"]) if data.get("ndc") else None,
                pixel_center=float(data["pixel_center"]),
                early_stop=float(data.get("early_stop", 1e-4)),
            )
        except (KeyError, TypeError, ValueError) as error:
            raise UserError(f"malformed render config: {error}") from None


@dataclass(frozen=True)
class RayBatch:
    """Rays in the space the field lives in (NDC for forward-facing scenes). All (n_rays, 3) float32."""

    origins: np.ndarray
    directions: np.ndarray
    viewdirs: np.ndarray

    def __len__(self) -> int:
        return self.origins.shape[0]


def prepare_rays(config: RenderConfig, rays_o: np.ndarray, rays_d: np.ndarray) -> RayBatch:
    """View directions from the world rays, then NDC if the scene is forward-facing (nerf-pytorch order)."""
    viewdirs = normalize_directions(rays_d)
    if config.ndc is not None:
        rays_o, rays_d = ndc_rays(config.ndc, rays_o, rays_d)
    return RayBatch(rays_o.astype(np.float32), rays_d.astype(np.float32), viewdirs)


def sample_along(rays: RayBatch, t_vals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sample points and their intervals. t_vals: (n_samples,) or (n_rays, n_samples)
    -> points (n_rays, n_samples, 3), deltas (n_rays, n_samples)."""
    t_vals = np.broadcast_to(t_vals, (len(rays), t_vals.shape[-1])).astype(np.float32)
    points = rays.origins[:, None, :] + t_vals[..., None] * rays.directions[:, None, :]
    deltas = sample_deltas(t_vals, np.linalg.norm(rays.directions, axis=-1))
    return points.astype(np.float32), deltas


@dataclass(frozen=True)
class RenderStats:
    n_rays: int
    n_samples_dense: int
    n_samples_evaluated: int


def render_rays(config: RenderConfig, rays: RayBatch, field: FieldFn, grid: OccupancyGrid | None,
                early_stop: float | None = None) -> tuple[np.ndarray, RenderStats]:
    """Colours of rays (n_rays, 3) with empty-space skipping (grid) and early ray termination."""
    points, deltas = sample_along(rays, sample_positions(config.sampling))
    march = march_rays(points, rays.viewdirs, deltas, field, grid,
                       config.early_stop if early_stop is None else early_stop)
    colors = composite(render_weights(march.sigmas, deltas), march.rgbs, np.asarray(config.background))
    return colors, RenderStats(len(rays), deltas.size, march.n_evaluated)


def render_view(camera: Camera, config: RenderConfig, field: FieldFn, grid: OccupancyGrid | None,
                chunk_rays: int = 4096, early_stop: float | None = None, progress=None
                ) -> tuple[np.ndarray, RenderStats]:
    """An ordinary (noise-free) render of a camera: image (height, width, 3) float32 and counts."""
    rays_o, rays_d = camera_rays(camera, config.pixel_center)
    rays = prepare_rays(config, rays_o, rays_d)
    colors, evaluated = [], 0
    for start in range(0, len(rays), chunk_rays):
        chunk = RayBatch(*(a[start:start + chunk_rays] for a in (rays.origins, rays.directions, rays.viewdirs)))
        chunk_colors, stats = render_rays(config, chunk, field, grid, early_stop)
        colors.append(chunk_colors)
        evaluated += stats.n_samples_evaluated
        if progress is not None:
            progress.update(len(chunk))
    image = np.concatenate(colors).reshape(camera.height, camera.width, 3)
    return image, RenderStats(len(rays), len(rays) * config.sampling.n_samples, evaluated)
