"""How each hiding method solves, by the name `--method` and bundles use: one line per method (solver.py)."""

from noisenerf.train.hide.exact_solver import ExactSolver
from noisenerf.train.hide.paper_solver import PaperSolver
from noisenerf.train.hide.solver import Solver

SOLVERS: dict[str, Solver] = {solver.method.name: solver for solver in (ExactSolver(), PaperSolver())}
