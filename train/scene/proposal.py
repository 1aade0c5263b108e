"""nerfacto's proposal sampler in torch, for fitting (runtime.proposal is the numpy twin every render uses, equal
to this one at eval by test), and the two losses that train it (mip-NeRF 360, Barron et al. 2022).

Bins live in spacing space s ∈ [0, 1] (runtime.proposal.spacing: uniform up to distance 1, linear in disparity
beyond). In training, nerfstudio's samplers jitter every ray's bins by one random offset (`single_jitter`), the
proposal weights are sharpened by an exponent that anneals to 1 (`anneal`), and the bins each stage passes on are
detached: the proposal networks learn only from the interlevel loss, the field only from the colour.
"""

from __future__ import annotations

from typing import Callable, Sequence

import torch

from noisenerf.runtime.proposal import WEIGHT_FLOOR, ProposalSampling
from noisenerf.train.scene.render import TorchRays, render_weights

DensityFn = Callable[[torch.Tensor], torch.Tensor]  # points (n, 3) -> σ (n,)
LOSS_EPS = 1e-7  # nerfstudio's EPS in lossfun_outer's denominator


def spacing(t: torch.Tensor) -> torch.Tensor:
    """s(t) = t/2 for t < 1, 1 − 1/(2t) beyond (runtime.proposal.spacing). (...) -> (...)."""
    return torch.where(t < 1, t / 2, 1 - 1 / (2 * torch.clamp_min(t, 1e-30)))


def spacing_inverse(s: torch.Tensor) -> torch.Tensor:
    """t(s) = 2s for s < 1/2, 1/(2 − 2s) beyond. (...) -> (...)."""
    return torch.where(s < 0.5, 2 * s, 1 / torch.clamp_min(2 - 2 * s, 1e-30))


def euclidean_bins(bins: torch.Tensor, near: float, far: float) -> torch.Tensor:
    """Edges in spacing space -> distances, t(x·s(far) + (1 − x)·s(near)). (r, m + 1) -> (r, m + 1)."""
    s_near, s_far = (spacing(torch.tensor(v, dtype=torch.float32)) for v in (near, far))
    return spacing_inverse(bins * s_far + (1 - bins) * s_near)


def uniform_bins(n_rays: int, n: int, jitter: torch.Tensor | None = None) -> torch.Tensor:
    """Stage 0's n bins (n + 1 edges in [0, 1]); with `jitter` (n_rays, 1) in [0, 1) each ray's inner edges move
    by one offset within their half-bins (UniformLinDispPiecewiseSampler's single jitter). -> (n_rays, n + 1)."""
    edges = torch.linspace(0.0, 1.0, n + 1).expand(n_rays, n + 1)
    if jitter is None:
        return edges
    centres = (edges[:, 1:] + edges[:, :-1]) / 2
    lower, upper = torch.cat([edges[:, :1], centres], -1), torch.cat([centres, edges[:, -1:]], -1)
    return lower + (upper - lower) * jitter


def pdf_bins(bins: torch.Tensor, weights: torch.Tensor, n: int, padding: float,
             jitter: torch.Tensor | None = None) -> torch.Tensor:
    """nerfstudio's PDFSampler: n bins of the piecewise-constant density `weights + padding` over `bins`, their
    n + 1 edges at the inverse CDF of n + 1 equal steps (at the steps' middles; with `jitter` (r, 1), one random
    offset within a step per ray). Detached. bins: (r, m + 1), weights: (r, m) -> (r, n + 1)."""
    weights = weights.detach() + padding
    total = weights.sum(-1, keepdim=True)
    pad = torch.clamp_min(WEIGHT_FLOOR - total, 0)
    weights, total = weights + pad / weights.shape[-1], total + pad
    cdf = torch.clamp_max(torch.cumsum(weights / total, -1), 1)
    cdf = torch.cat([torch.zeros_like(cdf[:, :1]), cdf], -1)
    edges = n + 1
    offset = torch.full_like(cdf[:, :1], 1 / (2 * edges)) if jitter is None else jitter / edges
    u = (torch.linspace(0.0, 1.0 - 1.0 / edges, edges, device=cdf.device) + offset).contiguous()
    above = torch.searchsorted(cdf, u, right=True)
    below, above = torch.clamp(above - 1, 0, cdf.shape[-1] - 1), torch.clamp(above, 0, cdf.shape[-1] - 1)
    cdf_below, cdf_above = cdf.gather(-1, below), cdf.gather(-1, above)
    bin_below, bin_above = bins.gather(-1, below), bins.gather(-1, above)
    t = torch.clip(torch.nan_to_num((u - cdf_below) / (cdf_above - cdf_below), nan=0.0, posinf=0.0, neginf=0.0), 0, 1)
    return (bin_below + t * (bin_above - bin_below)).detach()


