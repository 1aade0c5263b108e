"""The paper's method (`--method paper`): first-order optimisation of per-sample noise, block by block.

Three recipes are settings of one solver (settings.RECIPES):

- `paper`, the paper's text: Adam, lr 1e-2 decaying by 0.3 over the run, L = λ1·L_rgb + λ2·L_perturb for
  t ≤ μ, else L_rgb (eq. 5, 7, 8; Pixel Perturbation), and Adaptive Pixel Selection (our reading below).
- `authors`, the authors' public code: AdamW over the encoded inputs themselves (so the noise is the
  optimised input minus the clean encoding), lr 0.1 for t < 50 then 0.01, weight decay 0.8·0.3^(t/T)
  applied to the whole encoded input γ + δ, L_rgb only, no APS, no PP.
- `noisenerf` (the default): the authors' without weight decay, lr 0.1 until iteration 250 (docs/methods.md
  says why; the bench's paper_changes measures each).

All three stream the secret view through the solver in contiguous blocks of `block_pixels` pixels (the
authors' 6,144), each optimised for all its iterations before the next starts, and evaluate a block in
passes of at most `pass_samples` samples (gradients summed over passes: each pixel's loss depends on its
own noise only, so this is exact), so memory is bounded by the block and the pass, not the view.

Revival (our addition, on by default; `revival="off"` is the paper as written) has two parts.

- Donor starts. A ray whose samples all have raw density ≤ 0 renders the background whatever its
  colour branch says, and its gradient is exactly zero, so Adam never moves it (32–51 % of a view's
  rays start so; lego's white background is all dead). Before a block is optimised, such a ray starts
  from the encodings of a donor, the live ray of the view whose clean colour is nearest its target
  colour: noise = γ(donor) − γ(ray), sample by sample. It then renders the donor's colour (up to its
  own sample spacing), is live, and receives gradients. `revival="all"` (the default) also gives that
  start to every live ray whose donor is nearer its target than its own clean colour, so most pixels
  begin close to their colour; `"dead"` revives dead rays only.
- A density floor term, floor_weight·relu(density_floor − max_s raw σ_s) per ray, added to L. Rays
  also die during the optimisation (lr 0.1 moves inputs far), and a ray whose densest sample sits
  below zero gets its only gradient from this term; it is zero for clearly live rays.
- A saturation term, floor_weight·Σ_s w_s·Σ_c relu(|raw colour| − saturation_bound) per ray (weights held
  constant). lr 0.1 also carries a dark or bright pixel's visible samples deep into the sigmoid's flat
  tails, where the slope is ~1e-4 and Adam's second moment, remembering the slopes from before, shrinks
  each step to nothing: the pixel stays black or white. This term pulls those raw colours back inside
  ±7, where every 8-bit value is still reachable; it is zero elsewhere.

Measured on the demo scene (12-px procedural secret, 64 samples, authors' recipe, 300 iterations):
SSIM 0.83 with donor starts alone, 0.992 with both (BENCHMARKS.md has lego).

Skipping (ours, on by default; `--no-skip` runs the method as written). A sample whose raw density is
≤ 0 has zero weight (eq. 2), so neither its colour nor its density reaches the loss and its gradient is
exactly zero; it is 81 % of the samples of a lego view at the start and 97 % by the end (the authors'
weight decay pulls every encoded input toward 0, which lego's field leaves empty). Two settings:

- `skip_dead` (exact): the colour branch and the backward pass run only on live samples (and on a
  dead ray's densest sample, which the density floor term moves). The update is unchanged, bit for bit
  on a CPU (rows are padded so that BLAS runs them through the kernel the full batch uses).
- A field kind without dead samples (the hash grid's exp density) leaves out instead each ray's least
  opaque samples while their σΔ sum stays under half an 8-bit step (`negligible`): kept at their checked
  density with colour 0, they move the ray's colour by less than that (approximate, where dead samples
  are exact).
- `recheck_every` (approximate when > 1): a dead sample is not evaluated at all until the next check,
  every recheck_every iterations. Its noise still moves every step (Adam's momentum, weight decay), so
  a sample that comes alive between checks joins at the next one; 1 checks every iteration (exact). A
  check evaluates only the samples whose noise can have moved since the last: without weight decay,
  those a gradient has ever reached (the others have zero moments, so Adam never moves them); with it, all.
  The sample layout only: in the ray layout a sample's noise is its ray's, which the ray's live samples
  move at every step, so there every iteration is a check.

Retiring finished pixels (ours, on by default, off with `--no-skip`): the secret is 8-bit, so a pixel whose
every channel renders within `finish_within` (0.4) levels of its target is as good as it gets. It stops
moving at once (its rows leave Adam's update), and retires from the optimisation at a check once a render
of every one of its samples (not only those live at the last check) confirms it, when `retire_share` of the
open pixels have finished (retiring copies the optimiser's state); until then its samples still run. A
check's colours are exact, so they release a pixel frozen on colours that missed a sample come alive since the
last one, and so does a confirming render that does not confirm it. Pixels do not freeze while Pixel
Perturbation (eq. 7) acts. Pixels can no longer wander out of their bin, and the open pixels shrink as the block
converges: docs/bench/paper_recipe has what it saves and what it costs.

Our reading of Adaptive Pixel Selection (the paper gives no formula): every iteration computes the loss
gradient once on the largest batch, the whole block; for each size s in batch_fractions·(block size) the
candidate update is the Adam step applied to the s pixels with the largest gradient norms; one forward
pass of the tentatively updated block gives each pixel's L_rgb reduction, and the size with the largest
reduction per pixel queried is applied (frozen pixels ranked last). Without APS every open pixel not frozen is
updated every iteration.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Callable, Iterator

import torch

from noisenerf.train.hide.secret_view import SecretView, pass_slices
from noisenerf.train.hide.settings import PaperSettings
from noisenerf.train.scene.render import render_weights


def floor_weight(settings: PaperSettings) -> float:
    """The density floor term's weight: revival's, so zero without revival."""
    return settings.floor_weight if settings.revival != "off" else 0.0


def rgb_losses(colors: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """L_rgb per pixel, ‖Ĉ(γ(p)+δ) − C_M‖² (eq. 5). colors, target: (m, 3) -> (m,)."""
    return ((colors - target) ** 2).sum(-1)


def perturb_losses(colors: torch.Tensor, clean: torch.Tensor) -> torch.Tensor:
    """L_perturb per pixel, −‖Ĉ(γ(p)+δ) − Ĉ(γ(p))‖² (eq. 7). colors, clean: (m, 3) -> (m,)."""
    return -((colors - clean) ** 2).sum(-1)


def total_losses(colors: torch.Tensor, target: torch.Tensor, clean: torch.Tensor, t: int,
                 settings: PaperSettings) -> torch.Tensor:
    """L per pixel at iteration t: λ1·L_rgb + λ2·L_perturb while t ≤ μ with Pixel Perturbation, else L_rgb
    (eq. 8). colors, target, clean: (m, 3) -> (m,)."""
    if settings.pixel_perturbation and t <= settings.mu:
        return settings.lambda_rgb * rgb_losses(colors, target) + settings.lambda_perturb * perturb_losses(colors, clean)
    return rgb_losses(colors, target)


def density_shortfall(raw_density: torch.Tensor, floor: float) -> torch.Tensor:
    """How far each ray's densest sample is below the floor, relu(floor − max_s raw σ_s): zero for rays
    that are clearly live, and the only term with a gradient for a dead ray (its colour has none).
    raw_density: (m, n_samples) -> (m,)."""
    return torch.relu(floor - raw_density.amax(-1))


def saturation_excess(raw_rgb: torch.Tensor, weights: torch.Tensor, bound: float) -> torch.Tensor:
    """How far each ray's visible raw colours are past ±bound, Σ_s w_s·Σ_c relu(|raw_rgb| − bound), the
    weights w (eq. 2) held constant. Past a few units the sigmoid's slope is too small for a colour to come
    back (Adam's second moment remembers the slopes from before), so this term brings it back; every 8-bit
    value is reached inside ±7 (σ(−7) is 0.23 levels). raw_rgb: (m, n_samples, 3), weights: (m, n_samples)
    -> (m,)."""
    return (weights.detach()[..., None] * torch.relu(raw_rgb.abs() - bound)).sum((-2, -1))


def gradient_samples(raw_density: torch.Tensor, dead: torch.Tensor, floor: float | None) -> torch.Tensor:
    """The samples whose gradient is evaluated: live ones (not `dead`: the field kind's negligible samples,
    e.g. raw σ ≤ 0 under ReLU, where a sample has weight 0 in eq. 2 and no slope), and with the density floor
    term (floor not None, raw) the densest samples of each ray below the floor (density_shortfall's
    gradient). raw_density, dead: (m, n_samples) -> bool, same shape."""
    active = ~dead
    if floor is not None:
        densest = raw_density.amax(-1, keepdim=True)
        active |= (raw_density == densest) & (densest < floor)
    return active


def learning_rate(settings: PaperSettings, t: int) -> float:
    """The step size at iteration t (1-based)."""
    if settings.lr_schedule == "step":
        return settings.lr if t <= settings.lr_step_at else settings.lr_after
    return settings.lr * settings.lr_decay ** (t / settings.iters)


def decay_rate(settings: PaperSettings, t: int) -> float:
    """The decoupled weight decay at iteration t: weight_decay·weight_decay_decay^(t/iters)."""
    return settings.weight_decay * settings.weight_decay_decay ** (t / settings.iters)


IN_PLACE_SHARE = 0.5  # Adam works every row in place once this share of them moves (else gathers the moving ones)


def adam_step(state: OpenPixels, grad: torch.Tensor, steps: torch.Tensor, lr: float, betas=(0.9, 0.999),
              eps: float = 1e-8) -> None:
    """Adam with a step count per pixel (APS updates pixels at different times), in place on the state's noise and
    moments (o, k, dims) at the rows that move: those a gradient has reached (`touched`) of pixels not frozen.
    grad: (o, k, dims); steps: (o,) counts after this update. Where most rows move, every row is worked in place
    and the frozen pixels' put back (a row no gradient has reached has zero moments and gradient, so a direction of
    exactly 0); elsewhere the moving rows are gathered. The same bits either way."""
    # per pixel, then broadcast: pow's vectorised and scalar paths round differently
    correction1, correction2 = (1 - betas[0] ** steps.float()), (1 - betas[1] ** steps.float())
    moving = state.touched & ~state.frozen[:, None]
    if moving.float().mean() < IN_PLACE_SHARE:
        rows = moving.nonzero(as_tuple=True)
        first = betas[0] * state.first[rows] + (1 - betas[0]) * grad[rows]
        second = betas[1] * state.second[rows] + (1 - betas[1]) * grad[rows] * grad[rows]
        state.first[rows], state.second[rows] = first, second
        direction = (first / correction1[rows[0], None]) / ((second / correction2[rows[0], None]).sqrt() + eps)
        state.noise[rows] = state.noise[rows] - lr * direction
        return
    frozen = state.frozen.nonzero()[:, 0]
    saved = [tensor[frozen] for tensor in (state.noise, state.first, state.second)]
    state.first.mul_(betas[0]).add_(grad * (1 - betas[0]))
    scratch = grad * (1 - betas[1])
    state.second.mul_(betas[1]).add_(scratch.mul_(grad))
    denominator = torch.div(state.second, correction2[:, None, None], out=scratch).sqrt_().add_(eps)
    state.noise.sub_((state.first / correction1[:, None, None]).div_(denominator).mul_(lr))
    for tensor, rows in zip((state.noise, state.first, state.second), saved):
        tensor[frozen] = rows


@dataclass(frozen=True)
class ViewSurvey:
    """The clean view: each ray's colour and whether any of its samples has positive raw density."""

    colors: torch.Tensor  # (n_rays, 3)
    alive: torch.Tensor  # (n_rays,) bool


