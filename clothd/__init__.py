"""clothd: real-time cloth tracking and control for a textile cell (README.md)."""

import os

# One BLAS thread in every clothd process unless the user chose otherwise, set as the package loads, before
# numpy does: the matrices are small (the mesh EKF's banded solve), and a pool sized to every core only
# spins against the loop, hwsim and the other trackers. On a loaded 2-core machine the lockstep flow's
# banded solves took 224 ms a frame with it, 6 ms without (docs/benchmarks.md, "Production flow").
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
