"""Every hiding method's settings: frozen dataclasses, torch-free, so that they travel to workers with a
job, and the CLI and HideConfig (plan.py) read them without torch. Each is recorded in a bundle under
its `key`; their meaning is documented where they are used: ExactSettings in exact.py, CompactSettings in
compact.py, PaperSettings (and its recipes) in paper.py. methods.py says which method owns which.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from noisenerf.runtime.errors import UserError
from noisenerf.runtime.limits import MAX_COMPACT_COEFFICIENTS

CPU_PART_PIXELS = 16384  # part_pixels_for a CPU, and HideConfig's default


def part_pixels_for(device_type: str) -> int:
    """Pixels solved together: a GPU needs large batches to be busy (its Jacobians of 4 × 90 per pixel
    stay well under a GiB at 2^18); on a CPU smaller parts resume at a finer grain and cost the same."""
    return 1 << 18 if device_type == "cuda" else CPU_PART_PIXELS


def pass_samples_for(device_type: str) -> int:
    """Samples per pass: what fits comfortably on a GPU (a few GiB of activations at width 256), or
    what keeps a CPU run's memory near 1 GiB."""
    return 1 << 18 if device_type == "cuda" else 1 << 16


@dataclass(frozen=True)
class ExactSettings:
    key: ClassVar[str] = "exact"  # where bundles record these settings
    max_iters: int = 100  # per phase; late iterations only touch the few pixels left
    tolerance_bins: float = 0.1  # float32 phase: distance from the bin centre that counts as converged
    margin_bins: float = 0.1  # storage phase: what stays between a finished value and its bin edge
    density_floor: float = 1.0  # raw density the secret sample is lifted to (opacity exactly 1)
    damping: float = 1e-4  # initial λ, relative to tr(JJᵀ)/4
    step_scales: tuple[float, ...] = (1.0, 0.5, 0.25)
    restart_after: int = 8
    donors: int = 4  # the k-th restart starts from one of the 4k finished pixels nearest in target colour
    restart_spread: float = 1.0  # spread of a random restart around zero noise (restart)
    jitter: float = 0.1  # added to a pixel's restart point per restart it has had
    seed_stride: int = 16  # every seed_stride-th pixel is solved first and warm-starts the others
    chord_steps: int = 3  # warm-started pixels first step with their seed's Jacobian (chord_start)
    lattice_radius: int = 1  # integer lattices: free coefficients tried within ± this many steps (round_to_lattice)
    lattice_tries: int = 2  # integer lattices: best-predicted lattice points rendered per pixel

    def __post_init__(self):
        if self.lattice_tries < 1 or self.lattice_radius < 0 or self.chord_steps < 0:
            raise UserError("the exact solver needs lattice_tries ≥ 1, lattice_radius ≥ 0 and chord_steps ≥ 0")


@dataclass(frozen=True)
class CompactSettings:
    key: ClassVar[str] = "compact"  # where bundles record these settings
    coefficients: int = 5  # k per pixel (train/hide/compact.py: why 5)
    # how far one integer step of a coefficient moves a colour, in 8-bit bins (the median over the basis
    # sample's solved pixels, compact.stepped): coarser steps cost fewer bytes per coefficient until the
    # lattice misses colours
    step_bins: float = 0.35
    # every seed_stride-th pixel is solved first and warm-starts the others (ExactSettings.seed_stride); in a
    # basis 1: every pixel starts at the offset, so solutions stay near it rather than scattered around
    # seeds' noise, and code smaller
    seed_stride: int = 1
    # a seeded sample of a tile's pixels whose solved noise chooses its offset and basis: a smaller sample's
    # basis lets many more pixels escape, which costs more bytes and time than solving the sample
    basis_pixels: int = 1024
    max_iters: int = 50  # per phase in the basis; a pixel still unfinished escapes to full float16 noise
    tolerance_bins: float = 0.4  # float phase in the basis: round_to_lattice re-aims at the bin centre after it
    missed_weight: int = 16  # weight of the sample pixels a first basis misses, in the second (tile_space)

    def __post_init__(self):
        if not self.step_bins > 0 or self.seed_stride < 1:
            raise UserError(f"step_bins must be positive and seed_stride at least 1, got {self.step_bins} and "
                            f"{self.seed_stride}")
        if self.missed_weight < 1:
            raise UserError(f"missed_weight must be at least 1, got {self.missed_weight}")
        if not 1 <= self.coefficients <= MAX_COMPACT_COEFFICIENTS:
            raise UserError(f"coefficients per pixel must be between 1 and {MAX_COMPACT_COEFFICIENTS}, "
                            f"got {self.coefficients}")