def survey(secret_view: SecretView, pass_samples: int) -> ViewSurvey:
    """Render the view without noise, pass by pass, noting dead rays (every sample at the field kind's
    zero slope: raw density ≤ 0 under ReLU)."""
    colors, alive = [], []
    device = secret_view.device
    zero = torch.zeros(1, 1, secret_view.noise_dims, device=device)
    with torch.no_grad():
        for part in pass_slices(secret_view.n_rays, secret_view.n_samples, pass_samples):
            index = torch.arange(part.start, part.stop, device=device)
            raw_rgb, raw_density = secret_view.raw(index, zero)
            alive.append(~secret_view.field.zero_slope(raw_density).all(-1))
            colors.append(secret_view.shade(index, raw_rgb, raw_density))
    return ViewSurvey(torch.cat(colors), torch.cat(alive))


def nearest_donors(targets: torch.Tensor, clean: ViewSurvey, rows: int = 1024) -> tuple[torch.Tensor, torch.Tensor]:
    """For each target colour, the live ray whose clean colour is nearest, and that distance, a few rows
    at a time so memory stays rows × n_live. targets: (m, 3) -> donors (m,) int64, distances (m,);
    donors are −1 where the view has no live ray."""
    live = clean.alive.nonzero()[:, 0]
    if live.numel() == 0:
        return (torch.full(targets.shape[:1], -1, device=targets.device),
                torch.full(targets.shape[:1], float("inf"), device=targets.device))
    distances, donors = [], []
    for start in range(0, targets.shape[0], rows):
        nearest = torch.cdist(targets[start:start + rows], clean.colors[live]).min(dim=1)
        distances.append(nearest.values)
        donors.append(live[nearest.indices])
    return torch.cat(donors), torch.cat(distances)


