"""vflpcd: Vector Field-guided Learning Predictive Control daemon."""

import os

# The controller works on small matrices; on a few cores a multi-threaded BLAS only fights the
# control loop and the workers for them (a GP refit measured 148 ms single-threaded and 10 s with
# two OpenBLAS threads on two cores). A user's explicit setting wins.
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
