"""The Eb-RHRL iterations of ``ebrhrl.EbRHRL.solve`` as one loop to compile.

Steps 1-4 of the solver's docstring, written as plain loops over the prediction steps so that a
loop compiler (numba's ``njit``: ``vflpcd.controllers.loops`` compiles it, outside core) turns
them into one machine-code function; with the barrier's gradient inline
(``barrier.HorizonBarrier.gradient``: the exponential of an affine function of the position
error, constant slope below PI_MIN). ``solve_loop`` updates the actor and critic weights in
place and returns (targets (N, n_u), iterations, max epsilon_a, max epsilon_c, the steps whose target
the input bounds moved); ``bounded`` with (lo, hi) (N, n_u) clips the rollout's controls and
projects the targets (``EbRHRL.solve``'s ``bounds``), and returns at once with iterations -1 when
a bound has lo > hi (``EbRHRL`` raises it).

Run as Python it is slow; EbRHRL without a compiled loop runs its vectorised numpy path instead,
and the two give the same numbers to 1e-12 (tests/unit/core/control/test_ebrhrl.py).
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.control.barrier import PI_MIN


def solve_loop(A_cl, B, c, x0, K, Q, R2, P, M_inv, gamma, W_a, W_c, fa, fb, fh,
               pos_index, p_ref, x_p, normal, mu, length, eta_a, i_max, tol, phi_floor, bounded, lo, hi):
    N, n, n_u = B.shape[0], B.shape[1], B.shape[2]
    m = fa.shape[0]
    nb, d = mu.shape[0], pos_index.shape[0]
    x = np.empty((N + 1, n))
    u = np.empty((N, n_u))
    phi = np.empty((N + 1, m))
    lam = np.empty((N + 1, n))
    grad_h = np.zeros((N + 1, n))
    target = np.empty((N, n_u))
    BW = np.empty((N, n, m))
    inv = np.empty(N + 1)                     # 1 / max(||Phi_tau||^2, phi_floor), the normalised steps
    g = np.empty(n_u)
    Kx = np.empty(n_u)
    eta, eps_a_prev, eps_a, eps_c = eta_a, np.inf, np.inf, np.inf
    iterations = 0
    saturated = 0
    if bounded:                               # bounds with lo > hi: no iteration (iterations -1)
        for k in range(N):
            for v in range(n_u):
                if lo[k, v] > hi[k, v]:
                    return target, -1, eps_a, eps_c, 0
    for it in range(1, i_max + 1):
        iterations = it
        saturated = 0
        # step 1: rollout of the actor through x~_{tau+1} = (A - B K) x~ + B W_a' Phi(x~) + c
        for k in range(N if not bounded else 0):      # the bounded rollout applies u~ itself
            for i in range(n):
                for j in range(m):
                    s = 0.0
                    for v in range(n_u):
                        s += B[k, i, v] * W_a[k, j, v]
                    BW[k, i, j] = s
        for i in range(n):
            x[0, i] = x0[i]
        for k in range(N + 1):
            for j in range(m):
                s = fa[j]
                for i in range(n):
                    s += fb[j, i] * x[k, i] - fh[i] * x[k, i] * x[k, i]
                phi[k, j] = np.exp(s)
            if k == N:
                break
            if bounded:     # the actor's output clipped: x~_{tau+1} = (A - B K) x~ + B (u~ + K x~) + c
                for v in range(n_u):
                    s = 0.0
                    for i in range(n):
                        s += K[k, v, i] * x[k, i]
                    Kx[v] = s
                    s = 0.0
                    for j in range(m):
                        s += phi[k, j] * W_a[k, j, v]
                    u[k, v] = min(max(s - Kx[v], lo[k, v]), hi[k, v])
                for i in range(n):
                    s = 0.0
                    for l in range(n):
                        s += A_cl[k, i, l] * x[k, l]
                    r = 0.0
                    for v in range(n_u):
                        r += B[k, i, v] * (u[k, v] + Kx[v])
                    x[k + 1, i] = s + r + c[k, i]
                continue
            for i in range(n):
                s = c[k, i]
                for l in range(n):
                    s += A_cl[k, i, l] * x[k, l]
                for j in range(m):
                    s += BW[k, i, j] * phi[k, j]
                x[k + 1, i] = s
        if not bounded:
            for k in range(N):
                for v in range(n_u):
                    s = 0.0
                    for j in range(m):
                        s += phi[k, j] * W_a[k, j, v]
                    for i in range(n):
                        s -= K[k, v, i] * x[k, i]
                    u[k, v] = s
        # the barrier's gradient dh/dx~ along the rollout
        for k in range(N + 1):
            for i in range(n):
                grad_h[k, i] = 0.0
            for b in range(nb):
                pi = 0.0
                for q in range(d):
                    pi += normal[b, k, q] * (p_ref[k, q] + x[k, pos_index[q]] - x_p[b, k, q])
                pi = max(pi / length, PI_MIN)
                h = mu[b] * np.exp(-pi)
                for q in range(d):
                    grad_h[k, pos_index[q]] -= h * normal[b, k, q] / length
        # step 2: target costates, backwards
        for i in range(n):
            s = grad_h[N, i]
            for l in range(n):
                s += 2.0 * P[i, l] * x[N, l]
            lam[N, i] = s
        for k in range(N - 1, -1, -1):
            for i in range(n):
                s = grad_h[k, i]
                for l in range(n):
                    s += 2.0 * Q[i, l] * x[k, l] + gamma * A_cl[k, l, i] * lam[k + 1, l]
                for v in range(n_u):
                    r = 0.0
                    for w in range(n_u):
                        r += R2[v, w] * u[k, w]
                    s -= K[k, v, i] * r
                lam[k, i] = s
        # critic update (normalised step), step 3 targets and the actor update
        eps_c = 0.0
        eps_a = 0.0
        for k in range(N + 1):
            norm = 0.0
            for j in range(m):
                norm += phi[k, j] * phi[k, j]
            inv[k] = 1.0 / max(norm, phi_floor)
            e2 = 0.0
            for i in range(n):
                s = 0.0
                for j in range(m):
                    s += phi[k, j] * W_c[k, j, i]
                e = lam[k, i] - s
                e2 += e * e
                for j in range(m):
                    W_c[k, j, i] += phi[k, j] * inv[k] * e
            eps_c = max(eps_c, 0.5 * e2)
        for k in range(N):
            for v in range(n_u):
                s = 0.0
                for w in range(n_u):
                    s += R2[v, w] * u[k, w]
                for i in range(n):
                    s += gamma * B[k, i, v] * lam[k + 1, i]
                g[v] = s
            e2 = 0.0
            moved = False
            for v in range(n_u):
                s = 0.0
                for w in range(n_u):
                    s += M_inv[k, v, w] * g[w]
                t = u[k, v] - s
                if bounded:         # projected onto the bounds
                    p = min(max(t, lo[k, v]), hi[k, v])
                    moved = moved or p != t
                    t = p
                    s = u[k, v] - t
                target[k, v] = t
                e2 += s * s
            if moved:
                saturated += 1
            eps_a = max(eps_a, 0.5 * e2)
        if eps_a > eps_a_prev:          # the last step overshot (barrier curvature): halve the next
            eta *= 0.5
        for k in range(N):
            for j in range(m):
                for v in range(n_u):
                    W_a[k, j, v] += eta * phi[k, j] * inv[k] * (target[k, v] - u[k, v])
        eps_a_prev = eps_a
        if eps_a <= tol or not np.isfinite(eps_a):
            break
    return target, iterations, eps_a, eps_c, saturated
