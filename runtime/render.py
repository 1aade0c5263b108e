"""The numpy render pipeline, for any field backend (onnxruntime, or torch behind a numpy callback).

One pipeline: sampler → field callback (runtime.field_callbacks, evaluated by runtime.marching.march_rays)
→ compositor (runtime.compositing). An ordinary render's sampler is an object the model (or scene) owns, a
`Sampler`: `MarchingSampler` (uniform samples through the occupancy grid), `HierarchicalSampler` (coarse →
sample_pdf, for scenes with a fine network), or nerfacto's `runtime.proposal.ProposalSampler` with its own
compositor. One loop over a camera's pixels in chunks, `render_in_chunks`, which ordinary renders
(render_view) and reveals (runtime.reveal.render_tile) both run, so two backends rendering the same view
differ only by their field evaluation.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Callable, ClassVar, Protocol

import numpy as np

from noisenerf.runtime.camera import Camera, NDCSpace
from noisenerf.runtime.compositing import composite, render_weights
from noisenerf.runtime.errors import UserError
from noisenerf.runtime.field_callbacks import FieldFn, SampleFieldFn, plain
from noisenerf.runtime.limits import checked_float, checked_list
from noisenerf.runtime.marching import march_rays
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.pdf import Hierarchy, sample_pdf
from noisenerf.runtime.rays import RayBatch, pixel_range_rays
from noisenerf.runtime.sampling import SamplingConfig, sample_along, sample_positions

# the one chunking policy of a render: rays per chunk such that a chunk holds at most CHUNK_SAMPLES samples
# (~60 MB of buffers with a reveal's 90 float32 noise values each), and at most CHUNK_RAYS rays
CHUNK_SAMPLES = 1 << 17
CHUNK_RAYS = 4096


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
            raise UserError("malformed render config: expected an object", code="render.not_object")
        try:
            background = checked_list(data["background"], "render background", length=3, code="render.background")
            return RenderConfig(
                sampling=SamplingConfig.from_dict(data["sampling"]),
                background=tuple(checked_float(v, "render background", 0.0, 1.0, code="render.background")
                                 for v in background),
                ndc=NDCSpace.from_dict(data["ndc"]) if data.get("ndc") else None,
                pixel_center=checked_float(data["pixel_center"], "render pixel_center", 0.0, 1.0,
                                           code="render.pixel_center"),
                early_stop=checked_float(data.get("early_stop", 1e-4), "render early_stop", 0.0, 1.0,
                                         code="render.early_stop"),
            )
        except KeyError as error:
            raise UserError(f"malformed render config: missing {error}", code="render.missing_key",
                            key=error.args[0]) from None


@dataclass(frozen=True)
class RenderStats:
    n_rays: int
    n_samples_dense: int
    n_samples_evaluated: int

    def __add__(self, other: "RenderStats") -> "RenderStats":
        """Counts of two batches of rays together."""
        return RenderStats(*(a + b for a, b in zip(dataclasses.astuple(self), dataclasses.astuple(other))))


def render_samples(rays: RayBatch, t_vals: np.ndarray, field: SampleFieldFn, grid: OccupancyGrid | None,
                   early_stop: float) -> tuple[np.ndarray, np.ndarray, RenderStats]:
    """Weights (n_rays, n_samples) and colours (n_rays, n_samples, 3) of samples at t_vals ((n_samples,) or
    (n_rays, n_samples)), skipping what the grid rules out and rays past `early_stop`."""
    points, deltas = sample_along(rays.origins, rays.directions, t_vals)
    march = march_rays(points, rays.viewdirs, deltas, field, grid, early_stop)
    return render_weights(march.sigmas, deltas), march.rgbs, RenderStats(len(rays), deltas.size, march.n_evaluated)


def importance_positions(config: RenderConfig, rays: RayBatch, coarse: FieldFn, hierarchy: Hierarchy
                         ) -> tuple[np.ndarray, RenderStats]:
    """nerf-pytorch's fine-pass positions: the `coarse` network's weights at n_coarse uniform samples place
    n_importance more (sample_pdf over the midpoints, end weights dropped); both sets, sorted.
    -> t_vals (n_rays, n_coarse + n_importance), the coarse pass's counts."""
    t_vals = sample_positions(hierarchy.coarse(config.sampling))
    weights, _, stats = render_samples(rays, t_vals, plain(coarse), None, 0.0)
    mids = np.broadcast_to(0.5 * (t_vals[1:] + t_vals[:-1]), (len(rays), t_vals.shape[0] - 1))
    fine = sample_pdf(mids, weights[:, 1:-1], hierarchy.n_importance)
    both = np.concatenate([np.broadcast_to(t_vals, (len(rays), t_vals.shape[0])), fine], axis=-1)
    return np.sort(both, axis=-1), stats