REVIVALS = ("all", "dead", "off")  # which rays start from a colour donor (paper.py), the default first


@dataclass(frozen=True)
class PaperSettings:
    """One paper-mode run; RECIPES holds the named presets (these defaults are `noisenerf`'s), the ablation switches
    the strategies."""

    key: ClassVar[str] = "paper"  # where bundles record these settings

    recipe: str = "noisenerf"  # the preset these settings started from (recorded in the bundle)
    iters: int = 300
    lr: float = 0.1
    lr_schedule: str = "step"  # step: lr for t ≤ lr_step_at, then lr_after; exponential: lr·lr_decay^(t/iters)
    lr_decay: float = 0.3
    lr_step_at: int = 250
    lr_after: float = 0.01
    weight_decay: float = 0.0  # decoupled (AdamW), on the encoded input γ + δ, times weight_decay_decay^(t/iters)
    weight_decay_decay: float = 0.3
    pixel_perturbation: bool = False  # eq. 7–8 for t ≤ mu
    mu: int = 50
    lambda_rgb: float = 0.5
    lambda_perturb: float = 0.5
    adaptive_selection: bool = False
    batch_fractions: tuple[float, ...] = (0.25, 0.5, 1.0)
    revival: str = "all"  # off | dead | all: which rays start from a colour donor's encodings
    floor_weight: float = 0.1  # weight of revival's density floor term, see density_shortfall
    density_floor: float = 1.0
    saturation_bound: float = 7.0  # revival's colour term: raw colours past ±this are pulled back (paper.saturation_excess)
    block_pixels: int = 6144  # pixels optimised together (the authors' block)
    pass_samples: int = 1 << 16  # samples per forward/backward pass (memory bound, not a result)
    record_at: tuple[int, ...] = (50, 200, 300)
    skip_dead: bool = True  # exact: dead samples skip the colour branch and the backward pass (see the module docstring)
    recheck_every: int = 10  # sample layout: a dead sample is evaluated again every this many iterations (1: exact)
    finish_within: float | None = 0.4  # a pixel within this many 8-bit levels of its target stops (None: never; paper.py)
    retire_share: float = 0.05  # finished pixels retire at a check once this share of the open ones has (copies cost)
    tf32: bool = True  # CUDA matmuls in TF32: ~3× faster on Ampere and later; this method is approximate anyway

    def __post_init__(self):
        if self.lr_schedule not in ("step", "exponential"):
            raise UserError(f"unknown lr schedule {self.lr_schedule!r}")
        if self.revival not in REVIVALS:
            raise UserError(f"unknown revival {self.revival!r} (off, dead or all)")
        if self.finish_within is not None and not 0 <= self.finish_within < 0.5:
            raise UserError(f"finish_within must be in [0, 0.5) levels (a pixel within it rounds to its target), "
                            f"got {self.finish_within}")
        if not 0 <= self.retire_share <= 1:
            raise UserError(f"retire_share must be in [0, 1], got {self.retire_share}")
        if not self.saturation_bound > 0:
            raise UserError(f"saturation_bound must be positive, got {self.saturation_bound}")
        if self.iters < 1 or self.block_pixels < 1 or self.pass_samples < 1 or self.recheck_every < 1:
            raise UserError("--iters, block_pixels, pass_samples and recheck_every must be positive")


RECIPES = {
    "paper": PaperSettings(recipe="paper", lr=1e-2, lr_schedule="exponential", weight_decay=0.0,
                           pixel_perturbation=True, adaptive_selection=True),
    "authors": PaperSettings(recipe="authors", lr_step_at=50, weight_decay=0.8),
    "noisenerf": PaperSettings(),
}


# `--no-skip`: every sample of every ray, every iteration, finished pixels too
NO_SKIP = {"skip_dead": False, "recheck_every": 1, "finish_within": None}


def recipe(name: str, **overrides) -> PaperSettings:
    """The named recipe with some settings replaced (iters, revival, the ablation switches, ...)."""
    return dataclasses.replace(RECIPES[name], **overrides)
