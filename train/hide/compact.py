"""The compact noise layout: a small basis per tile, a few integer coefficients per pixel.

Pixels of one secret view see nearly the same field, so the noise that brings them to their colours
varies in few directions. Per tile, from a seeded sample of its pixels:

- offset o (dims,): its γ(x) part one vector that lifts every sampled ray's density (lift_density), its
  γ(d) part the mean of the sample's noise solved in γ(d) alone with that γ(x) fixed (BranchView);
- basis B (dims, k): the top-k principal directions of that solved γ(d) noise around o, zero in γ(x);
- scale: 1; each column of B is stretched so that one integer step of its coefficient moves a colour
  by about CompactSettings.step_bins 8-bit bins where the sample's solved pixels lie (stepped): a step
  far finer than a bin only costs bits.

Each pixel's noise is o + (q · scale) Bᵀ with q (k,) int16 (or int8); the exact solver works in that
space (train/hide/exact.NoiseSpace) and judges only lattice points, as the ray layout judges only float16
noise. Since the noise leaves γ(x) at o, each ray's trunk (density and feature) is evaluated once and the
solver renders only the view branch, a fraction of the field's work; a basis in γ(d) alone also lets
fewer pixels escape than one in the whole noise. A field without a view branch gets its offset and basis
from the sample solved in the full noise. A basis cannot reach every colour from every start; those
pixels escape: they are solved again in the direction segment alone (a branch escape, its float16 values
stored beside the coefficients: 58 bytes with its index for the NeRF MLP) or, where that fails too, in the
full 90 values (184 bytes), so every pixel is still exact (train/hide/exact_solver.solve_pixels).

Why k = 5: every coefficient costs bytes at every pixel and each escape tens to hundreds, so k trades bytes
per pixel against escapes: k = 4 lets so many pixels escape that the worst keys grow and hides slow down,
k = 6 costs a coefficient's bytes at every pixel to save escapes that branch escapes made cheap.
int8 coefficients leave most pixels unreachable on their lattice. The measurements are in docs/formats.md
("Key sizes") and the bench's `keys` experiment.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from noisenerf.runtime import interlaced
from noisenerf.train.hide.secret_view import BranchView, SecretView
from noisenerf.train.hide.exact import (ExactProblem, NoiseSpace, is_lifted, raw_floors, refine, round_to_lattice,
                                        solve_exact)
from noisenerf.train.hide.settings import CompactSettings, ExactSettings

def in_basis(exact: ExactSettings, settings: CompactSettings) -> ExactSettings:
    """The exact solver's settings for a solve in a compact basis: at most max_iters per phase (the few
    pixels a basis cannot reach escape sooner), its float phase stopping at tolerance_bins, seeds every
    seed_stride pixels."""
    return dataclasses.replace(exact, max_iters=settings.max_iters, tolerance_bins=settings.tolerance_bins,
                               seed_stride=settings.seed_stride)


def principal_basis(noise: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and top-k principal directions of noise vectors, signs fixed (largest entry positive) so the
    basis is a function of the noise alone; zero columns where fewer than k vectors span fewer directions, and the
    zero offset and basis where there are none (a sample none of whose pixels the solver could bring to their
    colours: the tile's own solve then reports the pixels it cannot reach, rather than a space of NaN).
    noise: (s, dims) -> offset (dims,), basis (dims, k) with orthonormal (or zero) columns."""
    if len(noise) == 0:
        return noise.new_zeros(noise.shape[1]), noise.new_zeros(noise.shape[1], k)
    offset = noise.mean(0)
    _, _, vh = torch.linalg.svd((noise - offset).double(), full_matrices=False)
    basis = torch.zeros(noise.shape[1], k, dtype=torch.float64, device=noise.device)
    basis[:, :min(k, vh.shape[0])] = vh[:k].T
    basis = basis * torch.where(basis.gather(0, basis.abs().argmax(0, keepdim=True)) < 0, -1.0, 1.0)
    return offset.contiguous(), basis.float().contiguous()


