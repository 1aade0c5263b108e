"""The exact solver's steps between phases (lattice candidates, entering a compact tile's integer lattice,
the chord warm start), its settings' checks, and the local executor's worker processes parts are spread over."""

import dataclasses
import os
import signal

import numpy as np
import pytest
import torch

from helpers import make_tiny_scene
from noisenerf.cli.demo import DEMO_VIEW
from noisenerf.runtime.errors import UserError
from noisenerf.train.hide.compact import (LIFT_MARGIN, colour_bins_per_unit, lift_density, solver_view, stepped,
                                          tile_space)
from noisenerf.train.hide.exact import (ExactProblem, NoiseSpace, chord_start, damped_step,
                                        lattice_candidates, refine,
                                        residuals, round_to_lattice)
from noisenerf.train.hide.plan import HideConfig, plan
from noisenerf.train.hide.secret_view import BranchView, SecretView
from noisenerf.train.hide.settings import CompactSettings, ExactSettings
from noisenerf.train.hide.executors import LocalExecutor, sendable
from noisenerf.train.hide.jobs import FieldWeights, Job, JobRunner
from noisenerf.train.scene.procedural import DEMO_SCENE, procedural_secret
from noisenerf.train.scene.scene import load_scene

CPU = torch.device("cpu")


def test_lattice_candidates_move_the_colour_only_by_the_pivots_rounding():
    generator = torch.Generator().manual_seed(0)
    m, k, radius = 200, 6, 2
    jac = torch.randn(m, 3, k, generator=generator) * torch.rand(m, 1, k, generator=generator)
    coords = torch.randn(m, k, generator=generator) * 40
    candidates = lattice_candidates(coords, jac, radius)
    assert candidates.shape == (m, (2 * radius + 1) ** (k - 3), k)
    assert torch.equal(candidates, torch.round(candidates))
    moved = candidates - coords[:, None, :]
    # free coordinates stay within radius of their rounding, and at most 3 coordinates (the pivots) move
    # further than radius + 1/2 from the continuous point
    assert int((moved.abs() > radius + 0.5 + 1e-4).sum(-1).max()) <= 3
    colour_change = (moved @ jac.transpose(1, 2)).abs()  # (m, c, 3): what the lattice point costs in colour
    pivot_bound = 0.5 * jac.abs().sum(-1)  # every column's rounding at most half a step
    assert bool((colour_change <= pivot_bound[:, None, :] + 1e-3).all())
    best = colour_change.amax(-1).amin(-1)
    plain = ((torch.round(coords) - coords)[:, None, :] @ jac.transpose(1, 2)).abs().amax(-1)[:, 0]
    assert float(best.median()) < float(plain.median()) / 4


