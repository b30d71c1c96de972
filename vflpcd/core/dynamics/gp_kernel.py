"""The online GP's per-tick steps as loops to compile (the numpy paths give the same numbers to
1e-12, tests/unit/core/dynamics/test_gp_kernel.py).

``add_sample_loop``: ``sparse_gp.FITCGP.add_sample``'s update. Per output a, with
k = sf2_a exp(-|Zm_j - z|^2 / (2 ell_a^2)) (m,):

    v = L^-1 k,   lambda = max(sf2_a - v.v, 0) + sn2_a,   w = A^-1 v,
    A^-1 <- A^-1 - w w' / (lambda + v.w)      (Sherman-Morrison),
    c <- c + v y_a / lambda,   alpha = L^-T A^-1 c.

``corrected_next_loop``: ``compensation.KoopmanCompensation.corrected_next``, the horizon's
nominal next lifted states plus B_d m(z_tau), m the GP's mean (eq. FITC) at z_tau = [Upsilon_r,tau[z_index],
u_r,tau]: m_a(z) = sum_j alpha_aj sf2_a exp(-|z - Zm_j|^2 / (2 ell_a^2)).

``ald_delta_loop``: ``ald.ALDDictionary.delta``, delta(z) = sf2 - k' P k with
k_j = sf2 exp(-|D_j - z|^2 / (2 ell^2)) and P = K_DD^-1.

The online GP folds one sample in, tests it for the dictionary and corrects the horizon at every
model step; on the few inducing inputs a run holds (2 to 48) numpy's fixed cost per call made
these 46, 13 and 45 us of the controller's tick. A loop compiler (numba's ``njit``:
``vflpcd.controllers.loops``) turns each into one machine-code function; run as Python they are slow.
"""

from __future__ import annotations

import math

import numpy as np

from vflpcd.core.loop_algebra import matvec, row_sq_distance


def add_sample_loop(Zm, sf2, nh_inv_ell2, sn2, Linv, Ainv, c, z, y):
    n_y, m = Linv.shape[0], Zm.shape[0]
    Ainv_new = np.empty_like(Ainv)
    c_new = np.empty_like(c)
    alpha = np.empty_like(c)
    d2 = np.empty(m)
    for j in range(m):
        d2[j] = row_sq_distance(Zm, j, z)
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


def corrected_next_loop(nxt, U, u, z_index, Zm, sf2, nh_inv_ell2, alpha, B_d):
    N, n_K = nxt.shape
    m, n_z = Zm.shape
    n_y, n_zx = alpha.shape[0], z_index.shape[0]
    out = nxt.copy()
    z = np.empty(n_z)
    mean = np.empty(n_y)
    shift = np.empty(n_K)
    for k in range(N):
        for i in range(n_zx):
            z[i] = U[k, z_index[i]]
        for i in range(n_z - n_zx):
            z[n_zx + i] = u[k, i]
        for a in range(n_y):
            mean[a] = 0.0
        for j in range(m):
            d2 = row_sq_distance(Zm, j, z)
            for a in range(n_y):
                mean[a] += sf2[a] * math.exp(nh_inv_ell2[a, 0] * d2) * alpha[a, j]
        matvec(B_d, mean, shift)
        for r in range(n_K):
            out[k, r] += shift[r]
    return out


def ald_delta_loop(D, z, P, sf2, nh_inv_ell2):
    m = D.shape[0]
    k = np.empty(m)
    for j in range(m):
        k[j] = sf2 * math.exp(nh_inv_ell2 * row_sq_distance(D, j, z))
    Pk = np.empty(m)
    matvec(P, k, Pk)
    quad = 0.0
    for i in range(m):
        quad += k[i] * Pk[i]
    return sf2 - quad