LIFT_MARGIN = 2.0  # lift_density lifts its sample to this many density floors, so the tile's other rays clear one
LIFT_STEPS = (0.25, 0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0)  # step lengths lift_density tries
LIFT_ROUNDS = 8
# below this share of its sample lifted, a tile takes the basis in the full noise: every ray the shared γ(x)
# leaves unlifted would escape at 184 bytes (a trained scene's views lift whole; a random-weight net's may not)
MIN_LIFTED = 0.99


def lift_density(secret_view: SecretView, floor: float) -> torch.Tensor:
    """One position-segment noise vector (position_dims,) shared by a single-sample view's rays that lifts
    their densities towards LIFT_MARGIN · floor (as raw densities, through the kind's activation): from zero, steps along the mean density gradient of the rays
    still below, each of the LIFT_STEPS length that most raises Σ min(density, goal) over every ray, until
    all are there or no step helps; on a trained scene one step usually lifts every ray."""
    field, xyz_dims = secret_view.field, secret_view.field.config.position_dims
    encoded = secret_view.encodings(torch.arange(secret_view.n_rays, device=secret_view.device))[:, 0, :xyz_dims]
    goal = field.raw_density_at(LIFT_MARGIN * floor)

    def density(noise: torch.Tensor) -> torch.Tensor:
        return field.trunk_outputs(encoded + noise)[0]

    def progress(noise: torch.Tensor) -> float:
        return float(torch.clamp_max(density(noise), goal).sum())

    noise = torch.zeros(xyz_dims, device=secret_view.device)
    with torch.no_grad():
        best = progress(noise)
    for _ in range(LIFT_ROUNDS):
        with torch.no_grad():
            low = density(noise) < goal
        if not low.any():
            break
        with torch.enable_grad():  # the only gradient a hide takes: callers may be under no_grad
            moving = noise.expand(int(low.sum()), xyz_dims).clone().requires_grad_(True)
            gradient, = torch.autograd.grad(field.trunk_outputs(encoded[low] + moving)[0].sum(), moving)
        direction = gradient.mean(0) / (gradient.mean(0).norm() + 1e-12)
        with torch.no_grad():
            scores = [progress(noise + step * direction) for step in LIFT_STEPS]
        if max(scores) <= best:
            break
        best = max(scores)
        noise = noise + LIFT_STEPS[scores.index(best)] * direction
    return noise


def tile_space(secret_view: SecretView, pixels: torch.Tensor, settings: CompactSettings, exact: ExactSettings,
               storage: torch.dtype, seed: int) -> NoiseSpace:
    """The compact NoiseSpace of one tile with int8/int16 coefficients, from `basis_pixels` of its pixels
    (n, 3) uint8 drawn with `seed`. A field with a view branch gets a shared γ(x) noise that lifts the
    sample's density (lift_density) and a basis in γ(d) alone (direction_basis), unless that noise leaves
    more than 1 − MIN_LIFTED of the sample unlifted; then, as for a field without a view branch, the
    offset and basis come from the sample solved in the full noise."""
    generator = torch.Generator().manual_seed(seed)
    sample = torch.randperm(secret_view.n_rays, generator=generator)[:settings.basis_pixels].to(pixels.device)
    part = secret_view.subset(sample)
    if secret_view.field.config.has_view_branch:
        xyz_noise = lift_density(part, exact.density_floor)
        branch = BranchView(part, xyz_noise)
        lifted_floor = raw_floors(branch.field, exact.density_floor)[1]
        if float(is_lifted(branch.density, lifted_floor).float().mean()) >= MIN_LIFTED:
            space, index, noise = direction_basis(branch, pixels[sample], xyz_noise, settings, exact, generator)
            return stepped(branch, space, settings.step_bins, storage, index, noise)
    solved = solve_exact(ExactProblem(secret_view, sample, pixels[sample], NoiseSpace(torch.float32), exact, generator))
    index = solved.done.nonzero()[:, 0]
    offset, basis = principal_basis(solved.params[index], settings.coefficients)  # pixels left unsolved never count
    return stepped(part, NoiseSpace(torch.float32, basis, offset), settings.step_bins, storage, index,
                   solved.params[index])


