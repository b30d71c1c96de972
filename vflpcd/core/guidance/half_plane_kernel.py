"""The fairing's supporting half-planes (``fairing.half_planes``) and its clear check
(``fairing.regions_clear``) for planar superellipse regions, as plain loops to compile.

Per point x_k reached at t_k, among the regions whose reactive region holds it (varphi_i < 0,
within the reach of the centre then), the one it is deepest in relative to Q_i (varphi_i / c_i
largest, the first on ties): Newton along the gradient from x_k to varphi_i = ``clear_level`` c_i
(at most ``newton`` steps, ended when the miss is within ``tol``), and the half-plane through
that point q with the unit gradient there as its normal, n_k' x >= n_k' q.

``rows`` (R, 12): per region its centre x, y at the stamp, velocity x, y, stamp, squared reach,
cos and sin of the yaw, the two axes, p and c (``ObstacleImplicit``). ``n`` (K, 2) and ``b`` (K,)
are written: n_k = 0, b_k = -inf where no region holds x_k. ``primitives``' ``superellipse_at`` and
``row_centre`` are compiled with it (``vflpcd.controllers.loops``); ``fairing.half_planes`` is the same on numpy.
"""

from __future__ import annotations

import math

from vflpcd.core.guidance.primitives import row_centre, superellipse_at


def half_planes_loop(x, t, rows, clear_level, newton, tol, n, b):
    """The half-planes above for points x (K, 2) reached at t (K,)."""
    for k in range(x.shape[0]):
        n[k, 0], n[k, 1], b[k] = 0.0, 0.0, -math.inf
        worst = math.inf
        for i in range(rows.shape[0]):
            cx, cy = row_centre(rows, i, t[k])
            if (x[k, 0] - cx) ** 2 + (x[k, 1] - cy) ** 2 >= rows[i, 5]:
                continue
            cos, sin, ax0, ax1, p, c = rows[i, 6], rows[i, 7], rows[i, 8], rows[i, 9], rows[i, 10], rows[i, 11]
            v = superellipse_at(x[k, 0], x[k, 1], cx, cy, cos, sin, ax0, ax1, p)[0]
            if not (v < 0.0 and v / c < worst):
                continue
            qx, qy = x[k, 0], x[k, 1]
            for step in range(newton + 1):
                vq, gx, gy = superellipse_at(qx, qy, cx, cy, cos, sin, ax0, ax1, p)
                miss = clear_level * c - vq
                if step == newton or abs(miss) <= tol:
                    break
                s = miss / max(gx * gx + gy * gy, 1e-12)
                qx, qy = qx + s * gx, qy + s * gy
            norm = max(math.hypot(gx, gy), 1e-12)
            n[k, 0], n[k, 1] = gx / norm, gy / norm
            b[k] = n[k, 0] * qx + n[k, 1] * qy
            worst = v / c


def clear_loop(x, t, rows, first, last, eased, scale):
    """Whether every point x_k (K, 2) reached at t_k, first <= k < last and not ``eased[k]``, lies
    above the level ``scale`` c_i of every region (varphi_i > scale c_i where it is within the reach
    of the centre then; beyond the reach varphi_i = +inf; scale 1: outside every repulsive region
    Q_i), stopped at the first point that is not: ``fairing.regions_clear`` and the planner's
    ``reaches_any``."""
    for k in range(first, last):
        if eased[k]:
            continue
        for i in range(rows.shape[0]):
            cx, cy = row_centre(rows, i, t[k])
            if (x[k, 0] - cx) ** 2 + (x[k, 1] - cy) ** 2 >= rows[i, 5]:
                continue
            v = superellipse_at(x[k, 0], x[k, 1], cx, cy, rows[i, 6], rows[i, 7], rows[i, 8], rows[i, 9], rows[i, 10])[0]
            if not v > scale * rows[i, 11]:
                return False
    return True
