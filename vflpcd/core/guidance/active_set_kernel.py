"""The fairing's active set (``fairing.solve_active_set``) as one plain loop to compile.

The problem: min of a strictly convex quadratic whose Hessian M (N x N, N = K d) is banded with
u sub-diagonals, given in LAPACK's lower band layout ``low[i - j, j] = M[i, j]`` (i >= j), and
right-hand side f (the minimiser of the free problem solves M x = f), subject to one half-plane
per point, n_k' x_k >= b_k, for the points with ``constrained[k]``. An active half-plane is held
by a stiff spring: ``penalty`` (n_k n_k') is added to M's block k and ``penalty`` b_k n_k to f_k,
so each round is one banded Cholesky factorisation and triangular solves, and the spring's
stretch gap_k = n_k' x_k - b_k < 0 is the half-plane's multiplier over ``penalty``. A round
factorises again only from the first point whose spring changed since the last: the columns before
it, their factor and the forward solve there are the same numbers.

The dual active set of Goldfarb and Idnani (Math. Programming 27, 1983), which starts from a
minimiser and keeps every active multiplier non-negative (``active`` given: its half-planes held
from outside, gap_k > ``release``, are released first):

- the most violated inactive half-plane p (gap_p < -``violation``) is pushed towards by a force
  t n_p on point p; the points move along z = M_A^{-1} e_p n_p (M_A: M with the active springs);
- the force grows until p's half-plane holds (t2 = -gap_p / n_p' z_p: p is made active) or an
  active multiplier reaches zero first (t1 = -gap_k / n_k' z_k: k is released, the force is kept
  and p is pushed on with the new M_A);
- when no half-plane is violated, x is the minimiser.

Each step raises the dual objective, so no active set repeats: the rounds are about the number of
half-planes that end active, where a primal active set, which needs a feasible start and moves
a contact point one path point a round, took many times as many on the fairings among movers
(``test_the_active_set_converges_in_few_rounds_where_a_primal_one_cycled_or_crawled``).
Its iterates cut into the half-planes until the end, so when ``rounds`` run out, every violated
half-plane is made active until a minimiser violates none (at most K more rounds): the point
returned keeps the half-planes, though it is not the minimiser.

Returns the rounds taken (a positive number) when it converged, 0 when ``rounds`` ran out,
-1 when a factorisation met a non-positive pivot. ``active`` (K,) and ``x`` (N,) are written in
place. A loop compiler (numba's ``njit``: ``vflpcd.controllers.loops`` compiles it, outside core)
turns it into machine code; the fairing's numpy path runs the same steps with LAPACK's ``dpbsv``.
"""

from __future__ import annotations

import math

import numpy as np