def colour_bins_per_unit(view: SecretView | BranchView, space: NoiseSpace, index: torch.Tensor,
                         noise: torch.Tensor) -> torch.Tensor:
    """How far a unit of each basis coordinate moves the colours of rays `index` (s,) at their noise (s, dims),
    in 8-bit bins: the largest channel's |∂sigmoid(raw colour)/∂coordinate| · 255, the median over the rays.
    -> (k,)."""
    outputs, jac = view.outputs_and_jacobian(index, noise[:, None, :])
    colour = torch.sigmoid(outputs[:, :3])
    slope = (colour * (1 - colour))[:, :, None] * space.chain(jac)[:, :3]  # (s, 3, k)
    return 255.0 * slope.abs().amax(1).median(0).values


def stepped(view: SecretView | BranchView, space: NoiseSpace, step_bins: float, storage: torch.dtype,
            index: torch.Tensor, noise: torch.Tensor) -> NoiseSpace:
    """A float basis space as the tile's integer lattice: each column stretched so that one step of its
    coefficient moves a colour by about step_bins where the basis sample's solved pixels, rays `index` of
    `view`, lie (their noise (s, dims): colour_bins_per_unit; the colours' slopes there, not at the offset,
    since a field's colour can be flat at the offset and steep where the colours are), the scale 1. A
    column that moves no colour (a zero one) stays as it is. Where no sample pixel was solved, the slopes
    are measured over the view's rays at the offset."""
    if not len(index):
        index = torch.arange(view.n_rays, device=space.offset.device)
        noise = space.expand(space.zeros(view.n_rays, view.noise_dims, space.offset.device))[:, 0]
    per_unit = colour_bins_per_unit(view, space, index, noise)
    stretch = torch.where(per_unit > 0, step_bins / per_unit.clamp_min(1e-30), 1.0)
    return NoiseSpace(storage, (space.basis * stretch).contiguous(), space.offset, 1.0)


def direction_basis(branch: BranchView, pixels: torch.Tensor, xyz_noise: torch.Tensor, settings: CompactSettings,
                    exact: ExactSettings, generator: torch.Generator
                    ) -> tuple[NoiseSpace, torch.Tensor, torch.Tensor]:
    """tile_space's γ(d) basis from a sample's BranchView and pixels (s, 3): the principal directions of
    the sample's solved noise, found twice. The solved pixels the first basis cannot bring to their
    colours (mostly the darkest) count missed_weight times in the second, which turns the basis towards
    them and so cuts escapes. Pixels left unsolved never count. -> the float space, and the solved pixels'
    indices (d,) and noise (d, dims)."""
    dir_dims, k = branch.noise_dims - len(xyz_noise), settings.coefficients
    every = torch.arange(branch.n_rays, device=pixels.device)
    directions = direction_space(torch.float32, xyz_noise, xyz_noise.new_zeros(dir_dims),
                                 torch.eye(dir_dims, device=xyz_noise.device))
    solved = solve_exact(ExactProblem(branch, every, pixels, directions, exact, generator))
    first = direction_space(torch.float32, xyz_noise, *principal_basis(solved.params[solved.done], k))
    trial = solve_exact(ExactProblem(branch, every, pixels, first, in_basis(exact, settings), generator))
    weights = torch.where(trial.done, 1, settings.missed_weight) * solved.done
    done = solved.done.nonzero()[:, 0]
    return (direction_space(torch.float32, xyz_noise, *principal_basis(solved.params.repeat_interleave(weights, 0), k)),
            done, directions.expand(solved.params[done])[:, 0])


