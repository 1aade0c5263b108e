"""Noise solvers for a set of a secret view's pixels (a hide's part, or a compact basis's sample).

`solve_exact` (the default) renders its secret view with a single sample per ray. That sample's interval
is the 1e10 last one, so once its density is positive its opacity is exactly 1 and the pixel's colour is
the sigmoid of the field's raw colour. Each pixel is then four equations in its noise values (90 for
the standard NeRF) — raw colour = logit(target colour), raw density ≥ the raw floor (raw_floors: the
field kind's inverse density activation at density_floor) — and all four are piecewise linear in the
noise (every kind's networks are ReLU nets), so a Gauss–Newton step lands exactly unless it crosses a
ReLU boundary. The step
is the minimum-norm Levenberg–Marquardt one, δ += Jᵀ(JJᵀ + λI)⁻¹r, with a short backtracking line search;
J is exact (the field's hand-written four-row reverse pass), and a pixel retires as soon as it is
finished, so later iterations only pay for the few left. Every 16th pixel is solved first; the others
start from the noise of the solved seed nearest in target colour, moved by a few Gauss–Newton steps
with that seed's Jacobian (chord_start: forward passes only, which spare Jacobians of their own).

Two phases: the first solves in float32 until every channel sits within `tolerance_bins` of its bin's
centre; the second rounds to the storage dtype and polishes, judging only storable noise, until every
channel rounds to its 8-bit value with `margin_bins` to spare (far more than the torch ↔ onnxruntime
disagreement). Between the phases, a compact tile's integer lattice (each of its k coefficients in
steps that move a colour by about CompactSettings.step_bins) is entered by round_to_lattice, a search
among nearby lattice points predicted by the Jacobian: the steps of k coefficients together can move a
colour by more than a bin, so plain rounding would leave many pixels to LM on the lattice, which costs far
more Jacobians than rendering a few predicted points.

A solve is one ExactProblem, what stays fixed over it (the view and its pixels, the noise space,
settings, generator and counts), which every step takes; what Levenberg–Marquardt changes from one
iteration to the next is a Refinement. The solver renders through a SolverView: the whole field
(SecretView), or for a compact tile whose noise moves only γ(d), the view branch alone (BranchView, ~1/12
of the multiply-adds).

A pixel that has not finished after `restart_after` iterations, or whose Jacobian is zero (every ReLU
it needs is off), restarts from the noise of a finished pixel of nearby target colour; every other
restart is a seeded random start instead, and each further restart of the same pixel draws from more
donors and adds a wider seeded jitter.

The paper's own method lives in paper.py; exact_solver.py runs this solver over a tile.
"""

from __future__ import annotations

import dataclasses
import itertools
from dataclasses import dataclass

import torch

from noisenerf.train.hide.secret_view import BranchView, SecretView
from noisenerf.train.hide.settings import ExactSettings

SolverView = SecretView | BranchView  # what the solver renders: the whole field, or its view branch alone

END_PULL_BINS = 0.2  # targets for 0 and 255 sit this far inside, where a sigmoid can arrive
# Levenberg–Marquardt's λ schedule (÷3 after a step that improved, ×10 after one that did not, within a range):
# fixed constants of the algorithm beside ExactSettings, which holds what bundles record and runs may vary
DAMPING_DOWN, DAMPING_UP, DAMPING_RANGE = 3.0, 10.0, (1e-7, 1e6)


def bin_targets(pixels: torch.Tensor) -> torch.Tensor:
    """Centres of the 8-bit bins, pulled END_PULL_BINS inside at 0 and 255 where a sigmoid never
    arrives. pixels: (m, 3) uint8 -> (m, 3) float32 in (0, 1)."""
    return torch.clamp(pixels.float() / 255.0, END_PULL_BINS / 255.0, 1.0 - END_PULL_BINS / 255.0)


def logit(p: torch.Tensor) -> torch.Tensor:
    """Inverse sigmoid, log(p / (1 − p)). (...) -> (...)."""
    return torch.log(p) - torch.log1p(-p)


