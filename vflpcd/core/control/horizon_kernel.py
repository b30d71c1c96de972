"""The tick's work after the lift as one loop to compile: ``VFLPC``'s horizon problem, its solve and
the command, in one call (``tick_horizon.CompiledHorizon``).

``horizon_command_loop`` runs, in order and with the numpy path's operations:

* the nominal linearisation (``tick_kernel.linearisation_loop``: u_r,tau and the next lifted
  states), corrected by the GP's mean when ``corrected`` (``gp_kernel.corrected_next_loop``);
* the error model's c_tau = [next_tau - Upsilon_r,tau+1]_{1..n} and x~_0 = [Upsilon - Upsilon_r,0]_{1..n}
  (``error_model.ErrorModel.problem``);
* with ``increments``, the increment form's fill (``rate_kernel.increment_loop``: its c_z, z0 and
  the bounds lo, hi, written into the arrays given);
* Eb-RHRL's iterations (``ebrhrl_kernel.solve_loop``, on the increment form or the problem itself;
  ``A_cl`` is the solver's A - B K of that form);
* the command u = u_r,0 + u~_0 clipped into the limits (``tick_kernel.command_loop``), with
  u~_0 = u~_{-1} + v_0 in the increment form (``rate.RateForm.deviation``), the first target otherwise.

It returns (u, targets, iterations, max epsilon_a, max epsilon_c, saturated steps); whether the
solve is kept (its divergence test, the light weights' saturation) is the controller's, which then
uses u or throws it away. Each step is the function the calls one by one run, so the numbers are
theirs (tests/unit/core/control/test_tick_horizon.py, in closed loop).

Why one call: after the daemon's 10 ms sleep every distinct call of a tick pays for what the
machine let go cold meanwhile, about 12 us per compiled call on this machine against some 2 us
back to back (docs/results.md, "One compiled call after the lift"); five calls and the Python
between them become one. Run as Python it is slow: the controller uses it compiled only.
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.control.ebrhrl_kernel import solve_loop
from vflpcd.core.control.rate_kernel import increment_loop
from vflpcd.core.control.tick_kernel import command_loop, linearisation_loop
from vflpcd.core.dynamics.gp_kernel import corrected_next_loop


def horizon_command_loop(U, U_r, A, B, B_x_pinv, n_x, u_min, u_max, u_prev, du_max,
                         corrected, z_index, Zm, sf2, nh_inv_ell2, alpha, B_d,
                         increments, B_N, commanded, c_z, x0_z, lo, hi,
                         A_cl, B_s, K, Q, R2, P, M_inv, gamma, W_a, W_c, fa, fb, fh,
                         pos_index, p_ref, x_p, normal, mu, length, eta_a, i_max, tol, phi_floor, bounded):
    u_r, nxt = linearisation_loop(U_r, A, B, B_x_pinv, n_x, u_min, u_max)
    if corrected:
        nxt = corrected_next_loop(nxt, U_r[:-1], u_r, z_index, Zm, sf2, nh_inv_ell2, alpha, B_d)
    N, n, n_u = nxt.shape[0], nxt.shape[1] - 1, u_r.shape[1]
    c = np.empty((N, n))
    x0 = np.empty(n)
    for k in range(N):
        for i in range(n):
            c[k, i] = nxt[k, i] - U_r[k + 1, i]
    for i in range(n):
        x0[i] = U[i] - U_r[0, i]
    c_s, x0_s = c, x0                   # the problem the solver sees: the increment form's, or its own
    if increments:
        increment_loop(c, B_N, u_r, x0, u_prev, du_max, commanded, c_z, x0_z, lo, hi)
        c_s, x0_s = c_z, x0_z
    target, iterations, eps_a, eps_c, saturated = solve_loop(
        A_cl, B_s, c_s, x0_s, K, Q, R2, P, M_inv, gamma, W_a, W_c, fa, fb, fh, pos_index, p_ref, x_p, normal,
        mu, length, eta_a, i_max, tol, phi_floor, bounded, lo, hi)
    u_tilde0 = np.empty(n_u)
    for j in range(n_u):
        u_tilde0[j] = x0_s[n + j] + target[0, j] if increments else target[0, j]
    u = command_loop(u_r[0], u_tilde0, u_min, u_max, u_prev, du_max)
    return u, target, iterations, eps_a, eps_c, saturated