def direction_space(storage: torch.dtype, xyz_noise: torch.Tensor, dir_offset: torch.Tensor,
                    dir_basis: torch.Tensor) -> NoiseSpace:
    """A NoiseSpace whose noise leaves γ(x) at xyz_noise (xyz_dims,): offset [xyz_noise ‖ dir_offset (dir_dims,)],
    basis [0 ‖ dir_basis (dir_dims, k)]."""
    return NoiseSpace(storage, torch.cat([dir_basis.new_zeros(len(xyz_noise), dir_basis.shape[1]), dir_basis]),
                      torch.cat([xyz_noise, dir_offset]))


def solver_view(secret_view: SecretView, space: NoiseSpace) -> SecretView | BranchView:
    """What the exact solver renders for a part in `space`: the view branch alone where the space's noise
    leaves γ(x) at its offset (tile_space, fields with a view branch), else the whole field."""
    xyz_dims = secret_view.field.config.position_dims
    if space.basis is not None and secret_view.field.config.has_view_branch and not space.basis[:xyz_dims].any():
        return BranchView(secret_view, space.offset[:xyz_dims])
    return secret_view


# iterations (without restarts) a pixel gets from its prediction: most finish in a few, and one that does not keeps
# its own solution, so longer tries would cost time for almost no bytes
PREDICTED_ITERS = 8


def predicted_choice(secret_view: SecretView, space: NoiseSpace, pixels: torch.Tensor, shape: tuple[int, int],
                     params: torch.Tensor, free: torch.Tensor, settings: ExactSettings,
                     generator: torch.Generator) -> torch.Tensor:
    """A solved band of whole rows (a part; shape (h, w)) of a compact tile: its params (n, k) moved, pass by
    interlaced pass (runtime/interlaced.py), to what the bundle codes cheapest. Each pixel of a pass after the
    roots is solved again from its prediction (the coefficients its pass predicts from those chosen before
    it) with minimum-norm steps, and rounds to the lattice point nearest that prediction among those that
    round right (round_to_lattice's anchor); one that does not round right from there keeps its own solution,
    a `free` pixel (n,) bool (an escape: its coefficients are never expanded) takes its prediction, and roots
    keep theirs. secret_view: the band's rays, pixels (n, 3) theirs; settings: the solve's in the basis, run
    for at most PREDICTED_ITERS iterations without restarts. -> params (n, k) on the lattice; every pixel not
    free still rounds right."""
    settings = dataclasses.replace(settings, max_iters=PREDICTED_ITERS, restart_after=PREDICTED_ITERS)
    height, width = shape
    solved = space.integers(params).long().reshape(height, width, -1).cpu().numpy()
    chosen, is_free = solved.copy(), free.reshape(height, width).cpu().numpy()
    for ys, xs, kind, d in interlaced.passes(height, width):
        if kind == "root":
            continue
        chosen[ys, xs] = interlaced.predictions(chosen, ys, xs, kind, d)
        ys, xs = ys[~is_free[ys, xs]], xs[~is_free[ys, xs]]
        if not len(ys):
            continue
        index = torch.from_numpy(ys * width + xs).to(params.device)
        every = torch.arange(len(index), device=params.device)
        problem = ExactProblem(solver_view(secret_view.subset(index), space), every, pixels[index], space, settings,
                               generator)
        prediction = torch.from_numpy(chosen[ys, xs]).to(params.device)
        converged, _ = refine(problem, space.params_of(prediction), storage_phase=False)
        rounded = round_to_lattice(problem, converged, prediction)
        right = problem.rounds_right(problem.outputs(every, rounded), every).cpu().numpy()
        chosen[ys, xs] = np.where(right[:, None], space.integers(rounded).long().cpu().numpy(), solved[ys, xs])
    return space.params_of(torch.from_numpy(chosen.reshape(height * width, -1)).to(params.device))
