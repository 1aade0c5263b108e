"""The hiding methods, by the name `--method` and bundles use: one line per method (solver.py)."""

from noisenerf.train.hide.exact_solver import ExactSolver
from noisenerf.train.hide.paper_solver import PaperSolver
from noisenerf.train.hide.solver import Solver

METHODS: dict[str, Solver] = {solver.name: solver for solver in (ExactSolver(), PaperSolver())}
