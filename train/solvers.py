"""Noise solvers for one chunk of a secret view's pixels.

`solve_exact` (the default): per-pixel Levenberg–Marquardt. Given per-pixel noise, pixels are
independent problems with 3 outputs and `dims` (90) unknowns, so each takes the minimum-norm damped
Gauss–Newton step δ += Jᵀ(JJᵀ + λI)⁻¹r. The exact 3×dims Jacobian costs three backward passes, so it is
computed once and then kept current by Broyden's rank-one secant updates (one forward per iteration),
recomputed only for pixels whose step was rejected. A pixel retires as soon as all three channels sit
inside their 8-bit bin with a margin; candidates are rounded to the storage dtype before they are
judged, so what is stored is what was verified.

A pixel that has not finished after `restart_after` iterations is stuck in a region where the ReLUs
it needs are off (LM only sees local gradients); it restarts from the noise of the finished pixel whose
8-bit colour is nearest to its own, plus a small seeded jitter, since nearby pixels of one view map
noise to colour almost alike.

Rays whose samples are all ReLU-dead have a zero Jacobian. They are revived by a Newton step on the
largest pre-activation density along the ray (its gradient survives the dead ReLU), raising it to
+REVIVE_TARGET; where even that gradient vanishes, a seeded random kick moves the noise.

`solve_paper`: the paper's optimisation (Adam, lr 1e-2 decaying by 0.3 over the run, Pixel
Perturbation for the first μ iterations, Adaptive Pixel Selection), see its docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from noisenerf.train.secret_view import SecretView

REVIVE_TARGET = 1.0


def bin_targets(pixels: torch.Tensor) -> torch.Tensor:
    """Centres of the 8-bit bins, pulled 0.3 bin inside at 0 and 255 where a sigmoid never arrives.
    pixels: (m, 3) uint8 -> (m, 3) float32."""
    return torch.clamp(pixels.float() / 255.0, 0.3 / 255.0, 1.0 - 0.3 / 255.0)


def pixels_inside_bins(colors: torch.Tensor, pixels: torch.Tensor, margin_bins: float) -> torch.Tensor:
    """Whether every channel rounds to its 8-bit value with `margin_bins` to spare. (m, 3) -> (m,) bool."""
    distance = torch.abs(colors * 255.0 - pixels.float())
    return torch.all(distance <= 0.5 - margin_bins, dim=-1)


def quantize(noise: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Round to the storage dtype and back, so the solver only ever judges storable noise."""
    return noise.to(dtype).to(noise.dtype)


