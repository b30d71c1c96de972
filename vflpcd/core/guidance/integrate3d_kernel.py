"""The steps of eq. (xi_r) in 3-D (``GuidancePlanner3D._integrate``) as one plain loop to compile.

One step at xi_k = (x, y, z): the path's chi_P^ (``GuidanceField3D.path_unit``, the graph
path's splines by Horner's rule on their pieces), times the cup_Q_i of each obstacle whose reach
holds xi_k (the mover where it is at the step's time; its chi_R_i^ = gamma_i grad varphi_i x m_i -
k_r varphi_i grad varphi_i, made unit, added with weight 1 - cup), normalised; |chi_c| < epsilon
reuses the previous direction. gamma_i is decided at the first step inside R_i: the side rule's
gamma, flipped when its circulation runs against the path's tangent (cos < ``backwards``).

Arrays, all float64:

- ``start`` (3,); ``xyz`` (max_steps + 1, 3): xyz[0] the start, step k writes xyz[k + 1];
- ``obstacles`` (O, 20): per obstacle its ``ObstacleImplicit.row3d`` (centre x, y, z at the stamp,
  velocity x, y, z, stamp, squared reach, cos and sin of the yaw, axes a0, a1, a2, p, q, c), the
  side rule's gamma and the detour plane's normal m x, y, z; ``gammas`` (O,): the decided gamma_i,
  0.0 while undecided (written);
- ``frame`` (12,): the graph path's origin and its rotation R (row-major); ``knots`` (m,) and
  ``pieces`` (4, m - 1, 4): the breakpoints and the coefficients (highest power first) of f, f', g,
  g' (``GraphPath3D``);
- ``params`` (13,): k_p, k_r, l1, l2, epsilon, beta, x_end, max_steps, t0, speed, the path's
  abscissa limits x0, x1, and backwards; ``step_times`` (T,) (T = 0: none);
- ``out`` (2,): the points written (steps + 1) and the inherited steps.

Returns ``REACHED``, ``OUT_OF_STEPS`` or ``VANISHED`` (the field vanished at the start with no
heading to inherit). Run interpreted (where numba is missing) it is the same arithmetic, number for
number; compiled (``vflpcd.controllers.loops``) ``step_time``, ``cup_at`` and
``superellipsoid_at`` are compiled with it.
"""

from __future__ import annotations

import math

from vflpcd.core.guidance.integrate_kernel import OUT_OF_STEPS, REACHED, VANISHED, step_time
from vflpcd.core.guidance.primitives import cup_at, knot_interval, superellipsoid_at

__all__ = ["REACHED", "OUT_OF_STEPS", "VANISHED", "steps3d_loop", "piece_at"]


def piece_at(pieces, j: int, i: int, h: float) -> float:
    """Spline j's piece i (coefficients highest power first) at h, by Horner's rule."""
    out = 0.0
    for n in range(pieces.shape[2]):
        out = out * h + pieces[j, i, n]
    return out


