"""The fairing's active set (``fairing.solve_active_set``) as one plain loop to compile.

The problem: min of a strictly convex quadratic whose Hessian M (N x N, N = K d) is banded with
u sub-diagonals, given in LAPACK's lower band layout ``low[i - j, j] = M[i, j]`` (i >= j), and
right-hand side f (the minimiser of the free problem solves M x = f), subject to one half-plane
per point, n_k' x_k >= b_k, for the points with ``constrained[k]``. An active half-plane is held
by a stiff spring: ``penalty`` (n_k n_k') is added to M's block k and ``penalty`` b_k n_k to f_k,
so each round is one banded Cholesky factorisation and two triangular solves, and the spring's
stretch gap_k = n_k' x_k - b_k < 0 is the half-plane's multiplier over ``penalty``. A round
factorises again only from the first point whose spring changed since the last: the columns before
it, their factor and the forward solve there are the same numbers.

Two phases (Nocedal and Wright, Numerical Optimization, algorithm 16.3, for the second):

1. from ``active``, every half-plane that the round's minimiser violates by more than
   ``violation`` is made active, until a minimiser violates none (the active set only grows: at
   most K rounds);
2. from that feasible point x, each round solves for the minimiser x* of the active set and steps
   from x towards it as far as the inactive half-planes let it (the first that x* would violate
   blocks and is made active); when x* is reached, the active half-plane that the spring holds
   from outside the most (gap_k > ``release``: a negative multiplier) is released, and when none
   is, x* is the minimiser of the problem. Every step keeps the half-planes and does not raise
   the cost, so the release does not cycle as jumping to x* would (a release lets a point
   inwards, the next solve adds the half-planes that it crosses, and those push back).

Returns the rounds taken (a positive number) when it converged, 0 when ``rounds`` ran out (x is
then the last feasible point, or the last minimiser when phase 1 never found one), -1 when a
factorisation met a non-positive pivot. ``active`` (K,) and ``x`` (N,) are written in place.
A loop compiler (numba's ``njit``: ``vflpcd.controllers.loops`` compiles it, outside core) turns
it into machine code; the fairing's numpy path runs the same two phases with LAPACK's ``dpbsv``.
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
    xs = np.empty(N)
    factored = np.zeros(K, dtype=np.bool_)     # the active set that low and y were computed for
    k0 = 0                                     # the first point whose spring changed since (all at first)
    feasible = False
    for r in range(rounds):
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
        xs[:] = y
        for i in range(N - 1, -1, -1):   # L' x* = y
            s = xs[i]
            for m in range(1, min(u, N - 1 - i) + 1):
                s -= low[m, i] * xs[i + m]
            xs[i] = s / low[0, i]
        if not feasible:             # phase 1: add every violated half-plane
            added = False
            for k in range(K):
                if constrained[k] and not active[k]:
                    g = -b[k]
                    for j in range(d):
                        g += n[k, j] * xs[k * d + j]
                    if g < -violation:
                        active[k] = True
                        added = True
            x[:] = xs
            if added:
                continue
            feasible = True
        else:                        # phase 2: step towards x* until a half-plane blocks
            step, block = 1.0, -1
            for k in range(K):
                if constrained[k] and not active[k]:
                    after, before = -b[k], -b[k]
                    for j in range(d):
                        after += n[k, j] * xs[k * d + j]
                        before += n[k, j] * x[k * d + j]
                    if after < -violation:
                        before = max(before, 0.0)
                        reach = before / (before - after)
                        if reach < step:
                            step, block = reach, k
            if block >= 0:
                for i in range(N):
                    x[i] += step * (xs[i] - x[i])
                active[block] = True
                continue
            x[:] = xs
        held, drop = release, -1     # x = x*: release the half-plane held from outside the most
        for k in range(K):
            if active[k]:
                g = -b[k]
                for j in range(d):
                    g += n[k, j] * xs[k * d + j]
                if g > held:
                    held, drop = g, k
        if drop < 0:
            return r + 1
        active[drop] = False
    return 0

