"""`--method exact` (the default): every pixel's 8-bit value recovered exactly (exact.py's solver), a
tile at a time in resumable parts, its noise stored compactly (compact.py) or as float noise per ray."""

from __future__ import annotations

import contextlib
import dataclasses
from typing import TYPE_CHECKING, Callable

import torch

from noisenerf.runtime.layouts import LAYOUTS, CompactBasis, CompactNoise, TileNoise, VectorNoise
from noisenerf.train.hide.compact import in_basis, predicted_choice, solver_view, tile_space
from noisenerf.train.hide.exact import (ExactProblem, NoiseSpace, SolveCounts, is_lifted, raw_floors, rescue,
                                        solve_exact)
from noisenerf.train.hide.methods import METHODS
from noisenerf.train.hide.secret_view import BranchView, SecretView
from noisenerf.train.hide.settings import CompactSettings, ExactSettings
from noisenerf.train.hide.solver import Solver, TileSolution, part_seed, storage_dtype
from noisenerf.train.hide.tiling import part_rows

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig

CPU_THREADS = 1  # see ExactSolver.threads
ESCAPE_DTYPE = torch.float16  # a compact tile's escaped pixels store full noise as the ray layout does
COUNTS = ("iterations", "jacobians", "renders", "restarts")


def stored_noise(space: NoiseSpace, params: torch.Tensor, escaped: torch.Tensor, branch_escaped: torch.Tensor,
                 escape_noise: torch.Tensor, shape: tuple[int, ...], position_dims: int, band_rows: int) -> TileNoise:
    """What a tile's bundle entry holds for solved params (n, P), of shape `shape` (its last entry −1 for P)
    in the storage dtype: float noise, or for a compact space integer coefficients (an escaped pixel's as its
    part's predicted_choice left them) coded in bands of band_rows rows and the basis, with the escaped pixels
    (n,) bool and their float16 noise, and the branch escapes (n,) bool and the float16 values of their noise
    after its first position_dims (escape_noise (n, dims) holds both kinds' noise)."""
    if space.basis is None:
        return VectorNoise(params.reshape(shape).to(space.storage).cpu().numpy())
    escapes, branch_escapes = escaped.nonzero()[:, 0], branch_escaped.nonzero()[:, 0]
    basis = CompactBasis(basis=space.basis.cpu().numpy(), offset=space.offset.cpu().numpy(), scale=space.scale,
                         escapes=escapes.to(torch.int32).cpu().numpy(),
                         escape_noise=escape_noise[escapes].to(ESCAPE_DTYPE).cpu().numpy(),
                         branch_escapes=branch_escapes.to(torch.int32).cpu().numpy(),
                         branch_escape_noise=escape_noise[branch_escapes, position_dims:].to(ESCAPE_DTYPE).cpu().numpy())
    coefficients = space.integers(params)  # an escape's are never expanded: predicted_choice made them cheap
    return CompactNoise.of(coefficients.reshape(shape).cpu().numpy(), basis, band_rows)


def branch_space(space: NoiseSpace, position_dims: int) -> NoiseSpace:
    """Float16 noise in the direction segment alone, the position segment at the compact space's offset: where
    a branch escape is solved. Its expansion is exactly [offset's position part ‖ the float16 values]."""
    dims = len(space.offset)
    embedding = torch.eye(dims, device=space.offset.device)[:, position_dims:]
    offset = torch.cat([space.offset[:position_dims], space.offset.new_zeros(dims - position_dims)])
    return NoiseSpace(ESCAPE_DTYPE, embedding, offset)