def jacobian(view: SecretView, index: torch.Tensor, noise: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Colours (m, 3) and the exact Jacobian ∂colour/∂noise (m, 3, P), P = noise.shape[1]·dims.
    Pixels are independent, so one backward pass of a channel's sum gives that row for every pixel."""
    noise = noise.detach().requires_grad_(True)
    with torch.enable_grad():
        colors = view.render(index, noise)
        rows = [torch.autograd.grad(colors[:, c].sum(), noise, retain_graph=c < 2)[0].flatten(1) for c in range(3)]
    return colors.detach(), torch.stack(rows, dim=1)


def damped_step(jac: torch.Tensor, residual: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
    """Minimum-norm Levenberg–Marquardt step Jᵀ(JJᵀ + λ·(tr(JJᵀ)/3)·I)⁻¹ r.
    jac: (m, 3, P), residual: (m, 3), damping: (m,) -> (m, P)."""
    normal = jac @ jac.transpose(1, 2)
    scale = damping * normal.diagonal(dim1=1, dim2=2).mean(-1) + 1e-12
    normal = normal + scale[:, None, None] * torch.eye(3, dtype=jac.dtype, device=jac.device)
    return (jac.transpose(1, 2) @ torch.linalg.solve(normal, residual[..., None]))[..., 0]


def broyden_update(jac: torch.Tensor, step: torch.Tensor, change: torch.Tensor) -> torch.Tensor:
    """Broyden's rank-one secant update J += (Δc − JΔδ)Δδᵀ/‖Δδ‖². jac: (m, 3, P), step: (m, P),
    change: (m, 3) -> (m, 3, P)."""
    norm2 = (step * step).sum(-1).clamp_min(1e-30)
    miss = change - (jac @ step[..., None])[..., 0]
    return jac + miss[..., None] * (step / norm2[:, None])[:, None, :]


def revival_step(view: SecretView, index: torch.Tensor, noise: torch.Tensor, generator: torch.Generator,
                 kick: float) -> torch.Tensor:
    """Noise that lifts the ray's largest pre-activation density to +REVIVE_TARGET (a Newton step on
    it), or a random kick where its gradient vanishes too. noise: (m, k, dims) -> (m, k, dims)."""
    noise = noise.detach().requires_grad_(True)
    with torch.enable_grad():
        _, raw_density = view.raw(index, noise)
        peak = raw_density.max(dim=1).values
        grad = torch.autograd.grad(peak.sum(), noise)[0]
    norm2 = grad.flatten(1).pow(2).sum(-1)
    newton = grad * ((REVIVE_TARGET - peak.detach()) / norm2.clamp_min(1e-30))[:, None, None]
    random = torch.randn(noise.shape, generator=generator).to(noise.device) * kick
    return noise.detach() + torch.where((norm2 > 1e-20)[:, None, None], newton, random)


@dataclass(frozen=True)
class ExactSettings:
    max_iters: int = 200
    margin_bins: float = 0.1  # what stays between a finished value and its bin edge (≫ ORT/torch parity)
    max_step: float = 20.0  # cap on ‖Δδ‖ per iteration: keeps the linear model honest
    kick: float = 1.0
    restart_after: int = 25
    restart_jitter: float = 0.05


def donor_noise(stuck: torch.Tensor, finished: torch.Tensor, pixels: torch.Tensor, noise: torch.Tensor,
                generator: torch.Generator, jitter: float) -> torch.Tensor:
    """Restart points for stuck pixels: the noise of the finished pixel nearest in 8-bit colour, jittered.
    stuck, finished: index tensors into pixels (m, 3) / noise (m, k, dims) -> (len(stuck), k, dims)."""
    distance = torch.cdist(pixels[stuck].float(), pixels[finished].float())
    donors = finished[distance.argmin(dim=1)]
    return noise[donors] + torch.randn(noise[stuck].shape, generator=generator).to(noise.device) * jitter


@dataclass(frozen=True)
class ChunkResult:
    noise: torch.Tensor  # (m, k, dims) float32 (already representable in the storage dtype)
    iterations: int
    jacobians: int  # pixel-Jacobians computed (3 backward passes each)
    renders: int  # pixel renders (forward passes)
    revivals: int
    restarts: int


def solve_exact(view: SecretView, index: torch.Tensor, pixels: torch.Tensor, noise: torch.Tensor,
                storage: torch.dtype, settings: ExactSettings, generator: torch.Generator) -> ChunkResult:
    """Bring pixels `index` (m,) to their 8-bit values `pixels` (m, 3) uint8, from noise (m, k, dims)."""
    target = bin_targets(pixels)
    noise = quantize(noise.clone(), storage)
    m = index.shape[0]
    active = torch.arange(m, device=noise.device)
    damping = torch.full((m,), 1e-3, device=noise.device)
    jac = torch.zeros(m, 3, noise[0].numel(), device=noise.device)
    stale = torch.ones(m, dtype=torch.bool, device=noise.device)
    with torch.no_grad():
        colors = view.render(index, noise)
    age = torch.zeros(m, dtype=torch.int64, device=noise.device)
    renders, jacobians, revivals, restarts = m, 0, 0, 0
    iteration = 0
    for iteration in range(1, settings.max_iters + 1):
        done = pixels_inside_bins(colors, pixels, settings.margin_bins)
        active = active[~done[active]]
        if active.numel() == 0:
            iteration -= 1
            break
        stuck = active[age[active] >= settings.restart_after]
        if stuck.numel() and done.any():
            noise[stuck] = quantize(donor_noise(stuck, done.nonzero()[:, 0], pixels, noise, generator,
                                                settings.restart_jitter), storage)
            age[stuck], stale[stuck], damping[stuck] = 0, True, 1e-3
            restarts += stuck.numel()
        age[active] += 1
        fresh = active[stale[active]]
        if fresh.numel():
            colors[fresh], jac[fresh] = jacobian(view, index[fresh], noise[fresh])
            stale[fresh] = False
            jacobians += fresh.numel()
            dead = fresh[jac[fresh].flatten(1).abs().amax(-1) < 1e-12]
            if dead.numel():
                noise[dead] = quantize(revival_step(view, index[dead], noise[dead], generator, settings.kick), storage)
                stale[dead] = True
                revivals += dead.numel()
                active = active[~torch.isin(active, dead)]
                with torch.no_grad():
                    colors[dead] = view.render(index[dead], noise[dead])
        residual = target[active] - colors[active]
        step = damped_step(jac[active], residual, damping[active])
        step = step * torch.clamp(settings.max_step / step.norm(dim=-1).clamp_min(1e-30), max=1.0)[:, None]
        candidate = quantize(noise[active] + step.reshape(noise[active].shape), storage)
        with torch.no_grad():
            new_colors = view.render(index[active], candidate)
        renders += active.numel()
        taken = (candidate - noise[active]).flatten(1)
        jac[active] = broyden_update(jac[active], taken, new_colors - colors[active])
        better = ((target[active] - new_colors) ** 2).sum(-1) < (residual ** 2).sum(-1)
        accepted, rejected = active[better], active[~better]
        noise[accepted], colors[accepted] = candidate[better], new_colors[better]
        damping[accepted] = torch.clamp(damping[accepted] / 3, min=1e-6)
        damping[rejected] = torch.clamp(damping[rejected] * 4, max=1e6)
        stale[rejected] = True
    return ChunkResult(noise, iteration, jacobians, renders, revivals, restarts)


@dataclass(frozen=True)
class PaperSettings:
    """The paper's optimisation; the two strategies can be switched off for its Table 3 ablation.

    Our reading of Adaptive Pixel Selection (the paper gives no formula): every iteration computes the
    loss gradient once on the largest batch, which is the whole view; for each size s in
    batch_fractions·(n pixels) the candidate update is the Adam step applied to the s pixels with the
    largest gradient norms; one forward pass of the tentatively updated view gives each pixel's L_rgb
    reduction, and the size with the largest reduction per pixel queried is applied. Without APS every
    pixel is updated every iteration.
    """

    iters: int = 300
    lr: float = 1e-2
    lr_decay: float = 0.3  # lr·decay^(t/iters), nerf-pytorch's exponential schedule
    mu: int = 50  # Pixel Perturbation for iterations t ≤ μ (eq. 8)
    lambda_rgb: float = 0.5
    lambda_perturb: float = 0.5
    batch_fractions: tuple[float, ...] = (0.25, 0.5, 1.0)
    pixel_perturbation: bool = True
    adaptive_selection: bool = True
    record_at: tuple[int, ...] = (50, 200, 300)


def rgb_losses(colors: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """‖Ĉ(γ(p)+δ) − C_M‖² per pixel (eq. 5). (m, 3) -> (m,)."""
    return ((colors - target) ** 2).sum(-1)


def perturb_losses(colors: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """−‖Ĉ(γ(p)+δ) − Ĉ(γ(p))‖² per pixel (eq. 7). (m, 3) -> (m,)."""
    return -((colors - clean) ** 2).sum(-1)


def adam_direction(grad: torch.Tensor, moments: tuple[torch.Tensor, torch.Tensor], steps: torch.Tensor,
                   betas=(0.9, 0.999), eps: float = 1e-8) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Adam with a step count per pixel (pixels are updated at different times).
    grad, moments: (m, k, dims), steps: (m,) counts after this update -> direction, new moments."""
    first = betas[0] * moments[0] + (1 - betas[0]) * grad
    second = betas[1] * moments[1] + (1 - betas[1]) * grad * grad
    correction1 = (1 - betas[0] ** steps.float())[:, None, None]
    correction2 = (1 - betas[1] ** steps.float())[:, None, None]
    return (first / correction1) / ((second / correction2).sqrt() + eps), first, second


def solve_paper(view: SecretView, pixels: torch.Tensor, settings: PaperSettings, noise: torch.Tensor,
                record=None) -> torch.Tensor:
    """Optimise the noise of every pixel of the view (paper eq. 5–8). pixels: (n, 3) uint8,
    noise: (n, k, dims) -> noise. `record(t, colors, loss)` is called at settings.record_at."""
    index = torch.arange(view.n_rays, device=noise.device)
    target = pixels.float() / 255.0
    with torch.no_grad():
        clean = view.render(index, torch.zeros_like(noise[:, :1]))
    moments = (torch.zeros_like(noise), torch.zeros_like(noise))
    steps = torch.zeros(view.n_rays, dtype=torch.int64, device=noise.device)
    sizes = sorted({max(1, int(round(f * view.n_rays))) for f in settings.batch_fractions})
    for t in range(1, settings.iters + 1):
        lr = settings.lr * settings.lr_decay ** (t / settings.iters)
        noise = noise.detach().requires_grad_(True)
        with torch.enable_grad():
            colors = view.render(index, noise)
            losses = rgb_losses(colors, target)
            if settings.pixel_perturbation and t <= settings.mu:
                losses = settings.lambda_rgb * losses + settings.lambda_perturb * perturb_losses(colors, clean)
            grad = torch.autograd.grad(losses.sum(), noise)[0]
        noise = noise.detach()
        direction, first, second = adam_direction(grad, moments, steps + 1)
        tentative = noise - lr * direction
        if settings.adaptive_selection and len(sizes) > 1:
            with torch.no_grad():
                new_colors = view.render(index, tentative)
            order = torch.argsort(grad.flatten(1).norm(dim=-1), descending=True)
            gain = (rgb_losses(colors.detach(), target) - rgb_losses(new_colors, target))[order].cumsum(0)
            best = max(sizes, key=lambda s: float(gain[s - 1]) / s)
            chosen = order[:best]
        else:
            chosen = index
        noise[chosen] = tentative[chosen]
        moments[0][chosen], moments[1][chosen] = first[chosen], second[chosen]
        steps[chosen] += 1
        if record is not None and t in settings.record_at:
            with torch.no_grad():
                final = view.render(index, noise)
            record(t, final, float(rgb_losses(final, target).mean()))
    return noise
