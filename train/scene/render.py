"""The torch render pipeline: volume rendering (paper eq. 2), the differentiable twin of
noisenerf.runtime.compositing, and the scene's rays rendered densely (with optional noise),
hierarchically and with skipping.

Rays, sample positions and skip masks come from noisenerf.runtime (one convention for both sides);
this module evaluates the torch fields on them and composites differentiably.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from noisenerf.runtime.compositing import MAX_OPTICAL_DEPTH
from noisenerf.runtime.field_callbacks import NoisyFieldFn
from noisenerf.runtime.marching import grid_candidates
from noisenerf.runtime.occupancy import OccupancyGrid
from noisenerf.runtime.proposal import DensityFn
from noisenerf.runtime.rays import RayBatch
from noisenerf.runtime.sampling import LAST_DELTA
from noisenerf.train.scene.field_kinds import Field


def optical_depths(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """σ·Δ per sample, capped so that inf never enters a sum. (n_rays, n_samples) -> (n_rays, n_samples)."""
    return torch.clamp_max(sigmas * deltas, MAX_OPTICAL_DEPTH)


def transmittance(depths: torch.Tensor) -> torch.Tensor:
    """T_i = exp(−Σ_{j<i} σ_jΔ_j) as an exclusive cumsum (no subtraction, so no inf − inf).
    depths: (n_rays, n_samples) -> (n_rays, n_samples)."""
    exclusive = torch.cat([torch.zeros_like(depths[:, :1]), torch.cumsum(depths, dim=1)[:, :-1]], dim=1)
    return torch.exp(-exclusive)


def render_weights(sigmas: torch.Tensor, deltas: torch.Tensor) -> torch.Tensor:
    """w_i = T_i·(1 − exp(−σ_iΔ_i)). (n_rays, n_samples) -> (n_rays, n_samples)."""
    depths = optical_depths(sigmas, deltas)
    return transmittance(depths) * -torch.expm1(-depths)


def composite(weights: torch.Tensor, rgbs: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Ĉ = Σ w_i c_i + (1 − Σ w_i)·background. weights (n_rays, n_samples), rgbs (n_rays, n_samples, 3),
    background (3,) or one per ray (n_rays, 3) -> (n_rays, 3)."""
    color = torch.einsum("rs,rsc->rc", weights, rgbs)
    return color + (1.0 - weights.sum(dim=1, keepdim=True)) * background


def sample_pdf(bins: torch.Tensor, weights: torch.Tensor, n_samples: int) -> torch.Tensor:
    """Deterministic inverse-CDF samples of the piecewise-constant pdf given by weights over bins
    (nerf-pytorch's sample_pdf with det=True, including its 1e-5 floor and denominator guard).

    bins: (n_rays, n_bins + 1), weights: (n_rays, n_bins) -> (n_rays, n_samples).
    """
    weights = weights + 1e-5
    pdf = weights / weights.sum(dim=-1, keepdim=True)
    cdf = torch.cat([torch.zeros_like(pdf[:, :1]), torch.cumsum(pdf, dim=-1)], dim=-1)
    u = torch.linspace(0.0, 1.0, n_samples, dtype=cdf.dtype, device=cdf.device).expand(cdf.shape[0], n_samples)
    index = torch.searchsorted(cdf, u.contiguous(), right=True)
    below = torch.clamp_min(index - 1, 0)
    above = torch.clamp_max(index, cdf.shape[-1] - 1)
    cdf_below, cdf_above = torch.gather(cdf, 1, below), torch.gather(cdf, 1, above)
    bin_below, bin_above = torch.gather(bins, 1, below), torch.gather(bins, 1, above)
    denom = cdf_above - cdf_below
    denom = torch.where(denom < 1e-5, torch.ones_like(denom), denom)
    return bin_below + (u - cdf_below) / denom * (bin_above - bin_below)


def sample_deltas(t_vals: torch.Tensor, directions: torch.Tensor) -> torch.Tensor:
    """Δ_i = (t_{i+1} − t_i)·‖d‖ with a 1e10 last interval, the twin of runtime.sampling.sample_deltas.
    t_vals: (n_rays, n_samples), directions: (n_rays, 3) -> (n_rays, n_samples)."""
    steps = torch.cat([t_vals[:, 1:] - t_vals[:, :-1], torch.full_like(t_vals[:, :1], LAST_DELTA)], dim=1)
    return steps * torch.linalg.vector_norm(directions, dim=-1, keepdim=True)


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


