"""The composite guiding vector fields of the paper, vectorised over points (N, 2).

Path-following and repulsive fields (section II-A):
    chi_P   = gamma_0 E grad phi   - k_p    phi   grad phi
    chi_R_i = gamma_i E grad varphi_i - k_r_i varphi_i grad varphi_i
Smooth bump functions (section II-A), per obstacle with repulsive level c < 0:
    f1 = exp(l1 / (c - varphi)) if varphi > c else 0,   f2 = exp(l2 / varphi) if varphi < 0 else 0,
    cup_Q = f1 / (f1 + f2),  cap_R = f2 / (f1 + f2)
computed as a logistic function of log f1 - log f2 so that nothing overflows.
Composite field, eq. (eq_yaocvf):
    chi = (prod_i cup_Q_i) chi_P^ + sum_i cap_R_i chi_R_i^
Kinodynamic composite field, eq. (guiding_vector_dynamic_constraint), with virtual obstacles I':
    chi_c = (prod_{I \\ I'} cup_Q_i  prod_{I'} s_i) chi_P^ + sum_{I \\ I'} cap_R_i chi_R_i^ + sum_{I'} (1 - s_i) chi_R_i^
with s_i of eq. (S_xi): exp(k_c / (c_i - varphi_i)) in the buffer region
M_b = ex R_actl ∩ in R_vrtl, 1 elsewhere (and 0 on Q_vrtl and inside it, its limit).
"""

from __future__ import annotations

import math

import numpy as np

E = np.array([[0.0, -1.0], [1.0, 0.0]])  # rotation by +90 deg


def bump(varphi: np.ndarray, c: float, l1: float, l2: float) -> tuple[np.ndarray, np.ndarray]:
    """(cup_Q, cap_R) for values varphi (N,): 1/0 outside R, 0/1 inside Q, smooth in between."""
    varphi = np.asarray(varphi, float)
    cup = np.where(varphi >= 0.0, 1.0, 0.0)
    mid = (varphi > c) & (varphi < 0.0)
    if np.any(mid):
        v = varphi[mid]
        z = l1 / (c - v) - l2 / v  # log f1 - log f2
        cup[mid] = 0.5 * (1.0 + np.tanh(0.5 * z))  # logistic(z), stable for any z
    return cup, 1.0 - cup


def cup_at(varphi: float, c: float, l1: float, l2: float) -> float:
    """``bump``'s cup_Q at one value, in plain floats (cap_R = 1 - cup_Q)."""
    if varphi >= 0.0:
        return 1.0
    if varphi <= c:
        return 0.0
    return 0.5 * (1.0 + math.tanh(0.5 * (l1 / (c - varphi) - l2 / varphi)))


def guiding_at(gamma: float, k: float, phi: float, gx: float, gy: float) -> tuple[float, float]:
    """``guiding`` at one point in plain floats: gamma E grad phi - k phi grad phi."""
    return -gamma * gy - k * phi * gx, gamma * gx - k * phi * gy


def superellipse_at(x, y, cx, cy, c, s, ax0, ax1, p):
    """(varphi, d varphi / dx, d varphi / dy) of the superellipse centred at (cx, cy), yaw (cos c,
    sin s), axes ax0, ax1, exponent p, at (x, y): ``ObstacleImplicit.value_grad`` at one planar
    point in plain floats (the compiled loops' form; ``row_centre`` places a row's centre)."""
    zx = ((x - cx) * c + (y - cy) * s) / ax0
    zy = (-(x - cx) * s + (y - cy) * c) / ax1
    ax, ay = abs(zx), abs(zy)
    S = ax ** p + ay ** p
    coef = max(S, 1e-300) ** (1.0 / p - 1.0)
    hx = coef * math.copysign(ax ** (p - 1.0), zx) / ax0 if zx != 0.0 else 0.0
    hy = coef * math.copysign(ay ** (p - 1.0), zy) / ax1 if zy != 0.0 else 0.0
    return S ** (1.0 / p) - 1.0, hx * c - hy * s, hx * s + hy * c


def superellipsoid_at(x, y, z, cx, cy, cz, c, s, a0, a1, a2, p, q):
    """(varphi, its gradient's x, y, z) of the superellipsoid centred at (cx, cy, cz), yaw (cos c,
    sin s) about z, axes a0, a1, a2, exponents p (horizontal) and q, at (x, y, z):
    ``ObstacleImplicit.value_grad`` at one 3-D point in plain floats (the 3-D steps,
    ``integrate3d_kernel``)."""
    dx, dy = x - cx, y - cy
    z0, z1 = (dx * c + dy * s) / a0, (-dx * s + dy * c) / a1
    z2 = (z - cz) / a2
    b0, b1, b2 = abs(z0), abs(z1), abs(z2)
    S = b0 ** p + b1 ** p
    T = S ** (q / p) + b2 ** q
    tq = max(T, 1e-300) ** (1.0 / q - 1.0)
    sq = max(S, 1e-300) ** (q / p - 1.0)
    h0 = tq * sq * math.copysign(b0 ** (p - 1.0), z0) / a0 if z0 != 0.0 else 0.0
    h1 = tq * sq * math.copysign(b1 ** (p - 1.0), z1) / a1 if z1 != 0.0 else 0.0
    h2 = tq * math.copysign(b2 ** (q - 1.0), z2) / a2 if z2 != 0.0 else 0.0
    return T ** (1.0 / q) - 1.0, h0 * c - h1 * s, h0 * s + h1 * c, h2


def knot_interval(knots, x: float) -> int:
    """The spline piece holding x (clamped to the knots (m,)): ``bisect_right(knots, x) - 1`` within
    [0, m - 2], in plain ints (the compiled loops' form: the path grid's fill, the 3-D steps)."""
    lo, hi = 0, len(knots)
    while lo < hi:
        mid = (lo + hi) // 2
        if x < knots[mid]:
            hi = mid
        else:
            lo = mid + 1
    return min(max(lo - 1, 0), len(knots) - 2)


def row_centre(rows, i: int, t: float) -> tuple[float, float]:
    """The centre at time t of obstacle i of ``rows`` (each an ``ObstacleImplicit.row``)."""
    return rows[i, 0] + rows[i, 2] * (t - rows[i, 4]), rows[i, 1] + rows[i, 3] * (t - rows[i, 4])


def guiding(gamma: float, k: float, phi: np.ndarray, grad: np.ndarray) -> np.ndarray:
    """gamma E grad phi - k phi grad phi for phi (N,), grad (N, 2): the chi_P / chi_R_i form."""
    return gamma * (grad @ E.T) - k * phi[:, None] * grad


def unit(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v / |v|, |v|) row-wise for v (N, d); rows of zero norm stay zero."""
    n = np.linalg.norm(v, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(n[:, None] > 0.0, v / n[:, None], 0.0)
    return u, n


def s_virtual(varphi_v: np.ndarray, c_v: float, k_c: float, in_buffer: np.ndarray) -> np.ndarray:
    """s_i of eq. (S_xi) for a virtual obstacle: values varphi_v (N,), buffer-region mask (N,)."""
    varphi_v = np.asarray(varphi_v, float)
    s = np.ones_like(varphi_v)
    above = in_buffer & (varphi_v > c_v)
    s[above] = np.exp(k_c / (c_v - varphi_v[above]))
    s[in_buffer & (varphi_v <= c_v)] = 0.0
    return s