def revival_noise(secret_view: SecretView, index: torch.Tensor, targets: torch.Tensor, clean: ViewSurvey,
                  mode: str) -> torch.Tensor:
    """Starting noise per sample that gives rays `index` (m,) the encodings of their colour donor,
    γ(donor) − γ(ray): for dead rays (mode "dead"), or also for live rays whose donor is nearer their
    target than their own clean colour (mode "all"); zero elsewhere. targets: (m, 3) in [0, 1]
    -> (m, n_samples, dims)."""
    noise = torch.zeros(index.numel(), secret_view.n_samples, secret_view.noise_dims, device=secret_view.device)
    if mode == "off":
        return noise
    donors, distances = nearest_donors(targets, clean)
    own = torch.linalg.vector_norm(targets - clean.colors[index], dim=-1)
    revive = (donors >= 0) & (~clean.alive[index] | ((mode == "all") & (distances < own)))
    noise[revive] = secret_view.encodings(donors[revive]) - secret_view.encodings(index[revive])
    return noise


def select_pixels(gain: torch.Tensor, grad_norms: torch.Tensor, sizes: list[int]) -> torch.Tensor:
    """Adaptive Pixel Selection (eq. 6, as we read it in the module docstring): of the prefixes (largest
    gradient norm first) of each size, the one with the largest total L_rgb reduction per pixel.
    gain, grad_norms: (m,) -> chosen pixel positions (s,)."""
    order = torch.argsort(grad_norms, descending=True)
    cumulative = gain[order].cumsum(0)
    best = max(sizes, key=lambda s: float(cumulative[s - 1]) / s)
    return order[:best]