def quantize(noise: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """Round to the storage dtype and back, so the solver only ever judges storable noise."""
    return noise.to(dtype).to(noise.dtype)


INTEGER_LIMITS = {torch.int8: 127, torch.int16: 32767}  # symmetric ranges (−128 / −32768 never written)


@dataclass(frozen=True)
class NoiseSpace:
    """The unknowns of a part's pixels, `params` (m, P), and how they become noise (m, 1, dims).

    Full space (basis None): the params are the noise itself, stored in a float dtype (P = dims).
    Basis space: noise = offset + params Bᵀ with B (dims, k) (a compact tile's: orthogonal columns, stretched). With a float storage
    dtype the params are rounded to it (a compact tile's basis is found in float32); with an integer one
    (a compact tile) the params are q · scale for integers q, so `store` rounds them to the integer lattice.
    Expanding exactly as the reveal does (runtime.layouts.expand_coefficients: one float32 multiply, then
    the matmul) keeps what the solver judges what the recipient renders, to float32 summation order.
    """

    storage: torch.dtype
    basis: torch.Tensor | None = None  # (dims, k) float32
    offset: torch.Tensor | None = None  # (dims,) float32
    scale: float = 1.0  # compact: one integer step of a coefficient

    def expand(self, params: torch.Tensor) -> torch.Tensor:
        """(m, P) -> noise (m, 1, dims) float32."""
        if self.basis is None:
            return params[:, None, :]
        return (self.offset + params @ self.basis.T)[:, None, :]

    def chain(self, jacobian: torch.Tensor) -> torch.Tensor:
        """∂outputs/∂noise (m, 4, dims) -> ∂outputs/∂params (m, 4, P)."""
        return jacobian if self.basis is None else jacobian @ self.basis

    def store(self, params: torch.Tensor) -> torch.Tensor:
        """The nearest storable params: float rounding, or the clamped integer lattice. (m, P) -> (m, P)."""
        if not self.lattice:
            return quantize(params, self.storage)
        return self.params_of(self.integers(params))

    @property
    def lattice(self) -> bool:
        """Whether params are integer coefficients (times scale)."""
        return not self.storage.is_floating_point

    def params_of(self, integers: torch.Tensor) -> torch.Tensor:
        """Compact params of integer coefficients, q · scale in float32 as the reveal computes it. (...) -> (...)."""
        return integers.float() * torch.tensor(self.scale, dtype=torch.float32)

    def integers(self, params: torch.Tensor) -> torch.Tensor:
        """Compact params as their stored integers. (m, k) float32 -> (m, k) int8/int16."""
        limit = INTEGER_LIMITS[self.storage]
        return torch.clamp(torch.round(params / self.scale), -limit, limit).to(self.storage)

    def noise_units(self, like: torch.Tensor) -> torch.Tensor:
        """Params per unit of noise along each coordinate, (P,) like `like`'s: 1 in the full space, 1/‖Bⱼ‖ in a
        basis (a compact tile's columns are stretched to its lattice steps), so that a random restart or
        jitter of a given spread moves the noise alike in every space."""
        if self.basis is None:
            return torch.ones(like.shape[-1], dtype=like.dtype, device=like.device)
        return 1.0 / self.basis.norm(dim=0).clamp_min(1e-30)

    def width(self, dims: int) -> int:
        """P, the params per pixel for noise of `dims` values."""
        return dims if self.basis is None else self.basis.shape[1]

    def zeros(self, m: int, dims: int, device: torch.device) -> torch.Tensor:
        """Params of zero noise offset: (m, P)."""
        return torch.zeros(m, self.width(dims), device=device)


def sample_outputs(secret_view: SolverView, index: torch.Tensor, noise: torch.Tensor) -> torch.Tensor:
    """Raw colour and raw density of each ray's single sample. index: (m,), noise: (m, 1, dims) -> (m, 4)."""
    raw_rgb, raw_density = secret_view.raw(index, noise)
    return torch.cat([raw_rgb[:, 0], raw_density[:, :1]], dim=-1)


SINGULAR_DAMPING = 1e-4  # λ for a system singular in float32: well above float32's ε, as small as the start λ


def residuals(outputs: torch.Tensor, goal: torch.Tensor, floor: float) -> torch.Tensor:
    """What each equation still lacks: logit targets − raw colour, and the density shortfall (0 once the
    density is above the floor). outputs: (m, 4), goal: (m, 3) -> (m, 4)."""
    return torch.cat([goal - outputs[:, :3], torch.clamp_min(floor - outputs[:, 3:], 0.0)], dim=-1)


def damped_step(jac: torch.Tensor, residual: torch.Tensor, damping: torch.Tensor) -> torch.Tensor:
    """Minimum-norm Levenberg–Marquardt step Jᵀ(JJᵀ + λ·(tr(JJᵀ)/k)·I)⁻¹ r.
    jac: (m, k, P), residual: (m, k), damping: (m,) -> (m, P).

    A pixel whose rows of J are dependent (outputs that move together) while λ has shrunk below float32's
    resolution of JJᵀ gets a singular system; it is solved again with λ at SINGULAR_DAMPING instead."""
    normal = jac @ jac.transpose(1, 2)
    trace = normal.diagonal(dim1=1, dim2=2).mean(-1)
    eye = torch.eye(jac.shape[1], dtype=jac.dtype, device=jac.device)
    solution, info = torch.linalg.solve_ex(normal + (damping * trace + 1e-12)[:, None, None] * eye,
                                           residual[..., None])
    singular = info != 0
    if singular.any():
        floor = SINGULAR_DAMPING * trace[singular] + 1e-12
        solution[singular] = torch.linalg.solve(normal[singular] + floor[:, None, None] * eye,
                                                residual[singular][..., None])
    return (jac.transpose(1, 2) @ solution)[..., 0]


def colour_distance_bins(outputs: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
    """Largest per-channel distance of the sample's colour from a reference colour, in 8-bit bins.
    outputs: (m, 4), reference: (m, 3) in [0, 1] -> (m,)."""
    return torch.abs(torch.sigmoid(outputs[:, :3]) - reference).amax(-1) * 255.0


def donor_noise(stuck: torch.Tensor, finished: torch.Tensor, goal: torch.Tensor, noise: torch.Tensor,
                generator: torch.Generator, pool: torch.Tensor) -> torch.Tensor:
    """Restart points for stuck pixels: the params of a finished pixel picked at random among the pool[i]
    nearest in target logits. stuck (s,), finished: index tensors into goal (m, 3) / params (m, P);
    pool: (s,) int64 ≥ 1."""
    k = min(int(pool.max()), finished.numel())
    nearest = torch.cdist(goal[stuck], goal[finished]).topk(k, largest=False).indices
    pick = (torch.rand(stuck.numel(), generator=generator).to(pool.device) * pool.clamp_max(k)).long()
    return noise[finished[nearest[torch.arange(stuck.numel(), device=nearest.device), pick]]]


MIN_PIVOT_SINE = 1e-4  # pivot columns spanning less than this share of their lengths' volume count as rank < 3


def lattice_candidates(coords: torch.Tensor, jac: torch.Tensor, radius: int) -> torch.Tensor:
    """Integer points near where a pixel's linearised colour equations hold, for a coarse lattice where
    plain rounding misses the 8-bit bin. Of the k coordinates, the 3 whose columns of J span the most
    volume are pivots and the other k − 3 are free; each free coordinate takes the integers within
    ±radius of its continuous value, the pivots are solved for (J (q − coords) = 0) and rounded, so
    only the pivots' rounding perturbs the colour (Babai's rounding on a projected lattice).
    coords: (m, k) continuous lattice coordinates of a solution, jac: (m, 3, k) ∂raw colour/∂coordinate
    (k ≥ 3) -> (m, c, k) integer-valued float32 candidates, c = (2·radius + 1)^(k − 3)."""
    m, _, k = jac.shape
    subsets = torch.tensor(list(itertools.combinations(range(k), 3)), device=jac.device)
    volumes = torch.linalg.det(jac[:, :, subsets].permute(0, 2, 1, 3)).abs()  # (m, subsets)
    best = volumes.argmax(1)
    pivots = subsets[best]  # (m, 3)
    # relative to its columns' lengths, the volume says how far from rank 3 the pivots are: in float32 a
    # rank-2 J has a small nonzero determinant, whose solve would send the pivots to the lattice's edge
    lengths = jac.norm(dim=1).gather(1, pivots).prod(1)
    singular = volumes.gather(1, best[:, None])[:, 0] <= MIN_PIVOT_SINE * lengths
    is_free = torch.ones(m, k, dtype=torch.bool, device=jac.device).scatter(1, pivots, False)
    free = torch.arange(k, device=jac.device).expand(m, k)[is_free].reshape(m, k - 3)
    pivot_jac = jac.gather(2, pivots[:, None].expand(m, 3, 3))
    free_jac = jac.gather(2, free[:, None].expand(m, 3, k - 3))
    eye = torch.eye(3, device=jac.device).expand(m, 3, 3)
    trade, failed = torch.linalg.solve_ex(torch.where(singular[:, None, None], eye, pivot_jac), free_jac)
    singular = singular | (failed != 0) | ~torch.isfinite(trade).all(2).all(1)
    trade = torch.where(singular[:, None, None], 0.0, trade)  # (m, 3, k − 3); singular: plain rounding
    grid = torch.tensor(list(itertools.product(range(-radius, radius + 1), repeat=k - 3)), dtype=coords.dtype,
                        device=coords.device).reshape((2 * radius + 1) ** (k - 3), k - 3)  # (c, k − 3)
    free_coords = coords.gather(1, free)
    free_values = torch.round(free_coords)[:, None, :] + grid  # (m, c, k − 3)
    shift = (free_coords[:, None, :] - free_values) @ trade.transpose(1, 2)  # pivots keep J (q − coords) = 0
    pivot_values = coords.gather(1, pivots)[:, None, :] + shift
    candidates = torch.empty(m, grid.shape[0], k, dtype=coords.dtype, device=coords.device)
    candidates.scatter_(2, pivots[:, None].expand(-1, grid.shape[0], -1), torch.round(pivot_values))
    candidates.scatter_(2, free[:, None].expand(-1, grid.shape[0], -1), free_values)
    return candidates


@dataclass
class SolveCounts:
    iterations: int = 0
    jacobians: int = 0  # pixel-Jacobians computed (a forward and a four-row reverse pass each)
    renders: int = 0  # pixel forward passes (doneness checks and line search)
    restarts: int = 0


def raw_floors(field, density_floor: float) -> tuple[float, float]:
    """The raw densities the solver aims a single sample at (σ = density_floor: opacity exactly 1 over
    the last interval) and accepts as lifted (σ = half of it, room to spare), through the field kind's
    inverse density activation."""
    return field.raw_density_at(density_floor), field.raw_density_at(density_floor / 2)


def is_lifted(raw_density: torch.Tensor, lifted_floor: float) -> torch.Tensor:
    """Whether a single sample's raw density counts as lifted: at least `lifted_floor` (raw_floors).
    (...) -> (...) bool."""
    return raw_density >= lifted_floor


@dataclass
class Refinement:
    """What refine changes from one iteration to the next, for a problem's m pixels (ExactProblem keeps
    what does not)."""

    params: torch.Tensor  # (m, P)
    outputs: torch.Tensor  # (m, 4) at params
    # the storage phase: params stay storable and a pixel finishes when it rounds right; else the float32
    # phase, any float params, a pixel finished near its bin's centre
    storage_phase: bool
    done: torch.Tensor  # (m,) bool
    damping: torch.Tensor  # (m,) λ
    age: torch.Tensor  # (m,) int64: iterations since the pixel's last start
    restarts: torch.Tensor  # (m,) int64
    active: torch.Tensor  # (a,) int64: the pixels in the batch

    @staticmethod
    def start(problem: ExactProblem, params: torch.Tensor, storage_phase: bool) -> Refinement:
        """Every pixel in the batch at params (m, P), with the initial λ."""
        m, device = len(problem.index), params.device
        every = torch.arange(m, device=device)
        return Refinement(params.clone(), problem.outputs(every, params), storage_phase,
                          torch.zeros(m, dtype=torch.bool, device=device),
                          torch.full((m,), problem.settings.damping, device=device),
                          torch.zeros(m, dtype=torch.int64, device=device),
                          torch.zeros(m, dtype=torch.int64, device=device), every)


@dataclass(frozen=True, eq=False)  # tensors have no truth value: a problem equals only itself
class ExactProblem:
    """One solve's fixed part: pixels `index` (m,) of a single-sample view with 8-bit values `pixels` (m, 3)
    uint8, their noise sought in `space`, the settings, the generator every random start draws from and
    the counts the solve adds to. From the pixels: `target` (m, 3), the bin centres (bin_targets), `goal`
    (m, 3), their logits, and `values` (m, 3), the 8-bit values in [0, 1]. What changes from one
    iteration to the next is a Refinement's.

    refine moves the pixels with `step` and keeps in the batch those `batch` returns: a subclass may
    watch or vary an iteration without the solver knowing."""

    secret_view: SolverView
    index: torch.Tensor
    pixels: torch.Tensor
    space: NoiseSpace
    settings: ExactSettings
    generator: torch.Generator
    counts: SolveCounts = dataclasses.field(default_factory=SolveCounts)
    target: torch.Tensor = dataclasses.field(init=False)
    goal: torch.Tensor = dataclasses.field(init=False)
    values: torch.Tensor = dataclasses.field(init=False)
    floor: float = dataclasses.field(init=False)  # raw density aimed at, and accepted (raw_floors)
    lifted_floor: float = dataclasses.field(init=False)

    def __post_init__(self):
        floors = raw_floors(self.secret_view.field, self.settings.density_floor)
        object.__setattr__(self, "floor", floors[0])
        object.__setattr__(self, "lifted_floor", floors[1])
        object.__setattr__(self, "target", bin_targets(self.pixels))
        object.__setattr__(self, "goal", logit(self.target))
        object.__setattr__(self, "values", self.pixels.float() / 255.0)

    def subset(self, which: torch.Tensor) -> ExactProblem:
        """The problem of pixels `which` (s,) alone, indexed from 0; same settings, generator and counts."""
        return dataclasses.replace(self, index=self.index[which], pixels=self.pixels[which])

    def outputs(self, which: torch.Tensor, params: torch.Tensor) -> torch.Tensor:
        """sample_outputs of pixels `which` (a,) at params (a, P), without gradients, counted. -> (a, 4)."""
        self.counts.renders += which.numel()
        with torch.no_grad():
            return sample_outputs(self.secret_view, self.index[which], self.space.expand(params))

    def outputs_and_jacobian(self, which: torch.Tensor, params: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Outputs (a, 4) of pixels `which` (a,) at params (a, P) and their Jacobian in the params (a, 4, P),
        counted."""
        outputs, jac = self.secret_view.outputs_and_jacobian(self.index[which], self.space.expand(params))
        self.counts.jacobians += which.numel()
        return outputs, self.space.chain(jac)

    def judged(self, params: torch.Tensor, storage_phase: bool) -> torch.Tensor:
        """The params a phase judges: the nearest storable ones in the storage phase, any float32 params
        before it. (m, P) -> (m, P)."""
        return self.space.store(params) if storage_phase else params

    def lifted(self, outputs: torch.Tensor) -> torch.Tensor:
        return is_lifted(outputs[:, 3], self.lifted_floor)

    def converged(self, outputs: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
        """Float32 phase: pixels `which` (a,) with outputs (a, 4) near their bins' centres. -> (a,) bool."""
        near = colour_distance_bins(outputs, self.target[which]) <= self.settings.tolerance_bins
        return near & self.lifted(outputs)

    def rounds_right(self, outputs: torch.Tensor, which: torch.Tensor) -> torch.Tensor:
        """Storage phase: pixels `which` (a,) whose outputs (a, 4) round to their 8-bit values with
        margin_bins to spare. -> (a,) bool."""
        inside = colour_distance_bins(outputs, self.values[which]) <= 0.5 - self.settings.margin_bins
        return inside & self.lifted(outputs)

    def batch(self, state: Refinement) -> torch.Tensor:
        """The pixels the next step moves: those of the batch not finished. Finished pixels retire, so
        later iterations only pay for the few left. -> (a,) int64."""
        return state.active[~state.done[state.active]]

    def step(self, state: Refinement) -> None:
        """One Levenberg–Marquardt iteration of the batch, state.active: pixels stuck for restart_after
        iterations, or whose Jacobian is zero (every ReLU they need is off), restart; the others take the
        damped step with a line search, and λ falls after a step that improved, else rises."""
        settings, active = self.settings, state.active
        state.age[active] += 1
        stuck = active[(state.age[active] > settings.restart_after) & ~state.done[active]]
        if stuck.numel():
            restart(self, state, stuck)
        _, jac = self.outputs_and_jacobian(active, state.params[active])
        state.age[active[jac.flatten(1).abs().amax(-1) < 1e-12]] = settings.restart_after + 1  # restart next
        step = damped_step(jac, residuals(state.outputs[active], self.goal[active], self.floor),
                           state.damping[active])
        improved = line_search(self, state, step)
        state.damping[active] = torch.where(improved, torch.clamp(state.damping[active] / DAMPING_DOWN,
                                                                  min=DAMPING_RANGE[0]),
                                            torch.clamp(state.damping[active] * DAMPING_UP, max=DAMPING_RANGE[1]))


def restart(problem: ExactProblem, state: Refinement, stuck: torch.Tensor) -> None:
    """New starts for the stuck pixels (s,), judged as their phase judges params. The k-th restart of a
    pixel jitters its start by k·jitter and draws from more donors, so repeated restarts explore further;
    every other one starts afresh at random around zero noise, in case the donors' noise all lies in a
    basin this pixel's colour cannot be reached from."""
    settings = problem.settings
    finished_pixels = state.done.nonzero()[:, 0]
    state.restarts[stuck] += 1
    spread = settings.jitter * (state.restarts[stuck] - 1).float()[:, None]
    start = torch.zeros_like(state.params[stuck])
    from_donor = (state.restarts[stuck] % 2 == 1) & bool(finished_pixels.numel())
    if from_donor.any():
        start[from_donor] = donor_noise(stuck[from_donor], finished_pixels, problem.goal, state.params,
                                        problem.generator, settings.donors * state.restarts[stuck[from_donor]])
    spread = torch.where(from_donor[:, None], spread, spread + settings.restart_spread)
    jitter = torch.randn(start.shape, generator=problem.generator).to(start.device)
    state.params[stuck] = problem.judged(start + spread * jitter * problem.space.noise_units(start),
                                         state.storage_phase)
    state.outputs[stuck] = problem.outputs(stuck, state.params[stuck])
    state.age[stuck], state.damping[stuck] = 0, settings.damping
    problem.counts.restarts += stuck.numel()


def line_search(problem: ExactProblem, state: Refinement, step: torch.Tensor) -> torch.Tensor:
    """Moves each pixel of the batch, state.active (a,), by the first of settings.step_scales of its step
    (a, P) that lowers its ‖r‖², updating state.params and state.outputs; the others stay.
    -> improved (a,) bool."""
    settings, active = problem.settings, state.active
    params, outputs, goal = state.params[active], state.outputs[active], problem.goal[active]
    before = (residuals(outputs, goal, problem.floor) ** 2).sum(-1)
    improved = torch.zeros(active.numel(), dtype=torch.bool, device=params.device)
    for scale in settings.step_scales:
        trying = (~improved).nonzero()[:, 0]
        if trying.numel() == 0:
            break
        candidate = problem.judged(params[trying] + scale * step[trying], state.storage_phase)
        after = problem.outputs(active[trying], candidate)
        better = (residuals(after, goal[trying], problem.floor) ** 2).sum(-1) < before[trying]
        chosen = trying[better]
        params[chosen], outputs[chosen], improved[chosen] = candidate[better], after[better], True
    state.params[active], state.outputs[active] = params, outputs
    return improved


def refine(problem: ExactProblem, params: torch.Tensor, storage_phase: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """Levenberg–Marquardt on every pixel of the problem until it is finished (Refinement.storage_phase
    says when), Jacobians only for the batch (ExactProblem.batch). params (m, P) -> params, done (m,) bool."""
    finished = problem.rounds_right if storage_phase else problem.converged
    state = Refinement.start(problem, params, storage_phase)
    for iteration in range(1, problem.settings.max_iters + 1):
        state.done[state.active] = finished(state.outputs[state.active], state.active)
        if state.done.all():
            break
        state.active = problem.batch(state)
        problem.counts.iterations = max(problem.counts.iterations, iteration)
        problem.step(state)
    return state.params, state.done


@dataclass(frozen=True)
class ExactResult:
    params: torch.Tensor  # (m, P) float32, storable (NoiseSpace.store leaves them unchanged)
    done: torch.Tensor  # (m,) bool: the pixel rounds to its 8-bit value (a compact space may leave a few)


def chord_start(problem: ExactProblem, which: torch.Tensor, params: torch.Tensor, jac: torch.Tensor) -> torch.Tensor:
    """Warm starts for pixels `which` (w,) refined without Jacobians of their own: from params (w, P) (a
    solved seed's), take settings.chord_steps Gauss–Newton steps with that seed's Jacobian jac (w, 4, P)
    (the chord method), keeping each pixel's best. The seed's Jacobian is only a rough guide to the
    pixel's, but a few steps bring most pixels near enough for LM's own steps to take over at less cost:
    forward passes only. -> params (w, P)."""
    settings, goal = problem.settings, problem.goal[which]
    best = params
    outputs = problem.outputs(which, params)
    best_error = (residuals(outputs, goal, problem.floor) ** 2).sum(-1)
    damping = torch.full((which.numel(),), settings.damping, device=params.device)
    for _ in range(settings.chord_steps):
        params = params + damped_step(jac, residuals(outputs, goal, problem.floor), damping)
        outputs = problem.outputs(which, params)
        error = (residuals(outputs, goal, problem.floor) ** 2).sum(-1)
        better = error < best_error
        best, best_error = torch.where(better[:, None], params, best), torch.where(better, error, best_error)
    return best


LATTICE_VALUES = 1 << 24  # candidate coordinates (pixels × c × k) formed at once: ~64 MB a tensor
OUTSIDE_RANK = 1e7  # ranked behind every candidate predicted inside its bin (their L1 from an anchor is far less)


def round_to_lattice(problem: ExactProblem, params: torch.Tensor, anchor: torch.Tensor | None = None) -> torch.Tensor:
    """Storable params for float params (m, k) of an integer lattice: the field's Jacobian at the float
    solution predicts each lattice_candidates point's colour (the net is piecewise linear, so within a
    ReLU region exactly); the settings.lattice_tries best points (ranked by predicted distance from the
    8-bit value, those that keep the density lifted first; given integer anchors (m, k), those predicted
    to round right nearest their anchor in L1 first) are rendered in turn and the first that rounds right
    is kept, else the best ranked. Phase 2 of solve_exact polishes what is left.
    -> params (m, k) on the lattice."""
    space, settings = problem.space, problem.settings
    stored = space.store(params)
    if not space.lattice or space.basis.shape[1] < 3:
        return stored
    k = space.basis.shape[1]
    limit = INTEGER_LIMITS[space.storage]
    per_part = max(1, LATTICE_VALUES // ((2 * settings.lattice_radius + 1) ** (k - 3) * k))
    for part in torch.split(torch.arange(len(problem.index), device=params.device), per_part):
        outputs, jac = problem.outputs_and_jacobian(part, params[part])
        jac = jac * space.scale  # per integer step
        coords = params[part] / space.scale
        candidates = torch.clamp(lattice_candidates(coords, jac[:, :3], settings.lattice_radius), -limit, limit)
        predicted = outputs[:, None, :] + (candidates - coords[:, None, :]) @ jac.transpose(1, 2)  # (p, c, 4)
        distance = colour_distance_bins(predicted.flatten(0, 1), problem.values[part].repeat_interleave(
            candidates.shape[1], 0)).reshape(candidates.shape[:2])
        distance = distance + 255.0 * (predicted[..., 3] < problem.lifted_floor)  # unlifted: last
        if anchor is not None:  # cheapest to code first: the anchor is what the decoder predicts
            nearness = (candidates - anchor[part, None, :].float()).abs().sum(-1)
            distance = torch.where(distance <= 0.5 - settings.margin_bins, nearness, OUTSIDE_RANK + distance)
        ranked = space.params_of(candidates.gather(1, distance.argsort(1)[:, :settings.lattice_tries, None].expand(
            -1, -1, k)))
        chosen, left = ranked[:, 0].clone(), torch.arange(part.numel(), device=params.device)
        for t in range(ranked.shape[1]):
            after = problem.outputs(part[left], ranked[left, t])
            right = problem.rounds_right(after, part[left])
            chosen[left[right]] = ranked[left[right], t]
            left = left[~right]
            if left.numel() == 0:
                break
        stored[part] = chosen
    return stored


def solve_from(problem: ExactProblem, start: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Both phases from params `start` (m, P): float32 until converged near the bin centres, onto the
    storable lattice, then storable params until every value rounds right. -> params (m, P), done (m,) bool."""
    converged, _ = refine(problem, start, storage_phase=False)
    return refine(problem, round_to_lattice(problem, converged), storage_phase=True)


RESCUE_ROUNDS = 6  # further solves a pixel left unfinished gets (rescue), each from another start


def rescue(problem: ExactProblem, params: torch.Tensor, done: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Pixels that a solve left unfinished, solved again from other starts until they round right: round 0
    continues from their own params, round r ≥ 1 starts from the params of the r-th finished pixel
    nearest in target colour (whose ray is lifted and whose colour is near), jittered by r·jitter; every
    round has twice the iterations. Saturated colours far from every colour the view renders need this:
    their first solve ends in a basin without the colour, or with the density unlifted.
    params (m, P), done (m,) bool -> params, done."""
    params, done = params.clone(), done.clone()
    settings = problem.settings
    longer = dataclasses.replace(problem, settings=dataclasses.replace(settings, max_iters=2 * settings.max_iters))
    for r in range(RESCUE_ROUNDS):
        left, finished = (~done).nonzero()[:, 0], done.nonzero()[:, 0]
        if left.numel() == 0:
            break
        start = params[left]
        if r and finished.numel():
            nearest = torch.cdist(problem.goal[left], problem.goal[finished]).topk(min(r, finished.numel()),
                                                                                  largest=False).indices
            start = params[finished[nearest[:, -1]]]
            start = start + r * settings.jitter * problem.space.noise_units(start) * torch.randn(
                start.shape, generator=problem.generator).to(start.device)
        solved, ok = solve_from(longer.subset(left), problem.space.store(start))
        params[left[ok]], done[left[ok]] = solved[ok], True
    return params, done


def solve_exact(problem: ExactProblem) -> ExactResult:
    """Bring the problem's pixels of a single-sample view to their 8-bit values, with each pixel's noise in
    its space (the full 90 values, or a tile's compact basis).

    Every seed_stride-th pixel is solved first from zero params; every other pixel then starts from the
    params of the solved seed nearest in target colour, which is most of the way there, so it needs far
    fewer Jacobians than a start from zero. Each group runs both phases; a last storage-phase pass over
    the whole problem gives any pixel still left every finished pixel as a donor."""
    secret_view, space = problem.secret_view, problem.space
    if secret_view.n_samples != 1:
        raise ValueError("the exact solver needs a secret view with one sample per ray")
    m, device = len(problem.index), problem.pixels.device
    if m == 0:  # e.g. a part whose rays all escape (exact_solver.solve_pixels)
        return ExactResult(space.zeros(0, secret_view.noise_dims, device),
                           torch.zeros(0, dtype=torch.bool, device=device))
    params = space.zeros(m, secret_view.noise_dims, device)
    is_seed = torch.arange(m, device=device) % problem.settings.seed_stride == 0
    seeds, rest = is_seed.nonzero()[:, 0], (~is_seed).nonzero()[:, 0]
    params[seeds] = solve_from(problem.subset(seeds), params[seeds])[0]
    if rest.numel():
        nearest_seed = torch.cdist(problem.goal[rest], problem.goal[seeds]).argmin(dim=1)
        start = params[seeds[nearest_seed]]
        if problem.settings.chord_steps:
            _, seed_jac = problem.outputs_and_jacobian(seeds, params[seeds])
            start = chord_start(problem, rest, start, seed_jac[nearest_seed])
        params[rest] = solve_from(problem.subset(rest), start)[0]
    return ExactResult(*refine(problem, params, storage_phase=True))