def midpoints(rays: TorchRays, edges: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Points at the bins' middles along the unit view directions, and the bins' widths.
    edges: (r, m + 1) distances -> points (r, m, 3), deltas (r, m)."""
    middles = (edges[:, :-1] + edges[:, 1:]) / 2
    return rays.origins[:, None, :] + rays.viewdirs[:, None, :] * middles[..., None], edges[:, 1:] - edges[:, :-1]


def annealed(weights: torch.Tensor, exponent: float) -> torch.Tensor:
    """w^exponent, the proposal weights sharpened early in training (nerfstudio's proposal_weights_anneal)."""
    return weights if exponent == 1 else weights ** exponent


def proposal_stages(rays: TorchRays, sampling: ProposalSampling, densities: Sequence[DensityFn],
                    jitter: torch.Generator | None = None, exponent: float = 1.0
                    ) -> tuple[list[tuple[torch.Tensor, torch.Tensor]], torch.Tensor]:
    """The proposal stages of a batch of rays: each stage's (spacing edges (r, m + 1), weights (r, m)) — weights
    with the networks' gradient — and the field's spacing edges (r, samples + 1). jitter: a generator for training's
    random offsets (None: eval, runtime.proposal.proposal_edges's edges)."""
    n_rays = len(rays)
    random = (lambda: torch.rand(n_rays, 1, generator=jitter).to(rays.origins.device)) if jitter else (lambda: None)
    bins = uniform_bins(n_rays, sampling.proposal_samples[0], random()).to(rays.origins.device)
    counts = (*sampling.proposal_samples[1:], sampling.samples)
    stages = []
    for density, count in zip(densities, counts):
        points, deltas = midpoints(rays, euclidean_bins(bins, sampling.near, sampling.far))
        weights = render_weights(density(points.reshape(-1, 3)).reshape(deltas.shape), deltas)
        stages.append((bins, weights))
        bins = pdf_bins(bins, annealed(weights, exponent), count, sampling.histogram_padding, random())
    return stages, bins


def outer_measure(edges: torch.Tensor, envelope_edges: torch.Tensor, envelope_weights: torch.Tensor) -> torch.Tensor:
    """The envelope's weight over each bin: the sum of the envelope bins that overlap it (mip-NeRF 360 eq. 12).
    edges: (r, m + 1), envelope_edges: (r, k + 1), envelope_weights: (r, k) -> (r, m)."""
    cumulative = torch.cat([torch.zeros_like(envelope_weights[:, :1]), torch.cumsum(envelope_weights, -1)], -1)
    last = envelope_weights.shape[-1] - 1
    lo = torch.clamp(torch.searchsorted(envelope_edges[:, :-1].contiguous(), edges[:, :-1].contiguous(), right=True) - 1,
                     0, last)
    hi = torch.clamp(torch.searchsorted(envelope_edges[:, 1:].contiguous(), edges[:, 1:].contiguous(), right=True), 0, last)
    return cumulative[:, 1:].gather(-1, hi) - cumulative[:, :-1].gather(-1, lo)


def interlevel_loss(edges: torch.Tensor, weights: torch.Tensor,
                    stages: Sequence[tuple[torch.Tensor, torch.Tensor]]) -> torch.Tensor:
    """Σ over proposal stages of mean max(0, w − outer(w_proposal))² / (w + ε) (mip-NeRF 360 eq. 13): a proposal
    must bound the field's weights from above; the field's side is detached. edges (r, m + 1) and weights (r, m)
    of the field's samples in spacing space -> scalar."""
    edges, weights = edges.detach(), weights.detach()
    loss = weights.new_zeros(())
    for stage_edges, stage_weights in stages:
        excess = torch.clamp_min(weights - outer_measure(edges, stage_edges, stage_weights), 0)
        loss = loss + torch.mean(excess ** 2 / (weights + LOSS_EPS))
    return loss


def distortion_loss(edges: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Mean over rays of Σ_ij w_i w_j |s̄_i − s̄_j| + Σ_i w_i² Δs_i / 3 (mip-NeRF 360 eq. 15): weights gathered
    into as short a stretch of spacing as they can. edges (r, m + 1), weights (r, m) -> scalar."""
    middles = (edges[:, 1:] + edges[:, :-1]) / 2
    between = (weights[:, :, None] * weights[:, None, :] * (middles[:, :, None] - middles[:, None, :]).abs()).sum((1, 2))
    within = (weights ** 2 * (edges[:, 1:] - edges[:, :-1])).sum(-1) / 3
    return torch.mean(between + within)