def selection_sizes(settings: PaperSettings, m: int) -> list[int]:
    """APS's candidate batch sizes for m open pixels: batch_fractions of m, at least one pixel each."""
    return sorted({max(1, int(round(f * m))) for f in settings.batch_fractions})


def finished_pixels(colors: torch.Tensor, levels: torch.Tensor, within: float) -> torch.Tensor:
    """Pixels whose every channel renders within `within` 8-bit levels of its target: they round to it,
    with 0.5 − within of the bin left for the reveal's float32 to differ by. colors: (m, 3) in [0, 1],
    levels: (m, 3) integer-valued -> (m,) bool."""
    return ((colors * 255 - levels).abs() <= within).all(-1)


def confirmed(problem: BlockProblem, state: OpenPixels, within: float) -> torch.Tensor:
    """Which frozen open pixels (o,) bool are finished when every one of their samples is rendered, not
    only the samples live at the last check: the pixels that leave the optimisation."""
    candidates = state.frozen.nonzero()[:, 0]
    problem.work[1] += candidates.numel() * problem.secret_view.n_samples
    leaving = torch.zeros_like(state.frozen)
    colors = BlockProblem(problem.secret_view, problem.index[state.frozen], problem.settings).render_all(
        state.noise[candidates])
    leaving[candidates] = finished_pixels(colors, state.levels[candidates], within)
    return leaving


Recorder = Callable[[int, torch.Tensor, float], None]  # (iteration, colours (m, 3), mean L_rgb)


# (colours (p, 3), raw colours (p, n_samples, 3), raw densities (p, n_samples), part) -> (p,)
Loss = Callable[[torch.Tensor, torch.Tensor, torch.Tensor, slice], torch.Tensor]


