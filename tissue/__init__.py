"""probegym's finite-element tissue simulator.

Knows nothing of MuJoCo, Gymnasium or torch: a scriptable hyperelastic tet simulator with
implicit integration, sparse solvers, probe contact strategies and a PBD baseline.
"""

import os

# MKL (Pardiso) and numba's kernels each bring an OpenMP runtime; on a small machine their
# idle workers spin on the same cores and slow each other down 2-3x (measured here on two
# cores: a 26k-tet Newton step took 200 ms with both threaded, 100 ms with Pardiso
# sequential). So Pardiso runs on the calling thread unless the user says otherwise; this
# must be set before MKL is loaded. Override with MKL_THREADING_LAYER=INTEL: with the
# passive waiting below, threaded Pardiso is faster on idle cores (26k-tet paper LM step
# 247-261 -> 146-163 ms, two cores), but its factorisations are not bitwise repeatable, which
# runs, resumed cells and iteration-counted refresh rules rely on (see the README, Threads).
os.environ.setdefault("MKL_THREADING_LAYER", "SEQUENTIAL")
# Idle OpenMP workers of numba's kernels wait passively: on a busy shared machine spinning
# workers made parallel kernels 30-250 x slower (measured here under a load of 2-5 on two
# cores); passive waiting costs about 1-2 ms per step on an idle one.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
