"""``rate.RateForm``'s per-tick fill as a loop to compile (the numpy path in ``RateForm.increments``
gives the same numbers, tests/unit/core/control/test_rate.py):

* the increment form's affine terms c_z (N, n + n_u) = [c_tau + B_tau (-s_tau); -s_tau] for the
  inputs whose increment is the command's own (s_tau = u_r,tau - u_r,tau-1, s_0 = 0), [c_tau; 0]
  otherwise, and its start z0 = [x~_0; u_prev - u_r,0];
* the bounds (lo, hi) (N, n_u) on the increments v_tau that keep the command within the rate limit
  du_max at every step: -du_max - s_tau <= v_tau <= du_max - s_tau (s_tau = 0 for a command
  increment, whose v is the command's own step).

Compiled (numba's ``njit``: ``vflpcd.controllers.loops``) it is one call in place of some dozen
numpy calls on these small arrays; run as Python it is slow.
"""

from __future__ import annotations


def increment_loop(c, B, u_ref, x0, u_prev, du_max, commanded, c_z, x0_z, lo, hi):
    N, n = c.shape
    n_u = u_ref.shape[1]
    for k in range(N):
        for i in range(n):
            c_z[k, i] = c[k, i]
        for j in range(n_u):
            c_z[k, n + j] = 0.0
            step = 0.0 if k == 0 else u_ref[k, j] - u_ref[k - 1, j]
            lo[k, j] = -du_max[j] - step
            hi[k, j] = du_max[j] - step
    for q in range(commanded.shape[0]):
        j = commanded[q]
        for k in range(N):
            lo[k, j] = -du_max[j]
            hi[k, j] = du_max[j]
        for k in range(1, N):
            s = u_ref[k - 1, j] - u_ref[k, j]
            c_z[k, n + j] = s
            for i in range(n):
                c_z[k, i] += B[k, i, j] * s
    for i in range(n):
        x0_z[i] = x0[i]
    for j in range(n_u):
        x0_z[n + j] = u_prev[j] - u_ref[0, j]