def test_singular_jacobians_give_plain_rounding():
    coords = torch.tensor([[0.4, -1.6, 2.5, 7.2, 0.0, -0.5]])
    candidates = lattice_candidates(coords, torch.zeros(1, 3, 6), radius=1)
    pivots_and_centre = candidates[0, len(candidates[0]) // 2]
    assert torch.equal(pivots_and_centre, torch.round(coords[0]))


@pytest.fixture(scope="module")
def compact_view():
    """The problem of a 16×12 secret's view of the demo scene in a compact space, and its float-phase
    solution. The space's integer steps move a colour by about a third of a bin (the default), and five
    coefficients rounded at once miss many pixels' bins."""
    scene = load_scene(DEMO_SCENE)
    secret = procedural_secret(16, 12)
    config = HideConfig(view=DEMO_VIEW, tile_size=16)
    view = SecretView(scene.coarse, plan(scene, secret, config).tiles[0], scene.config.render, CPU)
    pixels = torch.tensor(secret.reshape(-1, 3))
    exact = ExactSettings()
    space = tile_space(view, pixels, CompactSettings(), exact, torch.int16, seed=0)
    problem = ExactProblem(view, torch.arange(view.n_rays), pixels, space, exact, torch.Generator().manual_seed(0))
    converged, done = refine(problem, space.zeros(view.n_rays, view.noise_dims, CPU), storage_phase=False)
    return problem, converged[done], done


def test_entering_the_lattice_keeps_more_pixels_exact_than_rounding(compact_view):
    problem, converged, done = compact_view
    which = done.nonzero()[:, 0]
    assert len(which) > 100
    entered = round_to_lattice(problem.subset(which), converged)
    assert torch.equal(problem.space.store(entered), entered)  # on the lattice
    right = {name: problem.rounds_right(problem.outputs(which, params), which)
             for name, params in {"lattice": entered, "rounded": problem.space.store(converged)}.items()}
    assert float(right["lattice"].float().mean()) >= 0.95
    assert int(right["lattice"].sum()) > int(right["rounded"].sum())


def test_a_compact_tile_lifts_its_density_once_and_moves_only_the_view_direction(compact_view):
    problem = compact_view[0]
    view, index, space = problem.secret_view, problem.index, problem.space
    xyz_dims = view.field.config.xyz_dims
    assert not space.basis[:xyz_dims].any() and space.basis[xyz_dims:].any()
    density = view.field.trunk_outputs(view.encodings(index)[:, 0, :xyz_dims] + space.offset[:xyz_dims])[0]
    assert float(density.min()) >= ExactSettings().density_floor  # every ray of the tile, not only the sample
    branch = solver_view(view, space)
    assert isinstance(branch, BranchView)
    assert solver_view(view, NoiseSpace(torch.float16)) is view  # full noise: the whole field


def test_each_coefficient_steps_a_colour_by_step_bins_where_the_solved_pixels_lie(compact_view):
    """stepped stretches each column so that, at the noise it is given (here the tile's solved pixels'), one
    integer step of each coefficient moves the median ray's largest channel by step_bins, though the principal
    directions move colours by very different amounts; the tile's own lattice is stepped so too (at its
    sample's solutions, which lie near these)."""
    problem, converged, done = compact_view
    view, space = solver_view(problem.secret_view, problem.space), problem.space
    which = done.nonzero()[:, 0]
    noise = space.expand(converged)[:, 0]
    unit = dataclasses.replace(space, storage=torch.float32, basis=space.basis / space.basis.norm(dim=0))
    unstretched = colour_bins_per_unit(view, unit, which, noise)
    assert float(unstretched.max() / unstretched.min()) > 2.0
    lattice = stepped(view, unit, 0.5, torch.int16, which, noise)
    assert lattice.scale == 1.0 and lattice.storage == torch.int16
    np.testing.assert_allclose(colour_bins_per_unit(view, lattice, which, noise).numpy(), 0.5, rtol=1e-4)
    np.testing.assert_allclose(colour_bins_per_unit(view, space, which, noise).numpy(), CompactSettings().step_bins,
                               rtol=0.3)
    none = which[:0]  # no solved pixel to measure at: the view's rays at the offset
    at_offset = space.expand(space.zeros(view.n_rays, view.noise_dims, CPU))[:, 0]
    every = torch.arange(view.n_rays)
    np.testing.assert_allclose(colour_bins_per_unit(view, stepped(view, unit, 0.5, torch.int16, none, noise[:0]),
                                                    every, at_offset).numpy(), 0.5, rtol=1e-4)


def test_lift_density_reaches_its_margin_on_every_sampled_ray(compact_view):
    view, index = compact_view[0].secret_view, compact_view[0].index
    xyz_dims = view.field.config.xyz_dims
    clean = view.field.trunk_outputs(view.encodings(index)[:, 0, :xyz_dims])[0]
    assert float(clean.min()) < 1.0  # the demo view's single samples start below the floor
    lifted = view.field.trunk_outputs(view.encodings(index)[:, 0, :xyz_dims] + lift_density(view, 1.0))[0]
    assert float(lifted.min()) >= LIFT_MARGIN


def test_the_view_branch_renders_what_the_whole_field_renders(compact_view):
    problem, converged, done = compact_view
    view, index, space = problem.secret_view, problem.index, problem.space
    branch = solver_view(view, space)
    noise = space.expand(converged + torch.randn(converged.shape, generator=torch.Generator().manual_seed(4)))
    which = index[done]
    whole_outputs, whole_jacobian = view.outputs_and_jacobian(which, noise)
    outputs, jacobian = branch.outputs_and_jacobian(which, noise)
    torch.testing.assert_close(outputs, whole_outputs, rtol=0, atol=1e-5)
    # through the basis (zero in γ(x)) the Jacobians agree: γ(x) columns and the density row never count
    torch.testing.assert_close(space.chain(jacobian)[:, :3], space.chain(whole_jacobian)[:, :3], rtol=0, atol=1e-5)
    assert not jacobian[:, 3].any() and not jacobian[:, :, :view.field.config.xyz_dims].any()
    raw_rgb, raw_density = branch.raw(which, noise)
    torch.testing.assert_close(torch.cat([raw_rgb[:, 0], raw_density], -1), outputs, rtol=0, atol=0)


def test_chord_start_is_never_worse_than_its_start(compact_view):
    problem, converged, done = compact_view
    which = done.nonzero()[:, 0]
    seeds, rest = which[::4], which[torch.arange(len(which)) % 4 != 0]
    donor = seeds[torch.cdist(problem.goal[rest], problem.goal[seeds]).argmin(1)]
    solved = dict(zip(which.tolist(), converged))
    start = torch.stack([solved[int(d)] for d in donor])
    _, jac = problem.outputs_and_jacobian(donor, start)
    moved = chord_start(problem, rest, start, jac)

    def error(params):
        outputs = problem.outputs(rest, params)
        return (residuals(outputs, problem.goal[rest], problem.settings.density_floor) ** 2).sum(-1)

    assert bool((error(moved) <= error(start)).all())
    assert float(error(moved).median()) < float(error(start).median())
    assert np.isfinite(moved.numpy()).all()


def test_a_step_whose_system_is_singular_in_float32_is_damped_not_refused():
    """Dependent rows of J with λ far below float32's resolution: the hide once stopped here with
    torch.linalg.solve's "input matrix is singular" (a payload in the tiny ring scene)."""
    generator = torch.Generator().manual_seed(0)
    row = torch.randn(1, 1, 90, generator=generator) * 100
    jac = torch.cat([row, row, 2 * row, torch.randn(1, 1, 90, generator=generator)], dim=1)  # rank 2 of 4
    healthy = torch.randn(1, 4, 90, generator=generator)
    residual = torch.tensor([[1.0, 1.0, 2.0, 0.5], [0.3, -0.2, 0.1, 0.0]])
    with pytest.raises(torch.linalg.LinAlgError):
        torch.linalg.solve(jac @ jac.transpose(1, 2) + 1e-12 * torch.eye(4), residual[:1, :, None])
    step = damped_step(torch.cat([jac, healthy]), residual, torch.tensor([1e-30, 1e-4]))
    assert torch.isfinite(step).all()
    reached = jac[0] @ step[0]  # the dependent rows' residual is in J's range: reached; the weak row moves
    assert torch.allclose(reached[:3], residual[0, :3], atol=1e-3) and 0 < reached[3] < residual[0, 3]
    alone = damped_step(healthy, residual[1:], torch.tensor([1e-4]))
    assert torch.equal(step[1], alone[0])  # a pixel whose system is fine is solved exactly as before


def test_rank_deficient_jacobians_give_finite_candidates():
    jac = torch.zeros(2, 3, 6)
    jac[0, :, 0] = 1.0  # one colour direction
    jac[1, 0, :2], jac[1, 1, :2] = torch.tensor([1.0, 2.0]), torch.tensor([2.0, 4.0])  # parallel columns
    candidates = lattice_candidates(torch.full((2, 6), 3.3), jac, radius=1)
    assert torch.isfinite(candidates).all() and torch.equal(candidates, torch.round(candidates))


def test_nearly_rank_2_jacobians_keep_candidates_near_the_solution():
    generator = torch.Generator().manual_seed(1)
    jac = torch.randn(50, 3, 6, generator=generator)
    jac[:, 2] = jac[:, 0] + 1e-7 * torch.randn(50, 6, generator=generator)  # two colour rows alike
    coords = torch.randn(50, 6, generator=generator) * 40
    candidates = lattice_candidates(coords, jac, radius=2)
    assert bool(((candidates - coords[:, None, :]).abs() <= 2.5 + 1e-4).all())


def test_three_coefficients_have_one_candidate_each():
    jac = torch.randn(4, 3, 3, generator=torch.Generator().manual_seed(2))
    coords = torch.randn(4, 3, generator=torch.Generator().manual_seed(3)) * 10
    candidates = lattice_candidates(coords, jac, radius=2)
    assert candidates.shape == (4, 1, 3)
    assert torch.equal(candidates[:, 0], torch.round(coords))  # all three are pivots, J (q − coords) = 0


@pytest.mark.parametrize("field, value", [("lattice_tries", 0), ("lattice_radius", -1), ("chord_steps", -1)])
def test_impossible_solver_settings_are_refused(field, value):
    with pytest.raises(UserError, match="lattice_tries ≥ 1"):
        ExactSettings(**{field: value})


def test_local_executor_spreads_jobs_over_other_processes_and_stops_on_an_error():
    scene = make_tiny_scene(seed=0)
    config = HideConfig(layout="ray", part_pixels=24)
    secret = np.random.default_rng(0).integers(0, 256, (8, 8, 3), dtype=np.uint8)
    tile = plan(scene, secret, config).tiles[0]
    pixels = torch.tensor(secret.reshape(-1, 3))
    weights = FieldWeights.of(scene, tile.network)
    jobs = [Job(0, c, tile, range(s, min(s + 24, 64)), pixels[s:s + 24], config, "cpu")
            for c, s in enumerate(range(0, 64, 24))]
    with LocalExecutor(weights, workers=2) as executor:
        for job in jobs:
            executor.submit(job)
        spread = {job.part: result for job, result in executor.results()}
        assert executor.workers  # three jobs waited at once: they went to the workers
    for job in jobs:  # the same tensors as solved here
        assert all(torch.equal(spread[job.part][name], value) for name, value in JobRunner().run(weights, job).items())
    with pytest.raises(IndexError), LocalExecutor(weights, workers=2) as executor:
        for rows in (range(0, 24), range(0, 10 ** 6)):  # a job past the tile's rays fails in its worker
            executor.submit(Job(0, 0, tile, rows, pixels[:24], config, "cpu"))
        list(executor.results())
    with pytest.raises(RuntimeError, match="a hide worker process ended with exit code -9"), \
            LocalExecutor(weights, workers=2) as executor:
        for job in jobs:
            executor.submit(job)
        executor.dispatch()
        for worker in executor.workers:  # killed (say, out of memory) before they finish: no endless wait
            os.kill(worker.pid, signal.SIGKILL)
        list(executor.results())


class Unpicklable(Exception):
    def __init__(self, what: str, where: int):  # pickling rebuilds it from args alone: fails
        super().__init__(f"{what} at {where}")


def test_a_worker_error_that_cannot_be_pickled_reaches_the_driver_named():
    error = sendable(Unpicklable("bad", 3))
    assert type(error) is RuntimeError and str(error) == "Unpicklable: bad at 3"
    refusal = UserError("m", code="a.b", n=1)
    assert sendable(refusal) is refusal


def test_a_basis_that_ignores_what_it_missed_is_refused():
    with pytest.raises(UserError, match="missed_weight must be at least 1, got 0"):
        CompactSettings(missed_weight=0)
