"""``sparse_gp.FITCGP.add_sample``'s update as one loop to compile (the numpy path gives the same
numbers to 1e-12, tests/unit/core/dynamics/test_gp_kernel.py).

Per output a, with k = sf2_a exp(-|Zm_j - z|^2 / (2 ell_a^2)) (m,):

    v = L^-1 k,   lambda = max(sf2_a - v.v, 0) + sn2_a,   w = A^-1 v,
    A^-1 <- A^-1 - w w' / (lambda + v.w)      (Sherman-Morrison),
    c <- c + v y_a / lambda,   alpha = L^-T A^-1 c.

The online GP folds one sample in at every model step, and on the few inducing inputs a run holds
(2 to 48) numpy's fixed cost per call made this 46 us of the controller's tick. A loop compiler
(numba's ``njit``: ``vflpcd.controllers.loops``) turns it into one machine-code function; run as
Python it is slow.
"""

from __future__ import annotations

import math

import numpy as np

from vflpcd.core.loop_algebra import matvec


def add_sample_loop(Zm, sf2, nh_inv_ell2, sn2, Linv, Ainv, c, z, y):
    n_y, m, n_z = Linv.shape[0], Zm.shape[0], Zm.shape[1]
    Ainv_new = np.empty_like(Ainv)
    c_new = np.empty_like(c)
    alpha = np.empty_like(c)
    d2 = np.empty(m)
    for j in range(m):
        acc = 0.0
        for i in range(n_z):
            e = Zm[j, i] - z[i]
            acc += e * e
        d2[j] = acc
    k = np.empty(m)
    v = np.empty(m)
    w = np.empty(m)
    t = np.empty(m)
    for a in range(n_y):
        for j in range(m):
            k[j] = sf2[a] * math.exp(nh_inv_ell2[a, 0] * d2[j])
        matvec(Linv[a], k, v)
        matvec(Ainv[a], v, w)
        vv, vw = 0.0, 0.0
        for i in range(m):
            vv += v[i] * v[i]
            vw += v[i] * w[i]
        lam = max(sf2[a] - vv, 0.0) + sn2[a]
        den = lam + vw
        for i in range(m):
            for j in range(m):
                Ainv_new[a, i, j] = Ainv[a, i, j] - w[i] * (w[j] / den)
            c_new[a, i] = c[a, i] + v[i] * (y[a] / lam)
        matvec(Ainv_new[a], c_new[a], t)
        matvec(Linv[a].T, t, alpha[a])
    return Ainv_new, c_new, alpha
