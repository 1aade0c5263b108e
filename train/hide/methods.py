"""The hiding methods, by the name `--method` and bundles use, as the CLI, HideConfig and the driver
see them: torch-free, one Method each (its settings, defaults and promises). How a method solves is its
Solver (solver.py; the registry is solvers.py), which names its Method.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

from noisenerf.runtime.errors import UserError
from noisenerf.train.hide.settings import (NO_SKIP, RECIPES, REVIVALS, CompactSettings, ExactSettings, PaperSettings,
                                           pass_samples_for, recipe)

if TYPE_CHECKING:
    from noisenerf.train.hide.plan import HideConfig


# An exact method's promise: every value, as the hide renders it, lies at least this many 8-bit levels inside the
# bin it rounds into (runtime.metrics.rounding_margins), so a reveal whose arithmetic differs by less (another
# execution provider, another CPU) still rounds it right. The solver keeps ExactSettings.margin_bins (0.1), twice
# this, in its own model of a pixel; the difference is room for the composite and the float16 escapes.
EXACT_MARGIN_LEVELS = 0.05

@dataclass(frozen=True)
class Method:
    """A hiding method: what it records, what it defaults to, and what it promises."""

    name: str  # the --method value, recorded in bundles
    settings_types: tuple[type, ...]  # frozen dataclasses with a `key` (settings.py), their defaults in every config
    layouts: tuple[str, ...]  # noise layouts it can write, the default first
    default_samples: int  # samples per ray of its secret view
    # its settings as `noisenerf hide`'s flags ask (add_arguments declares them), for a device type (cpu, cuda)
    from_arguments: Callable[[argparse.Namespace, str], tuple]
    add_arguments: Callable[[argparse.ArgumentParser], None] = lambda parser: None  # its own flags
    fixed_samples: bool = False  # whether its secret view takes default_samples per ray and no other
    default_network: str | None = None  # None: the scene's render network
    exact: bool = False  # whether it promises every 8-bit value, EXACT_MARGIN_LEVELS inside: run.hide refuses less
    spreads: bool = False  # whether the local executor spreads its parts over processes on a CPU

    def check(self, config: HideConfig) -> None:
        """Refuse settings this method cannot honour (UserError)."""
        if self.fixed_samples and config.n_samples != self.default_samples:
            n = self.default_samples
            count = "one sample" if n == 1 else f"{n} samples"
            raise UserError(f"--method {self.name} renders its secret view with {count} per ray (--samples {n})")


def paper_flags(parser: argparse.ArgumentParser) -> None:
    """The paper method's flags on `noisenerf hide`: its recipe and the recipe's overrides."""
    paper = PaperSettings()
    parser.add_argument("--recipe", choices=tuple(RECIPES), default=paper.recipe,
                        help=f"paper method: ours, the authors' public code or the paper's text (default {paper.recipe})")
    parser.add_argument("--iters", type=int, help=f"paper method: optimisation iterations (default {paper.iters})")
    parser.add_argument("--revival", choices=REVIVALS,
                        help=f"paper method: which rays start from a colour donor (default {paper.revival})")
    parser.add_argument("--no-skip", action="store_true",
                        help="paper method: every sample of every pixel through every iteration, the method as written "
                        f"(by default dead samples are skipped and checked again every {paper.recheck_every} "
                        f"iterations, and a pixel within {paper.finish_within} levels of its target retires)")


def paper_arguments(args: argparse.Namespace, device_type: str) -> tuple:
    """The recipe `--recipe` names, with `--iters`, `--revival` and `--no-skip` where given."""
    overrides = {name: value for name, value in (("iters", args.iters), ("revival", args.revival))
                 if value is not None} | (NO_SKIP if args.no_skip else {})
    return (recipe(args.recipe, pass_samples=pass_samples_for(device_type), **overrides),)


METHODS: dict[str, Method] = {method.name: method for method in (
    # one sample per ray makes every pixel a piecewise-linear problem (exact.py)
    Method("exact", (ExactSettings, CompactSettings), ("compact", "ray", "sample"), default_samples=1,
           from_arguments=lambda args, device_type: (), fixed_samples=True, exact=True, spreads=True),
    # nerf-pytorch's N_samples, the coarse sampling (and network) the paper's authors render with
    Method("paper", (PaperSettings,), ("sample", "ray"), default_samples=64, from_arguments=paper_arguments,
           add_arguments=paper_flags, default_network="coarse"),
)}