def solve_loop(low0, f0, n, b, constrained, active, x, rounds, penalty, violation, release):
    """The active set above on M = low0 (u + 1, N) and f0 (N,), half-planes n (K, d), b (K,)."""
    K, d = n.shape
    N = K * d
    u = low0.shape[0] - 1
    low = np.empty_like(low0)
    y = np.empty(N)
    xa = np.empty(N)                           # the minimiser of the active springs alone
    z = np.empty(N)
    factored = np.zeros(K, dtype=np.bool_)     # the active set that low and y were computed for
    p, force = -1, 0.0                         # the half-plane pushed towards, and the push
    dual = True                                # False: restoring (rounds ran out)
    for r in range(rounds + K + 1):
        if r == rounds:
            dual = False
        k0 = 0
        if r > 0:
            k0 = K
            for k in range(K):
                if active[k] != factored[k]:
                    k0 = k
                    break
        j0 = k0 * d          # the matrix, its factor and L y = f are unchanged before column j0
        low[:, j0:] = low0[:, j0:]
        y[j0:] = f0[j0:]
        for k in range(k0, K):      # the springs of the active half-planes
            if active[k]:
                for j1 in range(d):
                    y[k * d + j1] += penalty * b[k] * n[k, j1]
                    for j2 in range(j1, d):
                        low[j2 - j1, k * d + j1] += penalty * n[k, j1] * n[k, j2]
        for j in range(j0, N):      # banded Cholesky M = L L', L in place of low
            s = low[0, j]
            for m in range(1, min(u, j) + 1):
                s -= low[m, j - m] * low[m, j - m]
            if not s > 0.0:
                return -1
            pivot = math.sqrt(s)
            low[0, j] = pivot
            for i in range(j + 1, min(N, j + u + 1)):
                s = low[i - j, j]
                for m in range(1, min(u - (i - j), j) + 1):
                    s -= low[i - j + m, j - m] * low[m, j - m]
                low[i - j, j] = s / pivot
        for i in range(j0, N):      # L y = f
            s = y[i]
            for m in range(1, min(u, i) + 1):
                s -= low[m, i - m] * y[i - m]
            y[i] = s / low[0, i]
        for k in range(K):
            factored[k] = active[k]
        xa[:] = y
        for i in range(N - 1, -1, -1):   # L' xa = y
            s = xa[i]
            for m in range(1, min(u, N - 1 - i) + 1):
                s -= low[m, i] * xa[i + m]
            xa[i] = s / low[0, i]
        if not dual:                 # restoring: every violated half-plane made active
            added = False
            for k in range(K):
                if constrained[k] and not active[k] and half_plane_gap(n, b, k, xa) < -violation:
                    active[k] = True
                    added = True
            x[:] = xa
            if not added:
                return 0
            continue
        if p < 0:
            released = False         # a warm start's half-planes held from outside
            for k in range(K):
                if active[k] and half_plane_gap(n, b, k, xa) > release:
                    active[k] = False
                    released = True
            if released:
                continue
            worst = -violation
            for k in range(K):
                if constrained[k] and not active[k]:
                    g = half_plane_gap(n, b, k, xa)
                    if g < worst:
                        worst, p = g, k
            if p < 0:
                x[:] = xa
                return r + 1
            force = 0.0
        z[:] = 0.0                   # z = M_A^-1 e_p n_p: L w = e_p n_p, then L' z = w
        for i in range(p * d, N):
            s = n[p, i - p * d] if i < (p + 1) * d else 0.0
            for m in range(1, min(u, i - p * d) + 1):
                s -= low[m, i - m] * z[i - m]
            z[i] = s / low[0, i]
        for i in range(N - 1, -1, -1):
            s = z[i]
            for m in range(1, min(u, N - 1 - i) + 1):
                s -= low[m, i] * z[i + m]
            z[i] = s / low[0, i]
        for i in range(N):
            x[i] = xa[i] + force * z[i]
        reach_p = normal_dot(n, p, z)
        full = -half_plane_gap(n, b, p, x) / reach_p if reach_p > 0.0 else math.inf
        part, drop = math.inf, -1    # the first active multiplier to reach zero
        for k in range(K):
            if active[k]:
                a = normal_dot(n, k, z)
                if a > 0.0:
                    t = max(-half_plane_gap(n, b, k, x) / a, 0.0)
                    if t < part:
                        part, drop = t, k
        p, force, restore = dual_step(full, part, p, drop, active, force)
        if restore:
            dual = False
    return 0


def half_plane_gap(n, b, k, v):
    """n_k' v_k - b_k: how far point k of v (N,) lies outside half-plane k (negative: inside)."""
    d = n.shape[1]
    g = -b[k]
    for j in range(d):
        g += n[k, j] * v[k * d + j]
    return g


def normal_dot(n, k, v):
    """n_k' v_k for point k of v (N,)."""
    d = n.shape[1]
    a = 0.0
    for j in range(d):
        a += n[k, j] * v[k * d + j]
    return a


def dual_step(full, part, p, drop, active, force):
    """One step of the dual active set once the force that makes half-plane p hold (``full``) and
    the force at which active half-plane ``drop``'s multiplier reaches zero first (``part``) are
    known: p made active (the next p is chosen afresh: -1), or ``drop`` released with the force
    kept; ``active`` written in place. Returns (p, force, whether to restore: nothing moves p out)."""
    if full <= part:
        if not math.isfinite(full):
            return p, force, True
        active[p] = True
        return -1, force, False
    active[drop] = False
    return p, force + part, False
