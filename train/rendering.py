"""Volume rendering (paper eq. 2) in torch, the differentiable twin of noisenerf.runtime.compositing."""

from __future__ import annotations

import torch

from noisenerf.runtime.compositing import MAX_OPTICAL_DEPTH
from noisenerf.runtime.sampling import LAST_DELTA


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
    background (3,) -> (n_rays, 3)."""
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