class BlockProblem:
    """One block's rays of a secret view, rendered in bounded passes. With skipping, a pass evaluates only
    the samples that were live at the last check (gradient_samples); the others keep the raw density that
    check found (≤ 0: zero weight) and colour 0.

    work counts [samples through the full forward and backward pass, samples through a forward pass without
    gradients (density checks, renders confirming finished pixels), pixel-iterations with no sample to evaluate
    (retired pixels' among them)]; a subset counts in its parent's."""

    def __init__(self, secret_view: SecretView, index: torch.Tensor, settings: PaperSettings):
        self.secret_view, self.index, self.settings = secret_view, index, settings
        self.parts = pass_slices(index.numel(), secret_view.n_samples, settings.pass_samples)
        self.raw_floor = secret_view.field.raw_density_at(settings.density_floor)
        self.floor = self.raw_floor if floor_weight(settings) else None
        self.checked_density: torch.Tensor | None = None  # (m, n_samples) at the last check
        self.active: torch.Tensor | None = None  # (m, n_samples) bool: gradient_samples at the last check
        self.grad: torch.Tensor | None = None  # gradient_buffer's
        self.written: torch.Tensor | None = None  # (w,) the flattened samples whose rows it last wrote
        self.work = torch.zeros(3, dtype=torch.int64, device=index.device)  # counted where it runs: no host sync

    def forget(self) -> None:
        """Drops the check and the gradient buffer (a subset has its own)."""
        self.checked_density = self.active = self.grad = self.written = None

    def subset(self, keep: torch.Tensor) -> BlockProblem:
        """The same problem for the rays `keep` (m,) bool picks, its last check carried over and its work
        counted in this one's."""
        part = BlockProblem(self.secret_view, self.index[keep], self.settings)
        if self.checked_density is not None:
            part.checked_density, part.active = self.checked_density[keep], self.active[keep]
        part.work = self.work
        return part

    def render(self, noise: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) with noise (m, k, dims), without gradients: of the checked live samples when dead
        ones are skipped between checks, else of every sample."""
        with torch.no_grad():
            if self.settings.skip_dead and self.recheck_interval(noise.shape[1]) > 1:
                return torch.cat([self.skipping_pass(noise[p], p, None) for p in self.parts])
            return self.render_all(noise)

    def render_all(self, noise: torch.Tensor) -> torch.Tensor:
        """Colours (m, 3) with noise (m, k, dims) from every sample, without gradients."""
        with torch.no_grad():
            return torch.cat([self.secret_view.render(self.index[p], noise[p]) for p in self.parts])

    def check(self, noise: torch.Tensor, moved: torch.Tensor | None) -> None:
        """Every sample's raw density with noise (m, k, dims): which samples the next passes evaluate. Only
        the samples of `moved` rows (m, k) bool, those whose noise may have changed since the last check,
        are evaluated (None: all): the others keep the density they had, exactly."""
        with torch.no_grad():
            if self.checked_density is None or moved is None:
                self.checked_density = torch.cat([self.secret_view.raw_density(self.index[p], noise[p])
                                                  for p in self.parts])
                self.work[1] += self.checked_density.numel()
            else:
                self.recheck(noise, moved.expand(-1, self.secret_view.n_samples))
        self.active = gradient_samples(self.checked_density, self.secret_view.field.negligible(
            self.checked_density, self.secret_view.deltas[self.index]), self.floor)

    def recheck(self, noise: torch.Tensor, moved: torch.Tensor) -> None:
        """The raw density of the samples moved (m, n_samples) bool picks, into checked_density."""
        own = noise.shape[1] == self.secret_view.n_samples
        for part in self.parts:
            samples = moved[part].flatten().nonzero()[:, 0]
            rows = noise[part].flatten(0, 1)[samples] if own else noise[part][samples // self.secret_view.n_samples, 0]
            self.checked_density[part] = self.secret_view.raw_density_of(self.index[part], rows, samples,
                                                                         self.checked_density[part])
            self.work[1] += samples.numel()

    def losses_and_grad(self, noise: torch.Tensor, loss: Loss, t: int, moved: torch.Tensor | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """Colours (m, 3) and ∂Σloss/∂noise (m, k, dims) at iteration t, pass by pass; `moved` as in check. The
        gradient is this problem's buffer (gradient_buffer): read it before the next call."""
        if not self.settings.skip_dead:
            return self.full_losses_and_grad(noise, loss)
        if (t - 1) % self.recheck_interval(noise.shape[1]) == 0:
            self.check(noise, moved)
        grad = self.gradient_buffer(noise)
        return torch.cat([self.skipping_pass(noise[part], part, loss, grad[part]) for part in self.parts]), grad

    def weights(self, part: slice, raw_density: torch.Tensor) -> torch.Tensor:
        """The rendering weights w (eq. 2) (p, n_samples) of the rays of pass `part` from their raw densities."""
        view = self.secret_view
        return render_weights(view.field.density_of(raw_density), view.deltas[self.index[part]])

    def recheck_interval(self, k: int) -> int:
        """Iterations between density checks for noise of k vectors per ray: every iteration in the ray
        layout (k = 1), where a dead sample's noise is its ray's, which the live samples' gradients move."""
        return self.settings.recheck_every if k == self.secret_view.n_samples else 1

    def full_losses_and_grad(self, noise: torch.Tensor, loss: Loss) -> tuple[torch.Tensor, torch.Tensor]:
        """losses_and_grad through every sample (the method as written)."""
        colors, grads = [], []
        for part in self.parts:
            piece = noise[part].detach().requires_grad_(True)
            with torch.enable_grad():
                raw_rgb, raw_density = self.secret_view.raw(self.index[part], piece)
                rendered = self.secret_view.shade(self.index[part], raw_rgb, raw_density)
                grads.append(torch.autograd.grad(loss(rendered, raw_rgb, raw_density, part).sum(), piece)[0])
            colors.append(rendered.detach())
        self.work[0] += noise.shape[0] * self.secret_view.n_samples
        return torch.cat(colors), torch.cat(grads)

    def skipping_pass(self, piece: torch.Tensor, part: slice, loss: Loss | None, grad: torch.Tensor | None = None
                      ) -> torch.Tensor:
        """One pass's colours (p, 3), evaluating only the samples active at the last check; with a loss,
        ∂Σloss/∂noise is written into grad (p, k, dims), whose rows for the other samples must be zero
        (losses_and_grad keeps them so)."""
        active = self.active[part]
        samples = active.flatten().nonzero()[:, 0]
        n_samples = self.secret_view.n_samples
        own = piece.shape[1] == n_samples  # the sample layout: an evaluated sample's noise row is its own
        leaf = (piece.flatten(0, 1)[samples] if own else piece).detach()
        leaf.requires_grad_(loss is not None and samples.numel() > 0)
        with torch.set_grad_enabled(leaf.requires_grad):
            rows = leaf if own else leaf.expand(-1, n_samples, -1).flatten(0, 1)[samples]
            raw_rgb, raw_density = self.secret_view.raw_of(self.index[part], rows, samples, self.checked_density[part])
            rendered = self.secret_view.shade(self.index[part], raw_rgb, raw_density)
            if loss is None:
                return rendered
            self.count(active)
            if leaf.requires_grad:
                sample_grad = torch.autograd.grad(loss(rendered, raw_rgb, raw_density, part).sum(), leaf)[0]
                if own:
                    grad.view(-1, grad.shape[-1])[samples] = sample_grad
                else:
                    grad.copy_(sample_grad)
        return rendered.detach()

    def gradient_buffer(self, noise: torch.Tensor) -> torch.Tensor:
        """A tensor shaped like noise (m, k, dims), zero except where the last pass wrote (kept from one
        iteration to the next: a fresh one every iteration costs more in page faults than the passes)."""
        if self.grad is None or self.grad.shape != noise.shape:
            self.grad = torch.zeros_like(noise)
        elif noise.shape[1] == self.secret_view.n_samples:
            self.grad.view(-1, noise.shape[-1]).index_fill_(0, self.written, 0)
        else:
            self.grad.zero_()
        if noise.shape[1] == self.secret_view.n_samples:
            self.written = self.active.flatten().nonzero()[:, 0]
        return self.grad

    def gradient_rows(self, k: int) -> torch.Tensor:
        """Which noise rows (m, k) this iteration's gradient can reach (all of them without skipping)."""
        if not self.settings.skip_dead:
            return torch.ones(self.index.numel(), k, dtype=torch.bool, device=self.index.device)
        return self.active if k == self.secret_view.n_samples else self.active.any(-1, keepdim=True)

    def count(self, active: torch.Tensor) -> None:
        """Counts a pass's work: its active samples (p, n_samples) and its idle pixels."""
        self.work[0] += active.sum()
        self.work[2] += (~active.any(-1)).sum()