def render_rays(config: RenderConfig, rays: RayBatch, field: SampleFieldFn, grid: OccupancyGrid | None,
                early_stop: float | None = None) -> tuple[np.ndarray, RenderStats]:
    """Colours of rays (n_rays, 3): uniform samples (config.sampling) through the callback `field`, with
    empty-space skipping (grid) and early ray termination past `early_stop` (the config's when None)."""
    early_stop = config.early_stop if early_stop is None else early_stop
    weights, rgbs, stats = render_samples(rays, sample_positions(config.sampling), field, grid, early_stop)
    return composite(weights, rgbs, np.asarray(config.background)), stats


class Sampler(Protocol):
    """An ordinary (noise-free) render's strategy, owned by a model (runtime.model.Model.sampler) or a scene
    (train.scene.render.numpy_sampler): where a ray's samples go, which are evaluated, how they composite."""

    hierarchical: ClassVar[bool]  # samples placed by another network's pass (never skipping)

    @property
    def samples_per_ray(self) -> int:
        """The most samples one ray holds at once (what sets rays per chunk)."""

    @property
    def skips(self) -> bool:
        """Whether empty space is skipped and rays terminate early."""

    def render(self, rays: RayBatch, field: FieldFn) -> tuple[np.ndarray, RenderStats]:
        """Colours (n_rays, 3) float32 of the render network `field` along `rays`, and the counts."""


@dataclass(frozen=True)
class MarchingSampler:
    """Uniform samples (config.sampling) marched through the occupancy `grid` with early termination; with
    `skip` off, every sample in the grid's box is evaluated (None: every sample)."""

    config: RenderConfig
    grid: OccupancyGrid | None
    skip: bool = True
    hierarchical: ClassVar[bool] = False

    @property
    def samples_per_ray(self) -> int:
        return self.config.sampling.n_samples

    @property
    def skips(self) -> bool:
        return self.skip

    def render(self, rays: RayBatch, field: FieldFn) -> tuple[np.ndarray, RenderStats]:
        if self.skip:
            return render_rays(self.config, rays, plain(field), self.grid)
        return render_rays(self.config, rays, plain(field), None if self.grid is None else self.grid.box_only(), 0.0)


@dataclass(frozen=True)
class HierarchicalSampler:
    """nerf-pytorch's render of a scene with a fine network: the `coarse` network's weights at n_coarse uniform
    samples place n_importance more, and the fine network renders both sets. Never skips: every coarse weight
    moves the fine samples, and nerf-pytorch evaluates all; only rays whose transmittance is exactly 0 in
    float32 stop, where nothing behind counts anyway."""

    config: RenderConfig
    coarse: FieldFn
    hierarchy: Hierarchy
    hierarchical: ClassVar[bool] = True
    skips: ClassVar[bool] = False

    @property
    def samples_per_ray(self) -> int:
        return self.hierarchy.samples_per_ray

    def render(self, rays: RayBatch, field: FieldFn) -> tuple[np.ndarray, RenderStats]:
        t_vals, before = importance_positions(self.config, rays, self.coarse, self.hierarchy)
        weights, rgbs, stats = render_samples(rays, t_vals, plain(field), None, 0.0)
        return composite(weights, rgbs, np.asarray(self.config.background)), RenderStats(
            len(rays), before.n_samples_dense + stats.n_samples_dense,
            before.n_samples_evaluated + stats.n_samples_evaluated)


def rays_per_chunk(n_samples: int, most_rays: int = CHUNK_RAYS) -> int:
    """Rays per chunk: at most `most_rays`, and few enough that a chunk holds at most CHUNK_SAMPLES samples,
    so a render's buffers stay bounded whatever n_samples a file asks for."""
    return max(1, min(most_rays, CHUNK_SAMPLES // n_samples))


ChunkRenderer = Callable[[int, int], tuple[np.ndarray, RenderStats]]  # (start, stop) -> colours (m, 3), counts


def render_in_chunks(n_rays: int, chunk_rays: int, render_chunk: ChunkRenderer,
                     progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, RenderStats]:
    """The one render loop: colours (n_rays, 3) float32 of rays 0..n_rays, `chunk_rays` at a time, so a
    render holds one chunk's rays, samples and noise at once; `progress(n)` is told of each chunk's n rays."""
    colors = np.empty((n_rays, 3), dtype=np.float32)
    stats = RenderStats(0, 0, 0)
    for start in range(0, n_rays, chunk_rays):
        stop = min(start + chunk_rays, n_rays)
        colors[start:stop], chunk_stats = render_chunk(start, stop)
        stats = stats + chunk_stats
        if progress is not None:
            progress(stop - start)
    return colors, stats


def render_view(camera: Camera, config: RenderConfig, field: FieldFn, sampler: Sampler, chunk_rays: int = CHUNK_RAYS,
                progress=None) -> tuple[np.ndarray, RenderStats]:
    """An ordinary (noise-free) render of a camera by the scene's `sampler`: image (height, width, 3) float32
    and counts."""
    def render_chunk(start: int, stop: int) -> tuple[np.ndarray, RenderStats]:
        return sampler.render(pixel_range_rays(camera, config, start, stop), field)

    colors, stats = render_in_chunks(camera.width * camera.height, rays_per_chunk(sampler.samples_per_ray, chunk_rays),
                                     render_chunk, progress)
    return colors.reshape(camera.height, camera.width, 3), stats