def solve_pixels(secret_view: SecretView, index: torch.Tensor, pixels: torch.Tensor, space: NoiseSpace,
                config: HideConfig, seed: int, width: int) -> dict[str, torch.Tensor]:
    """One part's solve, as saved for resume: params (m, P), counts, and for a compact space the pixels it
    could not finish: those the view branch alone still brings to their colours, `branch_escaped` (m,) uint8,
    solved again in float16 direction noise, the others, `escaped` (m,) uint8, in full float16 noise, both
    kinds' noise in `escape_noise` (m, dims) (zero where neither). Compact solves run at most
    CompactSettings.max_iters per phase: the few pixels its basis cannot reach escape sooner, and their
    float phase stops at CompactSettings.tolerance_bins. The pixels (whole rows `width` wide) then take the
    coefficients cheapest to code (compact.predicted_choice)."""
    generator, counts = torch.Generator().manual_seed(seed), SolveCounts()
    settings = config.get(ExactSettings)
    if space.basis is None:
        problem = ExactProblem(secret_view, index, pixels, space, settings, generator, counts)
        result = solve_exact(problem)
        params, _ = rescue(problem, result.params, result.done)
        return {"noise": params, "counts": torch.tensor(dataclasses.astuple(counts))}
    solving = solver_view(secret_view, space)
    # a ray the tile's shared position noise leaves unlifted can only escape: no basis solve for it
    tried = (is_lifted(solving.density[index], raw_floors(solving.field, settings.density_floor)[1])
             if isinstance(solving, BranchView)
             else torch.ones_like(index, dtype=torch.bool)).nonzero()[:, 0]
    result = solve_exact(ExactProblem(solving, index[tried], pixels[tried], space,
                                      in_basis(settings, config.get(CompactSettings)), generator, counts))
    params = space.zeros(len(index), secret_view.noise_dims, index.device)
    done = torch.zeros_like(index, dtype=torch.bool)
    params[tried], done[tried] = result.params, result.done
    escape_noise = space.expand(params)[:, 0]  # the escapes' starts; the finished pixels' noise, their donors
    branch_escaped = torch.zeros_like(done)
    if isinstance(solving, BranchView) and not done[tried].all():  # the view branch, every direction value free
        position_dims = secret_view.field.config.position_dims
        directions = branch_space(space, position_dims)
        problem = ExactProblem(solving, index[tried], pixels[tried], directions, settings, generator, counts)
        solved, ok = rescue(problem, directions.store(escape_noise[tried, position_dims:]), done[tried])
        reached = ok & ~done[tried]
        branch_escaped[tried[reached]] = True
        escape_noise[tried[reached]] = directions.expand(solved[reached])[:, 0]
    escaped = ~(done | branch_escaped)
    if escaped.any():  # escapes start from their own compact noise (it keeps the tile's density lift)
        escapes = ExactProblem(secret_view, index, pixels, NoiseSpace(ESCAPE_DTYPE), settings, generator, counts)
        full, _ = rescue(escapes, escape_noise, ~escaped)
        escape_noise[escaped] = full[escaped]
    escape_noise[done] = 0
    params = predicted_choice(secret_view.subset(index), space, pixels[index], (len(index) // width, width), params,
                              ~done, in_basis(settings, config.get(CompactSettings)), generator)
    return {"noise": params, "counts": torch.tensor(dataclasses.astuple(counts)), "escaped": escaped.to(torch.uint8),
            "branch_escaped": branch_escaped.to(torch.uint8), "escape_noise": escape_noise}


def sound_part(saved: dict[str, torch.Tensor], space: NoiseSpace) -> bool:
    """What the solver assumes of a saved part beyond its layout: storable params (on the lattice, or
    in the storage dtype), counts ≥ 0, escapes 0 or 1, no pixel both kinds of escape."""
    flags = [saved[name] for name in ("escaped", "branch_escaped") if name in saved]
    return (torch.equal(space.store(saved["noise"]), saved["noise"]) and bool((saved["counts"] >= 0).all())
            and all(bool((flag <= 1).all()) for flag in flags)
            and (len(flags) < 2 or not bool((flags[0] & flags[1]).any())))


class ExactSolver(Solver):
    method = METHODS["exact"]

    @contextlib.contextmanager
    def threads(self, device: torch.device):
        """One torch thread on a CPU. The Levenberg–Marquardt loop is thousands of small ops; with torch's
        OpenMP pool of one thread per core, every op is a parallel region whose idle threads spin, and on
        a machine whose cores are shared that spinning took the solver's own CPU (docs/methods.md, "Predictable
        speed", has the figures). One thread costs little on a quiet machine, much less than a pool on a busy
        one, and makes the bundle's bytes independent of the machine's core count."""
        if device.type != "cpu":
            yield
            return
        before = torch.get_num_threads()
        torch.set_num_threads(CPU_THREADS)
        try:
            yield
        finally:
            torch.set_num_threads(before)

    def prepares(self, config: HideConfig) -> bool:
        return LAYOUTS[config.layout].shares_basis

    def prepare(self, secret_view: SecretView, pixels: torch.Tensor, config: HideConfig, tile_index: int) -> NoiseSpace:
        """A compact tile's basis, from its own seed (part_seed's part −1)."""
        return tile_space(secret_view, pixels, config.get(CompactSettings), config.get(ExactSettings),
                          storage_dtype(config.dtype), part_seed(config, tile_index, -1))

    def part_pixels(self, config: HideConfig) -> int:
        return config.part_pixels

    def solve_part(self, secret_view: SecretView, rows: range, pixels: torch.Tensor, config: HideConfig, tile_index: int,
                   part: int, prepared: NoiseSpace | None, width: int) -> dict[str, torch.Tensor]:
        """Part `part`: solved in a view of its rays alone (ray i being ray rows[i] of the tile)."""
        index = torch.arange(rows.start, rows.stop, device=pixels.device)
        return solve_pixels(secret_view.subset(index), torch.arange(len(rows), device=pixels.device), pixels,
                           part_space(config, prepared), config, part_seed(config, tile_index, part), width)

    def part_layout(self, config: HideConfig, rows: int, dims: int, prepared: NoiseSpace | None
                    ) -> tuple[dict, Callable]:
        space = part_space(config, prepared)
        layout = {"noise": ((rows, space.width(dims)), torch.float32), "counts": ((len(COUNTS),), torch.int64)}
        if space.basis is not None:
            layout.update(escaped=((rows,), torch.uint8), branch_escaped=((rows,), torch.uint8),
                          escape_noise=((rows, dims), torch.float32))
        return layout, lambda tensors: sound_part(tensors, space)

    def assemble(self, secret_view: SecretView, pixels: torch.Tensor, shape: tuple[int, int], config: HideConfig,
                 prepared: NoiseSpace | None, parts: list[dict[str, torch.Tensor]]) -> TileSolution:
        """The parts' params, escapes and counts merged; the report has the solver's counts and the number
        of escaped pixels."""
        space = part_space(config, prepared)
        device = pixels.device
        params = torch.cat([part["noise"] for part in parts]).to(device)
        counts = torch.stack([part["counts"] for part in parts])
        totals = {name: int(counts[:, i].max() if name == "iterations" else counts[:, i].sum())
                  for i, name in enumerate(COUNTS)}
        if space.basis is None:
            escaped = branch_escaped = torch.zeros(len(params), dtype=torch.bool, device=device)
            escape_noise = torch.zeros(len(params), secret_view.noise_dims, device=device)
        else:
            escaped, branch_escaped = (torch.cat([part[name] for part in parts]).bool().to(device)
                                       for name in ("escaped", "branch_escaped"))
            escape_noise = torch.cat([part["escape_noise"] for part in parts]).to(device)
        outside = escaped | branch_escaped
        noise = torch.where(outside[:, None, None], escape_noise[:, None, :], space.expand(params))
        stored = stored_noise(space, params, escaped, branch_escaped, escape_noise,
                              LAYOUTS[config.layout].stored_shape(*shape, 1, -1), secret_view.field.config.position_dims,
                              part_rows(shape[1], shape[0], config.part_pixels))
        return TileSolution(noise, {**totals, "escaped": int(outside.sum()), "branch_escaped": int(branch_escaped.sum())},
                            stored)


def part_space(config: HideConfig, prepared: NoiseSpace | None) -> NoiseSpace:
    """Where a tile's parts look for noise: its compact basis, or the full noise in the storage dtype."""
    return prepared if prepared is not None else NoiseSpace(storage_dtype(config.dtype))
