"""``error_model.ErrorModel``'s horizon linearisation for a scheduled input matrix, as one loop to compile.

For every prediction step tau (``ErrorModel._scheduled_linearisation`` is the numpy path, the same
numbers to 1e-12, tests/unit/core/control/test_error_model_scheduled.py):

    B_tau = B + s_r,tau B_s                       (s the schedule column j of Upsilon_r,tau)
    u_r,tau = argmin || x_r,tau+1 - [A Upsilon_r,tau + B_tau u]_{1..n_x} ||, clipped into [u_min, u_max]
    next_tau = A Upsilon_r,tau + B_tau u_r,tau
    A_tau = A + (B_s u_r,tau) e_j'   and B_tau, both without the constant observable's row and column.

The least squares are solved through their normal equations (n_u x n_u, Gaussian elimination with
partial pivoting). A loop compiler (numba's ``njit``: ``vflpcd.controllers.loops``) turns it into one
machine-code function; run as Python it is slow.
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.loop_algebra import matvec


def problem_loop(U_r, A, B, B_s, j, n_x, u_min, u_max):
    N, n_K, n_u = U_r.shape[0] - 1, A.shape[0], B.shape[1]
    n = n_K - 1
    u_r = np.empty((N, n_u))
    nxt = np.empty((N, n_K))
    A_out = np.empty((N, n, n))
    B_out = np.empty((N, n, n_u))
    Bt = np.empty((n_K, n_u))
    G = np.empty((n_u, n_u))
    r = np.empty(n_u)
    for k in range(N):
        s = U_r[k, j]
        matvec(A, U_r[k], nxt[k])
        for i in range(n_K):
            for a in range(n_u):
                Bt[i, a] = B[i, a] + s * B_s[i, a]
        for a in range(n_u):                       # normal equations on the physical rows
            acc = 0.0
            for i in range(n_x):
                acc += Bt[i, a] * (U_r[k + 1, i] - nxt[k, i])
            r[a] = acc
            for b in range(n_u):
                acc = 0.0
                for i in range(n_x):
                    acc += Bt[i, a] * Bt[i, b]
                G[a, b] = acc
        for a in range(n_u):                       # elimination with partial pivoting
            p = a
            for b in range(a + 1, n_u):
                if abs(G[b, a]) > abs(G[p, a]):
                    p = b
            if p != a:
                for b in range(n_u):
                    G[a, b], G[p, b] = G[p, b], G[a, b]
                r[a], r[p] = r[p], r[a]
            for b in range(a + 1, n_u):
                f = G[b, a] / G[a, a]
                for col in range(a, n_u):
                    G[b, col] -= f * G[a, col]
                r[b] -= f * r[a]
        for a in range(n_u - 1, -1, -1):           # back substitution (into r), then the clip
            acc = r[a]
            for b in range(a + 1, n_u):
                acc -= G[a, b] * r[b]
            r[a] = acc / G[a, a]
        for a in range(n_u):
            u_r[k, a] = min(max(r[a], u_min[a]), u_max[a])
        for i in range(n_K):
            acc = nxt[k, i]
            for a in range(n_u):
                acc += Bt[i, a] * u_r[k, a]
            nxt[k, i] = acc
        for i in range(n):
            for col in range(n):
                A_out[k, i, col] = A[i, col]
            acc = 0.0
            for a in range(n_u):
                acc += B_s[i, a] * u_r[k, a]
                B_out[k, i, a] = Bt[i, a]
            A_out[k, i, j] += acc
    return u_r, nxt, A_out, B_out
