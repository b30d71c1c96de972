"""The path's unit field chi_P^ on a block of grid cells (``grid.PathGrid.fill``), as a plain loop
to compile: ``GuidanceField.path_unit`` of a ``GraphPath`` at every cell (xs[i], ys[j]).

In the graph's local frame (origin o, rotation R: local = (p - o) R) the path is y' = f(x'), a
cubic spline (breakpoints ``breaks`` (n + 1,), coefficients ``coefs`` (4, n), highest power first,
as scipy's ``CubicSpline.c``), continued linearly beyond its ends; phi = y' - f(x'), grad phi =
R (-f'(x'), 1), and chi_P = gamma_0 E grad phi - k_p phi grad phi (``primitives.guiding_at``; the piece by
``primitives.knot_interval``; both compiled with it by ``vflpcd.controllers.loops``), normalised (a zero vector stays zero). ``out`` (len(xs),
len(ys), 2) is written.
"""

from __future__ import annotations

import math

from vflpcd.core.guidance.primitives import guiding_at, knot_interval


def fill_loop(xs, ys, origin, rot, breaks, coefs, gamma0, k_p, out):
    """chi_P^ at the cells of xs x ys into out."""
    x0, x1 = breaks[0], breaks[breaks.shape[0] - 1]
    for i in range(xs.shape[0]):
        px = xs[i] - origin[0]
        for j in range(ys.shape[0]):
            py = ys[j] - origin[1]
            qx = px * rot[0, 0] + py * rot[1, 0]
            qy = px * rot[0, 1] + py * rot[1, 1]
            xc = min(max(qx, x0), x1)
            k = knot_interval(breaks, xc)
            d = xc - breaks[k]
            c0, c1, c2, c3 = coefs[0, k], coefs[1, k], coefs[2, k], coefs[3, k]
            df = (3.0 * c0 * d + 2.0 * c1) * d + c2
            f = ((c0 * d + c1) * d + c2) * d + c3 + df * (qx - xc)
            gx = -df * rot[0, 0] + rot[0, 1]
            gy = -df * rot[1, 0] + rot[1, 1]
            vx, vy = guiding_at(gamma0, k_p, qy - f, gx, gy)
            norm = math.sqrt(vx * vx + vy * vy)
            if norm > 0.0:
                out[i, j, 0], out[i, j, 1] = vx / norm, vy / norm
            else:
                out[i, j, 0], out[i, j, 1] = 0.0, 0.0
