"""Rendering a scene's rays in torch: dense (with optional noise), hierarchical, and skipping.

Rays, sample positions and skip masks come from noisenerf.runtime (one convention for both sides);
this module evaluates the torch fields on them and composites differentiably.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from noisenerf.runtime.render import CoarseNetwork, RayBatch
from noisenerf.runtime.reveal import NoisyFieldFn
from noisenerf.runtime.sampling import Hierarchy
from noisenerf.train.field import NeRFField
from noisenerf.train.rendering import composite, render_weights, sample_deltas, sample_pdf


@dataclass(frozen=True)
class TorchRays:
    """A RayBatch on a torch device. All (n_rays, 3) float32."""

    origins: torch.Tensor
    directions: torch.Tensor
    viewdirs: torch.Tensor

    @staticmethod
    def from_batch(rays: RayBatch, device: torch.device | str) -> "TorchRays":
        return TorchRays(*(torch.from_numpy(np.ascontiguousarray(a)).to(device)
                           for a in (rays.origins, rays.directions, rays.viewdirs)))

    def __len__(self) -> int:
        return self.origins.shape[0]


def sample_points(rays: TorchRays, t_vals: torch.Tensor) -> torch.Tensor:
    """o + t·d. t_vals: (n_rays, n_samples) -> (n_rays, n_samples, 3)."""
    return rays.origins[:, None, :] + t_vals[..., None] * rays.directions[:, None, :]


def render_dense(field: NeRFField, rays: TorchRays, t_vals: torch.Tensor, background: torch.Tensor,
                 noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Every sample evaluated, with optional noise broadcast over samples.

    t_vals: (n_rays, n_samples); noise: (n_rays, n_samples or 1, noise_dims) or None
    -> colors (n_rays, 3), weights (n_rays, n_samples).
    """
    n_rays, n_samples = t_vals.shape
    points = sample_points(rays, t_vals).reshape(-1, 3)
    viewdirs = rays.viewdirs[:, None, :].expand(n_rays, n_samples, 3).reshape(-1, 3)
    if noise is not None:
        noise = noise.expand(n_rays, n_samples, noise.shape[-1]).reshape(n_rays * n_samples, -1)
    rgb, sigma = field(points, viewdirs, noise)
    weights = render_weights(sigma.reshape(n_rays, n_samples), sample_deltas(t_vals, rays.directions))
    return composite(weights, rgb.reshape(n_rays, n_samples, 3), background), weights


def render_masked(field: NeRFField, rays: TorchRays, t_vals: torch.Tensor, mask: torch.Tensor,
                  background: torch.Tensor) -> torch.Tensor:
    """Only samples where mask is True are evaluated; the rest count as σ = 0 (empty space skipping).

    t_vals, mask: (n_rays, n_samples) -> colors (n_rays, 3).
    """
    n_rays, n_samples = t_vals.shape
    rays_idx, samples_idx = torch.nonzero(mask, as_tuple=True)
    points = rays.origins[rays_idx] + t_vals[rays_idx, samples_idx, None] * rays.directions[rays_idx]
    rgb, sigma = field(points, rays.viewdirs[rays_idx])
    sigmas = torch.zeros(n_rays, n_samples, dtype=sigma.dtype, device=sigma.device).index_put(
        (rays_idx, samples_idx), sigma)
    rgbs = torch.zeros(n_rays, n_samples, 3, dtype=rgb.dtype, device=rgb.device).index_put(
        (rays_idx, samples_idx), rgb)
    return composite(render_weights(sigmas, sample_deltas(t_vals, rays.directions)), rgbs, background)


def render_hierarchical(coarse: NeRFField, fine: NeRFField, rays: TorchRays, t_vals: torch.Tensor,
                        n_importance: int, background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """nerf-pytorch's two-pass render: coarse samples, then n_importance samples drawn from the coarse
    weights, the fine field evaluated on the sorted union. -> coarse colors, fine colors (n_rays, 3)."""
    coarse_colors, weights = render_dense(coarse, rays, t_vals, background)
    mids = 0.5 * (t_vals[:, 1:] + t_vals[:, :-1])
    fine_t = sample_pdf(mids, weights[:, 1:-1].detach(), n_importance).detach()
    all_t, _ = torch.sort(torch.cat([t_vals, fine_t], dim=-1), dim=-1)
    fine_colors, _ = render_dense(fine, rays, all_t, background)
    return coarse_colors, fine_colors


def numpy_field(field: NeRFField) -> NoisyFieldFn:
    """The torch field behind the runtime's numpy callbacks (FieldFn, and NoisyFieldFn with noise), without
    gradients, computing in the field's own dtype (float32, or float64 for a reference copy).

    points, viewdirs: (n, 3), noise: (n, noise_dims) or None -> rgb (n, 3), sigma (n,).
    """
    parameter = next(field.parameters())

    def evaluate(points: np.ndarray, viewdirs: np.ndarray, noise: np.ndarray | None = None):
        arrays = (points, viewdirs) if noise is None else (points, viewdirs, noise)
        with torch.no_grad():
            rgb, sigma = field(*(torch.tensor(a, dtype=parameter.dtype, device=parameter.device) for a in arrays))
        return rgb.cpu().numpy(), sigma.cpu().numpy()

    return evaluate


def numpy_fields(fields: dict[str, NeRFField]) -> dict[str, NoisyFieldFn]:
    """numpy_field of each network of a scene (Scene.fields()), as runtime.reveal.reveal takes them."""
    return {name: numpy_field(field) for name, field in fields.items()}


def numpy_coarse(coarse: NeRFField, hierarchy: Hierarchy | None) -> CoarseNetwork | None:
    """The coarse pass of runtime.render's hierarchical render on the torch coarse field (None where the
    scene has no fine network: its renders are uniform)."""
    return CoarseNetwork(numpy_field(coarse), hierarchy) if hierarchy is not None else None