@contextlib.contextmanager
def matmul_precision(tf32: bool):
    """CUDA matmuls in TF32 inside the block when asked, restoring the caller's setting after."""
    before = torch.backends.cuda.matmul.allow_tf32
    torch.backends.cuda.matmul.allow_tf32 = tf32
    try:
        yield
    finally:
        torch.backends.cuda.matmul.allow_tf32 = before


def solve_block(secret_view: SecretView, index: torch.Tensor, pixels: torch.Tensor, noise: torch.Tensor,
                clean: torch.Tensor, settings: PaperSettings, record: Recorder | None = None
                ) -> tuple[torch.Tensor, torch.Tensor]:
    """Optimise the noise of rays `index` (m,) toward 8-bit pixels (m, 3) from a starting noise
    (m, k, dims) (k = 1 or n_samples), clean colours (m, 3) for eq. 7. Returns the noise (m, k, dims) and
    the block's work (BlockProblem.work)."""
    problem = BlockProblem(secret_view, index, settings)
    target = pixels.float() / 255.0
    noise = noise.clone()
    # the encoded input the authors' weight decay shrinks: γ + δ, with γ broadcast to the noise's shape
    encoded = secret_view.encodings(index) if settings.weight_decay else None
    if encoded is not None and noise.shape[1] != secret_view.n_samples:
        encoded = encoded.mean(1, keepdim=True)
    with matmul_precision(settings.tf32 and noise.is_cuda):
        return optimise(problem, target, noise, clean, encoded, settings, record), problem.work


