"""The sender's side (torch): the NeRF field, volume rendering, datasets, fitting and noise hiding.

OpenMP threads wait passively here. torch's CPU build runs its intra-op pool on libgomp, whose idle
threads spin (busy-wait) between parallel regions by default. The exact hide runs thousands of small
ops, so on a machine whose cores are shared the spinning pool threads take the CPU the solver itself
needs: a 64×64 hide measured 25–54 s instead of ~2 s beside other busy processes on 2 cores, and
~2 s again with OMP_WAIT_POLICY=PASSIVE (README, "Predictable speed"). libgomp reads the variable once,
when torch is first imported, so it is set (unless the user chose otherwise) before anything here
imports torch; a program that imported torch before noisenerf.train keeps its own policy.
"""

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