def skip_mask(field: Field, rays: TorchRays, t_vals: torch.Tensor, grid: OccupancyGrid,
              early_stop: float) -> torch.Tensor:
    """The skipping sampler: samples worth evaluating are in occupied cells (runtime.marching's
    grid_candidates) and, by a density-only pass without gradients, before the ray's transmittance drops
    below early_stop (0: no early termination). t_vals: (n_rays, n_samples) -> bool mask."""
    points = sample_points(rays, t_vals)
    mask = torch.from_numpy(grid_candidates(grid, points.cpu().numpy())).to(t_vals.device)
    if early_stop <= 0 or not mask.any():
        return mask
    with torch.no_grad():
        sigmas = torch.zeros_like(t_vals)
        sigmas[mask] = field.density(points[mask])
        weights_before = render_weights(sigmas, sample_deltas(t_vals, rays.directions))
        opacity_before = torch.cumsum(weights_before, dim=1) - weights_before
    return mask & (1.0 - opacity_before > early_stop)


def render_rays(field: Field, rays: TorchRays, t_vals: torch.Tensor, background: torch.Tensor,
                mask: torch.Tensor | None = None, noise: torch.Tensor | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """The torch render pipeline: samples at t_vals (uniform, jittered or importance positions) and an
    optional mask of the samples worth evaluating (skip_mask) → the field → the compositor (eq. 2).
    Samples left out by the mask count as σ = 0. Noise (one vector per ray or per sample) is added to
    every evaluated sample's encoded input; it needs every sample evaluated.

    t_vals: (n_rays, n_samples); mask: same shape, bool, or None; noise: (n_rays, 1 or n_samples, dims)
    or None -> colors (n_rays, 3), weights (n_rays, n_samples).
    """
    n_rays, n_samples = t_vals.shape
    points = sample_points(rays, t_vals)
    if mask is None:
        viewdirs = rays.viewdirs[:, None, :].expand(n_rays, n_samples, 3).reshape(-1, 3)
        if noise is not None:
            noise = noise.expand(n_rays, n_samples, noise.shape[-1]).reshape(n_rays * n_samples, -1)
        rgb, sigma = field(points.reshape(-1, 3), viewdirs, noise)
        sigmas, rgbs = sigma.reshape(n_rays, n_samples), rgb.reshape(n_rays, n_samples, 3)
    else:
        if noise is not None:
            raise ValueError("noise needs every sample evaluated (no mask)")
        rays_idx, samples_idx = torch.nonzero(mask, as_tuple=True)
        rgb, sigma = field(points[rays_idx, samples_idx], rays.viewdirs[rays_idx])
        sigmas = torch.zeros(n_rays, n_samples, dtype=sigma.dtype, device=sigma.device).index_put(
            (rays_idx, samples_idx), sigma)
        rgbs = torch.zeros(n_rays, n_samples, 3, dtype=rgb.dtype, device=rgb.device).index_put(
            (rays_idx, samples_idx), rgb)
    weights = render_weights(sigmas, sample_deltas(t_vals, rays.directions))
    return composite(weights, rgbs, background), weights


def render_hierarchical(coarse: Field, fine: Field, rays: TorchRays, t_vals: torch.Tensor,
                        n_importance: int, background: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """nerf-pytorch's two-pass render: coarse samples, then n_importance samples drawn from the coarse
    weights, the fine field evaluated on the sorted union. -> coarse colors, fine colors (n_rays, 3)."""
    coarse_colors, weights = render_rays(coarse, rays, t_vals, background)
    mids = 0.5 * (t_vals[:, 1:] + t_vals[:, :-1])
    fine_t = sample_pdf(mids, weights[:, 1:-1].detach(), n_importance).detach()
    all_t, _ = torch.sort(torch.cat([t_vals, fine_t], dim=-1), dim=-1)
    fine_colors, _ = render_rays(fine, rays, all_t, background)
    return coarse_colors, fine_colors


def numpy_field(field: Field) -> NoisyFieldFn:
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


def numpy_fields(fields: dict[str, Field]) -> dict[str, NoisyFieldFn]:
    """numpy_field of each network of a scene (Scene.fields()), as runtime.reveal.reveal_tiles takes them."""
    return {name: numpy_field(field) for name, field in fields.items()}


def numpy_density(network: torch.nn.Module) -> DensityFn:
    """A torch density network (a nerfacto proposal network) behind runtime.proposal's DensityFn, without
    gradients: points (n, 3) -> σ (n,) in the network's dtype."""
    parameter = next(network.parameters())

    def evaluate(points: np.ndarray) -> np.ndarray:
        with torch.no_grad():
            return network(torch.tensor(points, dtype=parameter.dtype, device=parameter.device)).cpu().numpy()

    return evaluate
