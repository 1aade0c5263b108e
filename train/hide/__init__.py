"""The hiding layer (torch): hide plans and tiles, the secret view, the solvers behind one interface
(solver.py), resume, payloads. Imports runtime and train.scene."""
