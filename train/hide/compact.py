"""The compact noise layout: a small basis per tile, a few integer coefficients per pixel.

Pixels of one secret view see nearly the same field, so the noise that brings them to their colours
varies in few directions. Per tile, from a seeded sample of its pixels solved first in the full noise:

- offset o (dims,): the mean of their solved noise (it lifts the density, as every solution does);
- basis B (dims, k): the top-k principal directions of their solved noise around o;
- scale: one integer step of a coefficient, coefficient_range / the dtype's largest integer.

Each pixel's noise is o + (q · scale) Bᵀ with q (k,) int16 (or int8); the exact solver works in that
space (train/hide/exact.NoiseSpace) and judges only lattice points, as the ray layout judges only float16
noise. A basis cannot reach every colour from every start (on lego 0.01–0.3 % of a photo's pixels stay
stuck in the 6-dimensional slice); those pixels escape: they are solved again in the full 90 values and
stored as float16 noise beside the coefficients, so every pixel is still exact.

Why k = 6 with steps of 1/32 (measured on a lego fit, README "Formats"): each coefficient costs ~1.2
bytes a pixel after xz, each escape 184 bytes. k = 4 left 0.3–6 % of pixels to escape and hid 4× slower
than the ray layout; k = 5 cost 6.2–6.6 bytes on most photos but let a fifth of one photo's pixels
(a near-white background) escape, 42 bytes a pixel; k = 6 costs ~0.8 byte more on easy photos, brings
that photo to 8.7 and hides faster (fewer restarts); k = 7–8 cost more than their fewer escapes save.
A coarser step (1/16) saves ~0.4 byte but escapes several times more pixels; int8 coefficients leave
most pixels unreachable on their lattice. (Measured before exact.round_to_lattice, which brought that
photo to 7.3; with it, k = 8 hid a 128-px photo ~4× slower than k = 6, its lattice search being 25×
larger, and k = 5 let 14 % of a koala escape.)
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import torch

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_COMPACT_COEFFICIENTS
from noisenerf.train.hide.secret_view import SecretView
from noisenerf.train.hide.exact import INTEGER_LIMITS, ExactSettings, NoiseSpace, solve_exact

@dataclass(frozen=True)
class CompactSettings:
    key: ClassVar[str] = "compact"  # where bundles record these settings
    coefficients: int = 6  # k per pixel
    coefficient_range: float = 1024.0  # largest storable |coefficient|: int16 steps of 1/32
    # a seeded sample of a tile's pixels whose solved noise chooses its offset and basis: 256 let 3.6 % of a
    # tench photo's pixels escape (13 bytes a pixel), 1,024 0.07 % (6.7), and hid it faster (README "Formats")
    basis_pixels: int = 1024
    max_iters: int = 50  # per phase in the basis; a pixel still unfinished escapes to full float16 noise
    tolerance_bins: float = 0.4  # float phase in the basis: round_to_lattice re-aims at the bin centre after it

    def __post_init__(self):
        if not 1 <= self.coefficients <= MAX_COMPACT_COEFFICIENTS:
            raise UserError(f"coefficients per pixel must be between 1 and {MAX_COMPACT_COEFFICIENTS}, "
                            f"got {self.coefficients}")


def principal_basis(noise: torch.Tensor, k: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean and top-k principal directions of noise vectors, signs fixed (largest entry positive) so the
    basis is a function of the noise alone; zero columns where fewer than k vectors span fewer directions.
    noise: (s, dims) -> offset (dims,), basis (dims, k) with orthonormal (or zero) columns."""
    offset = noise.mean(0)
    _, _, vh = torch.linalg.svd((noise - offset).double(), full_matrices=False)
    basis = torch.zeros(noise.shape[1], k, dtype=torch.float64, device=noise.device)
    basis[:, :min(k, vh.shape[0])] = vh[:k].T
    basis = basis * torch.where(basis.gather(0, basis.abs().argmax(0, keepdim=True)) < 0, -1.0, 1.0)
    return offset.contiguous(), basis.float().contiguous()


def tile_space(view: SecretView, pixels: torch.Tensor, settings: CompactSettings, exact: ExactSettings,
               storage: torch.dtype, seed: int) -> NoiseSpace:
    """The compact NoiseSpace of one tile with int8/int16 coefficients: `basis_pixels` of its pixels
    (n, 3) uint8 drawn with `seed`, solved in full float32 noise, give the offset and basis."""
    generator = torch.Generator().manual_seed(seed)
    sample = torch.randperm(view.n_rays, generator=generator)[:settings.basis_pixels].to(pixels.device)
    solved = solve_exact(view, sample, pixels[sample], NoiseSpace(torch.float32), exact, generator)
    offset, basis = principal_basis(solved.params, settings.coefficients)
    scale = float(np.float32(settings.coefficient_range / INTEGER_LIMITS[storage]))
    return NoiseSpace(storage, basis, offset, scale)