@dataclass
class OpenPixels:
    """The optimiser's state of a block's open pixels (o of them): their rows of every per-pixel tensor."""

    positions: torch.Tensor  # (o,) their positions in the block
    noise: torch.Tensor  # (o, k, dims)
    first: torch.Tensor  # (o, k, dims) Adam's moments
    second: torch.Tensor
    steps: torch.Tensor  # (o,) Adam's step counts
    touched: torch.Tensor  # (o, k) bool: rows a gradient has reached
    frozen: torch.Tensor  # (o,) bool: finished (finished_pixels), not yet confirmed
    target: torch.Tensor  # (o, 3) in [0, 1]
    levels: torch.Tensor  # (o, 3) the target's 8-bit values
    clean: torch.Tensor  # (o, 3) colours without noise, for eq. 7
    encoded: torch.Tensor | None  # (o, k, dims) the encoded inputs γ, for the authors' weight decay (of γ + δ)

    @staticmethod
    def start(noise: torch.Tensor, target: torch.Tensor, clean: torch.Tensor, encoded: torch.Tensor | None
              ) -> OpenPixels:
        """Every pixel of a block open, at its starting noise (m, k, dims) (this tensor, not a copy), Adam's
        state zero. target, clean: (m, 3); encoded: (m, k, dims), or None without weight decay."""
        m, device = noise.shape[0], noise.device
        return OpenPixels(torch.arange(m, device=device), noise, torch.zeros_like(noise), torch.zeros_like(noise),
                          torch.zeros(m, dtype=torch.int64, device=device),
                          torch.zeros(noise.shape[:2], dtype=torch.bool, device=device),
                          torch.zeros(m, dtype=torch.bool, device=device), target, (target * 255).round(), clean, encoded)

    def kept(self, keep: torch.Tensor) -> OpenPixels:
        """The pixels `keep` (o,) bool picks, none of them frozen: a frozen pixel the confirming render did not
        confirm moves again."""
        rows = {field.name: None if getattr(self, field.name) is None else getattr(self, field.name)[keep]
                for field in dataclasses.fields(self)}
        return OpenPixels(**rows | {"frozen": torch.zeros_like(rows["frozen"])})


def optimise(problem: BlockProblem, target: torch.Tensor, noise: torch.Tensor, clean: torch.Tensor,
             encoded: torch.Tensor | None, settings: PaperSettings, record: Recorder | None) -> torch.Tensor:
    """The iterations of solve_block (see there). The optimiser runs on the open pixels: a finished pixel
    (finished_pixels) stops moving at once and retires at a check, once a render of every one of its samples
    confirms it, its noise written to the block's (`noise`, returned)."""
    whole, m, state = problem, noise.shape[0], OpenPixels.start(noise, target, clean, encoded)
    for t in range(1, settings.iters + 1):
        # retiring copies the open pixels' state: worth it once a few percent of them have finished
        if settings.finish_within is not None and (t - 1) % problem.recheck_interval(noise.shape[1]) == 0 and int(
                state.frozen.sum()) >= max(1, settings.retire_share * state.positions.numel()):
            leaving = confirmed(problem, state, settings.finish_within)
            noise[state.positions[leaving]] = state.noise[leaving]
            problem, state = problem.subset(~leaving), state.kept(~leaving)
            whole.forget()  # only its view and work counter are used from here on
        whole.work[2] += m - state.positions.numel()  # pixels that have left are idle
        if state.positions.numel():
            state = iteration(problem, state, t, settings)
        if record is not None and t in settings.record_at:
            write_back(noise, state)
            colors = whole.render_all(noise)
            record(t, colors, float(rgb_losses(colors, target).mean()))
    write_back(noise, state)
    return noise


def write_back(noise: torch.Tensor, state: OpenPixels) -> None:
    """The open pixels' noise into the block's (m, k, dims), unless it is still the block's own tensor (no
    pixel has left)."""
    if state.noise is not noise:
        noise[state.positions] = state.noise


def decay_encoded(state: OpenPixels, rate: float) -> None:
    """The authors' decoupled weight decay on the encoded inputs, δ ← δ − rate·(γ + δ), in place (a fresh
    tensor every step costs more in page faults than in arithmetic), frozen pixels left alone."""
    moving = ~state.frozen
    if moving.all():
        state.noise.mul_(1 - rate).sub_(state.encoded, alpha=rate)
    else:
        state.noise[moving] = state.noise[moving] * (1 - rate) - rate * state.encoded[moving]