def steps3d_loop(start, xyz, obstacles, gammas, frame, knots, pieces, params, step_times, out) -> int:
    """The steps from ``start`` until the progress reaches x_end or max_steps are taken (module
    docstring)."""
    k_p, k_r, l1, l2, epsilon, beta = params[0], params[1], params[2], params[3], params[4], params[5]
    x_end, max_steps, t0, speed = params[6], int(params[7]), params[8], params[9]
    x0, x1, backwards = params[10], params[11], params[12]
    ox, oy, oz = frame[0], frame[1], frame[2]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = (frame[3], frame[4], frame[5], frame[6], frame[7], frame[8],
                                                   frame[9], frame[10], frame[11])
    x, y, z = start[0], start[1], start[2]
    xyz[0, 0], xyz[0, 1], xyz[0, 2] = x, y, z
    have_prev, px_, py_, pz_ = False, 0.0, 0.0, 0.0
    inherited = 0
    for k in range(max_steps):
        t = step_time(k, t0, beta, speed, step_times)
        # the graph path at xi_k (GraphPath3D.value_grad)
        qx_ = x - ox
        qy_ = y - oy
        qz_ = z - oz
        qx = qx_ * r00 + qy_ * r10 + qz_ * r20
        qy = qx_ * r01 + qy_ * r11 + qz_ * r21
        qz = qx_ * r02 + qy_ * r12 + qz_ * r22
        xc = min(max(qx, x0), x1)
        i = knot_interval(knots, xc)
        h = xc - knots[i]
        f, df, g, dg = piece_at(pieces, 0, i, h), piece_at(pieces, 1, i, h), piece_at(pieces, 2, i, h), \
            piece_at(pieces, 3, i, h)
        f, g = f + df * (qx - xc), g + dg * (qx - xc)
        p1, p2 = qy - f, qz - g
        g1x, g1y, g1z = -df * r00 + r01, -df * r10 + r11, -df * r20 + r21
        g2x, g2y, g2z = -dg * r00 + r02, -dg * r10 + r12, -dg * r20 + r22
        P, Vx, Vy, Vz = 1.0, 0.0, 0.0, 0.0
        for n in range(obstacles.shape[0]):
            row = obstacles[n]
            dt = t - row[6]
            cx, cy, cz = row[0] + row[3] * dt, row[1] + row[4] * dt, row[2] + row[5] * dt
            if (x - cx) ** 2 + (y - cy) ** 2 + (z - cz) ** 2 > row[7]:
                continue
            phi, gx, gy, gz = superellipsoid_at(x, y, z, cx, cy, cz, row[8], row[9], row[10], row[11], row[12],
                                                row[13], row[14])
            gamma = gammas[n]
            if gamma == 0.0:
                if phi >= 0.0:
                    continue
                # chi_R_i^ with the side rule's gamma, against the path's tangent at xi_k's abscissa
                rx, ry, rz = _repulsive_unit(row[16], gx, gy, gz, phi, k_r, row[17], row[18], row[19])
                ta = min(max(qx_ * r00 + qy_ * r10 + qz_ * r20, x0), x1)
                j = knot_interval(knots, ta)
                ht = ta - knots[j]
                s1, s2 = piece_at(pieces, 1, j, ht), piece_at(pieces, 3, j, ht)
                tx, ty, tz = r00 + r01 * s1 + r02 * s2, r10 + r11 * s1 + r12 * s2, r20 + r21 * s1 + r22 * s2
                tn = math.sqrt(tx * tx + ty * ty + tz * tz)
                along = rx * (tx / tn) + ry * (ty / tn) + rz * (tz / tn)
                gamma = -row[16] if along < backwards else row[16]
                gammas[n] = gamma
            rx, ry, rz = _repulsive_unit(gamma, gx, gy, gz, phi, k_r, row[17], row[18], row[19])
            cup = cup_at(phi, row[15], l1, l2)
            P *= cup
            Vx, Vy, Vz = Vx + (1.0 - cup) * rx, Vy + (1.0 - cup) * ry, Vz + (1.0 - cup) * rz
        # chi_P^ = unit(grad phi_1 x grad phi_2 - k_p phi_1 grad phi_1 - k_p phi_2 grad phi_2)
        ax, ay, az = g1y * g2z - g1z * g2y, g1z * g2x - g1x * g2z, g1x * g2y - g1y * g2x
        ux, uy, uz = _unit3(ax, ay, az, -k_p * p1 * g1x - k_p * p2 * g2x, -k_p * p1 * g1y - k_p * p2 * g2y,
                            -k_p * p1 * g1z - k_p * p2 * g2z)
        cx_, cy_, cz_ = P * ux + Vx, P * uy + Vy, P * uz + Vz
        norm = math.sqrt(cx_ * cx_ + cy_ * cy_ + cz_ * cz_)
        if norm < epsilon:  # the paper's rule at singular points
            if not have_prev:
                out[0], out[1] = k + 1, inherited
                return VANISHED
            inherited += 1
        else:
            px_, py_, pz_ = cx_ / norm, cy_ / norm, cz_ / norm
            have_prev = True
        x, y, z = x + beta * px_, y + beta * py_, z + beta * pz_
        xyz[k + 1, 0], xyz[k + 1, 1], xyz[k + 1, 2] = x, y, z
        if (x - ox) * r00 + (y - oy) * r10 + (z - oz) * r20 >= x_end:
            out[0], out[1] = k + 2, inherited
            return REACHED
    out[0], out[1] = max_steps + 1, inherited
    return OUT_OF_STEPS


def _repulsive_unit(gamma: float, gx: float, gy: float, gz: float, phi: float, k_r: float,
                    mx: float, my: float, mz: float):
    """chi_R_i^ = unit(gamma grad varphi x m - k_r varphi grad varphi) (``GuidanceField3D.repulsive_unit``)."""
    k = k_r * phi
    return _unit3(gamma * (gy * mz - gz * my), gamma * (gz * mx - gx * mz), gamma * (gx * my - gy * mx),
                  -k * gx, -k * gy, -k * gz)


def _unit3(ax: float, ay: float, az: float, bx: float, by: float, bz: float):
    """(a + b) / |a + b|; the zero vector stays zero."""
    x, y, z = ax + bx, ay + by, az + bz
    n = math.sqrt(x * x + y * y + z * z)
    if n > 0.0:
        return x / n, y / n, z / n
    return 0.0, 0.0, 0.0
