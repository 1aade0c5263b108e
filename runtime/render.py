"""Rendering a view from any field backend (onnxruntime, or torch behind a numpy callback).

The field is a callback `field(points (m, 3), viewdirs (m, 3)) -> rgb (m, 3), sigma (m,)`; everything
around it — rays, NDC, sample positions, skipping, compositing — is this module's, so two backends
rendering the same view differ only by their field evaluation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from noisenerf.runtime.camera import Camera, NDCSpace, ndc_rays, normalize_directions, pixel_rays
from noisenerf.runtime.compositing import composite, render_weights
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import checked_float, checked_list
from noisenerf.runtime.sampling import (
    FieldFn, OccupancyGrid, SamplingConfig, march_rays, sample_deltas, sample_positions,
)


VIEW_CHUNK_SAMPLES = 1 << 19  # samples per chunk of an ordinary render (4096 rays of 128): ~60 MB of buffers


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
    def from_dict(data) -> "RenderConfig":
        """From metadata someone else wrote: every number finite and in range (a NaN background would
        silently paint every pixel NaN)."""
        if not isinstance(data, dict):
            raise UserError("malformed render config: expected an object")
        try:
            background = checked_list(data["background"], "render background", length=3)
            return RenderConfig(
                sampling=SamplingConfig.from_dict(data["sampling"]),
                background=tuple(checked_float(v, "render background", 0.0, 1.0) for v in background),
                ndc=NDCSpace.from_dict(data["ndc"]) if data.get("ndc") else None,
                pixel_center=checked_float(data["pixel_center"], "render pixel_center", 0.0, 1.0),
                early_stop=checked_float(data.get("early_stop", 1e-4), "render early_stop", 0.0, 1.0),
            )
        except KeyError as error:
            raise UserError(f"malformed render config: missing {error}") from None


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


def rays_per_chunk(most_rays: int, n_samples: int, most_samples: int) -> int:
    """Rays per chunk: at most `most_rays`, and few enough that a chunk holds at most `most_samples` samples,
    so a render's buffers stay bounded whatever n_samples a file asks for."""
    return max(1, min(most_rays, most_samples // n_samples))


def view_rays(camera: Camera, config: RenderConfig, start: int, stop: int) -> RayBatch:
    """Rays of pixels start..stop (row-major) in the field's space: the same rays as camera_rays gives for
    the whole image, computed a chunk at a time so a large camera never holds all its rays at once."""
    index = np.arange(start, stop)
    px = (index % camera.width).astype(np.float32) + config.pixel_center
    py = (index // camera.width).astype(np.float32) + config.pixel_center
    return prepare_rays(config, *pixel_rays(camera, px, py))


def render_view(camera: Camera, config: RenderConfig, field: FieldFn, grid: OccupancyGrid | None,
                chunk_rays: int = 4096, early_stop: float | None = None, progress=None
                ) -> tuple[np.ndarray, RenderStats]:
    """An ordinary (noise-free) render of a camera: image (height, width, 3) float32 and counts."""
    n_rays = camera.width * camera.height
    chunk = rays_per_chunk(chunk_rays, config.sampling.n_samples, VIEW_CHUNK_SAMPLES)
    image = np.empty((n_rays, 3), dtype=np.float32)
    evaluated = 0
    for start in range(0, n_rays, chunk):
        stop = min(start + chunk, n_rays)
        image[start:stop], stats = render_rays(config, view_rays(camera, config, start, stop), field, grid,
                                               early_stop)
        evaluated += stats.n_samples_evaluated
        if progress is not None:
            progress.update(stop - start)
    return image.reshape(camera.height, camera.width, 3), RenderStats(n_rays, n_rays * config.sampling.n_samples,
                                                                      evaluated)