def iteration(problem: BlockProblem, state: OpenPixels, t: int, settings: PaperSettings) -> OpenPixels:
    """One Adam step (1-based t) of the open pixels; their state is updated in place unless APS keeps a copy."""
    lr, weight = learning_rate(settings, t), floor_weight(settings)
    # the rows that have moved: those a gradient has reached (Adam moves only them), or all under weight decay
    moved = None if settings.weight_decay else state.touched
    colors, grad = problem.losses_and_grad(state.noise, lambda rendered, raw_rgb, raw_density, part: (
        total_losses(rendered, state.target[part], state.clean[part], t, settings)
        + weight * (density_shortfall(raw_density, problem.raw_floor)
                    + saturation_excess(raw_rgb, problem.weights(part, raw_density.detach()), settings.saturation_bound))), t, moved)
    if settings.finish_within is not None and not (settings.pixel_perturbation and t <= settings.mu):
        finished = finished_pixels(colors, state.levels, settings.finish_within)
        # a check's colours are exact: they also release a pixel frozen on colours that missed a sample come alive
        checked = (t - 1) % problem.recheck_interval(state.noise.shape[1]) == 0
        state.frozen = finished if checked else state.frozen | finished
    # the rows a gradient has reached: only they move (elsewhere Adam's direction is exactly 0)
    state.touched |= problem.gradient_rows(state.noise.shape[1])
    sizes = selection_sizes(settings, state.noise.shape[0])
    aps = settings.adaptive_selection and len(sizes) > 1
    # APS keeps the old state of the pixels it does not choose; otherwise update in place
    tentative = dataclasses.replace(state, noise=state.noise.clone(), first=state.first.clone(),
                                    second=state.second.clone()) if aps else state
    if settings.weight_decay:
        decay_encoded(tentative, lr * decay_rate(settings, t))
    adam_step(tentative, grad, state.steps + 1, lr)
    if not aps:
        state.steps += (~state.frozen).long()
        return state
    gain = rgb_losses(colors, state.target) - rgb_losses(problem.render(tentative.noise), state.target)
    chosen = select_pixels(gain, grad.flatten(1).norm(dim=-1).masked_fill(state.frozen, -1.0), sizes)  # frozen last
    state.noise[chosen], state.steps[chosen] = tentative.noise[chosen], state.steps[chosen] + 1
    state.first[chosen], state.second[chosen] = tentative.first[chosen], tentative.second[chosen]
    return state


@dataclass(frozen=True)
class BlockResult:
    index: torch.Tensor  # (m,) rays of the view
    noise: torch.Tensor  # (m, k, dims), on the CPU in the storage dtype
    colors: torch.Tensor  # (len(points), m, 3): the block's colours at each recorded iteration, on the CPU
    work: torch.Tensor  # (3,) int64, BlockProblem.work


def skip_shares(work: torch.Tensor, n_rays: int, n_samples: int, iters: int) -> dict[str, float]:
    """What skipping left out of a view's blocks, whose work (BlockProblem.work) adds up to `work` (3,), as
    shares of the method as written (every sample of every ray through the forward and backward pass at
    every iteration): sample-iterations not through that pass, samples through a pass without gradients (density
    checks, retiring's confirming renders) per sample-iteration, and pixel-iterations with nothing evaluated."""
    evaluated, checked, idle = work.tolist()
    sample_iterations = n_rays * n_samples * iters
    return {"skipped_samples": 1 - evaluated / sample_iterations, "checked_samples": checked / sample_iterations,
            "idle_pixels": idle / (n_rays * iters)}


def recorded_points(settings: PaperSettings) -> list[int]:
    """The iterations at which blocks record their colours."""
    return [t for t in settings.record_at if t <= settings.iters]


def solve_blocks(secret_view: SecretView, pixels: torch.Tensor, layout_samples: int, settings: PaperSettings,
                 clean: ViewSurvey, dtype: torch.dtype) -> Iterator[BlockResult]:
    """The view's blocks one after another, each solved. pixels: (n_rays, 3) uint8."""
    for start in range(0, secret_view.n_rays, settings.block_pixels):
        index = torch.arange(start, min(start + settings.block_pixels, secret_view.n_rays), device=pixels.device)
        yield solved_block(secret_view, index, pixels[index], layout_samples, settings, clean, dtype)


def solved_block(secret_view: SecretView, index: torch.Tensor, pixels: torch.Tensor, layout_samples: int,
                 settings: PaperSettings, clean: ViewSurvey, dtype: torch.dtype) -> BlockResult:
    """One block of rays `index` (m,) solved toward its pixels (m, 3) uint8 from its revival start."""
    recorded = []
    noise, work = solve_block(secret_view, index, pixels, start_noise(secret_view, index, pixels, layout_samples, clean, settings),
                        clean.colors[index], settings, lambda t, colors, loss: recorded.append(colors.cpu()))
    colors = torch.stack(recorded) if recorded else torch.zeros(len(recorded_points(settings)), index.numel(), 3)
    return BlockResult(index, noise.to(dtype).cpu(), colors, work.cpu())


def start_noise(secret_view: SecretView, index: torch.Tensor, pixels: torch.Tensor, layout_samples: int,
                clean: ViewSurvey, settings: PaperSettings) -> torch.Tensor:
    """The block's starting noise (m, layout_samples, dims): revival noise (zero with revival off); in
    the ray layout a ray's one noise vector is the mean of its samples' revival noise."""
    noise = revival_noise(secret_view, index, pixels.float() / 255.0, clean, settings.revival)
    return noise if layout_samples == secret_view.n_samples else noise.mean(1, keepdim=True)
