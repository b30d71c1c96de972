"""Two steps of ``error_model.ErrorModel``'s tick as loops to compile (the numpy path gives the same
numbers to 1e-12, tests/unit/core/control/test_tick_kernel.py):

* ``window_loop``: the tick's window, the robot's state and the N + 1 reference states, taken into
  the robot's frame (``lifted.window_in_place``: planar, with the heading unwrapped along the
  window as ``np.unwrap`` does, or position-only) and normalised for the encoder in float32
  ((x - x_mean) / x_std, ``KoopmanModel.normalise_state``);
* ``window_lift_loop``: ``window_loop`` and the deep Koopman lift of the window, Upsilon = [x, rho_e(x_n), 1]
  (rows, n_K), by ``encoder_kernel.encoder_loop`` (``KoopmanModel.lift``, the same bits);
* ``linearisation_loop``: the nominal linearisation (``ErrorModel._linearisation``):
  u_r,tau = pinv(B_x) (x_r,tau+1 - [A Upsilon_r,tau]_{1..n_x}) clipped into [u_min, u_max], and
  next_tau = A Upsilon_r,tau + B u_r,tau;
* ``command_loop``: the tick's command (``tick_horizon.clipped_command``), u = u_r,0 + u~_0 clipped into the
  magnitude limits and then within du_max of the previous command, with numpy's maximum and
  minimum (a NaN stays NaN).

A loop compiler (numba's ``njit``: ``vflpcd.controllers.loops``) turns each into one machine-code
function, in place of some twenty numpy calls whose fixed cost dominated these small arrays; run
as Python they are slow.
"""

from __future__ import annotations

import math

import numpy as np

from vflpcd.core.dynamics.encoder_kernel import encoder_loop
from vflpcd.core.loop_algebra import matvec

KIND_NONE, KIND_POSITION, KIND_PLANAR = 0, 1, 2


def window_loop(state, reference, kind, position, heading, x_mean, x_std, window, normalised):
    T, n_x = reference.shape[0] + 1, state.shape[0]
    for c in range(n_x):
        window[0, c] = state[c]
    for r in range(1, T):
        for c in range(n_x):
            window[r, c] = reference[r - 1, c]
    if kind == KIND_PLANAR:
        h, i, j = heading, position[0], position[1]
        jump = False
        for r in range(1, T):
            if not abs(window[r, h] - window[r - 1, h]) < math.pi:
                jump = True
        if jump:                        # np.unwrap: each step taken into [-pi, pi), its correction summed
            correction = 0.0
            prev = window[0, h]
            for r in range(1, T):
                d = window[r, h] - prev
                prev = window[r, h]
                m = (d + math.pi) % (2.0 * math.pi) - math.pi
                if m == -math.pi and d > 0.0:
                    m = math.pi
                if abs(d) >= math.pi:
                    correction += m - d
                window[r, h] = window[r, h] + correction
        psi0 = window[0, h]
        co, si = math.cos(psi0), math.sin(psi0)
        x0, y0 = window[0, i], window[0, j]
        for r in range(T):
            dx, dy = window[r, i] - x0, window[r, j] - y0
            window[r, i] = co * dx + si * dy
            window[r, j] = co * dy - si * dx
            window[r, h] = window[r, h] - psi0
    elif kind == KIND_POSITION:
        for c in position:
            p0 = window[0, c]
            for r in range(T):
                window[r, c] = window[r, c] - p0
    for r in range(T):
        for c in range(n_x):
            normalised[r, c] = (window[r, c] - x_mean[c]) / x_std[c]


def window_lift_loop(state, reference, kind, position, heading, x_mean, x_std, window, normalised,
                     weights, biases, dims, work, U):
    window_loop(state, reference, kind, position, heading, x_mean, x_std, window, normalised)
    n_x, n_K = window.shape[1], U.shape[1]
    for r in range(window.shape[0]):
        for c in range(n_x):
            U[r, c] = window[r, c]
        U[r, n_K - 1] = 1.0
    encoder_loop(normalised, weights, biases, dims, work, U, n_x)


def linearisation_loop(U_r, A, B, B_x_pinv, n_x, u_min, u_max):
    N, n_K, n_u = U_r.shape[0] - 1, A.shape[0], B.shape[1]
    u_r = np.empty((N, n_u))
    nxt = np.empty((N, n_K))
    for k in range(N):
        matvec(A, U_r[k], nxt[k])
        for a in range(n_u):
            acc = 0.0
            for i in range(n_x):
                acc += (U_r[k + 1, i] - nxt[k, i]) * B_x_pinv[a, i]
            u_r[k, a] = min(max(acc, u_min[a]), u_max[a])
        for i in range(n_K):
            acc = 0.0
            for a in range(n_u):
                acc += u_r[k, a] * B[i, a]
            nxt[k, i] += acc
    return u_r, nxt


def command_loop(u_ref0, u_tilde0, u_min, u_max, u_prev, du_max):
    n_u = u_ref0.shape[0]
    u = np.empty(n_u)
    for j in range(n_u):
        v = u_ref0[j] + u_tilde0[j]
        for lo, hi in ((u_min[j], u_max[j]), (u_prev[j] - du_max[j], u_prev[j] + du_max[j])):
            if not (v >= lo or v != v):
                v = lo
            if not (v <= hi or v != v):
                v = hi
        u[j] = v
    return u
