"""The pursuer-evader region E_p that switches the barrier on (paper section III-C, Fig. fig_game).

Frame: the evader (the robot) at the origin, its velocity along +Y; X = Y rotated by -90 deg
(to the evader's right). A pursuer (an obstacle) at zeta = [X_e, Y_e] in that frame is a threat
when zeta lies in

    E_p = E_p1 ∩ E_p2,   E_p1 = { ||zeta|| <= l + l_safe },   E_p2 = H1 ∪ H2 ∪ H3,
    H1 = { X_e <= -l sin s_bar,  Y_e >= tan(s_bar) X_e + l / cos(s_bar) }
    H2 = { X_e >=  l sin s_bar,  Y_e >= -tan(s_bar) X_e + l / cos(s_bar) }
    H3 = { -l sin s_bar < X_e < l sin s_bar,  Y_e >= -sqrt(l^2 - X_e^2) }

with the boundary of the usable part s_bar = arccos(-v_p / v_e) in (pi/2, pi] (Exarchos et al.
2015), l the safety distance and l_safe the margin. The H1/H2 inequalities are evaluated
multiplied by cos(s_bar) < 0, i.e. Y_e cos s_bar -/+ X_e sin s_bar <= l, which stays finite at
s_bar = pi/2 (a static pursuer: E_p2 becomes the strip |X_e| <= l ahead of the evader's lower
terminal semicircle). A pursuer at least as fast as the evader (v_p >= v_e, the arccos argument
leaves [-1, 1]) gets s_bar = pi: E_p2 is then the half-plane Y_e >= -l. An evader at rest
(v_e ~ 0) has no velocity frame; every pursuer inside E_p1 then counts as a threat.
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.norms import row_norms, vector_norm

V_EVADER_MIN = 1e-3  # m/s: below this the evader has no velocity frame


def bup_angle(v_p, v_e) -> np.ndarray:
    """s_bar = arccos(-v_p / v_e) in [pi/2, pi]; v_p (K,) pursuer speeds, v_e evader speed >= 0.
    A pursuer as fast as or faster than the evader (or an evader at rest) gives pi."""
    v_p = np.abs(np.asarray(v_p, float))
    if not v_e > V_EVADER_MIN:
        return np.arccos(np.full_like(v_p, -1.0))
    return np.arccos(-np.minimum(np.maximum(v_p / float(v_e), 0.0), 1.0))


def in_region(zeta: np.ndarray, l: np.ndarray, l_safe: float, s_bar: np.ndarray) -> np.ndarray:
    """Membership of E_p for pursuers at zeta (K, 2) in the evader frame, safety distances l (K,)
    (or scalar), margin l_safe and BUP angles s_bar (K,) (or scalar). Returns (K,) bool."""
    zeta = np.atleast_2d(np.asarray(zeta, float))
    X, Y = zeta[:, 0], zeta[:, 1]
    l, s_bar = _per_pursuer(l, X.shape), _per_pursuer(s_bar, X.shape)
    sin_s, cos_s = np.sin(s_bar), np.cos(s_bar)
    l_sin, y_cos, x_sin = l * sin_s, Y * cos_s, X * sin_s
    e1 = np.hypot(X, Y) <= l + l_safe
    h1 = (X <= -l_sin) & (y_cos - x_sin <= l)
    h2 = (X >= l_sin) & (y_cos + x_sin <= l)
    inner = np.abs(X) < l_sin
    h3 = inner & (Y >= -np.sqrt(np.maximum(l * l - X * X, 0.0)))
    return e1 & (h1 | h2 | h3)


def _per_pursuer(value, shape: tuple[int, ...]) -> np.ndarray:
    """A scalar or per-pursuer value as an array of ``shape`` (K,) (a view when it is one already)."""
    value = np.asarray(value, float)
    return value if value.shape == shape else np.broadcast_to(value, shape)


def evader_frame(relative: np.ndarray, evader_velocity: np.ndarray) -> np.ndarray:
    """Pursuer positions relative to the evader, (K, d) world (d = 2 or 3), -> zeta (K, 2) in the
    evader frame: Y_e along the evader velocity (d,), X_e >= 0 the distance off that axis. E_p is
    mirror-symmetric in X_e (H1 and H2 mirror each other), so the side is not needed, and the same
    (X_e, Y_e) serves the planar and the 3-D robot (E_p rotated about the velocity axis)."""
    v = np.asarray(evader_velocity, float)
    rel = np.atleast_2d(np.asarray(relative, float))
    speed = vector_norm(v)
    ey = v / speed if speed > V_EVADER_MIN else np.eye(len(v))[1]
    zeta = np.empty((len(rel), 2))
    zeta[:, 1] = Y = rel @ ey
    zeta[:, 0] = row_norms(rel - Y[:, None] * ey[None, :])
    return zeta


def threats(robot_position: np.ndarray, robot_velocity: np.ndarray, centers: np.ndarray,
            velocities: np.ndarray, l: np.ndarray, l_safe: float) -> np.ndarray:
    """Which pursuers are in E_p: robot position/velocity (d,) world, pursuer centres and
    velocities (K, d) world, safety distances l (K,). Returns (K,) bool."""
    centers = np.atleast_2d(np.asarray(centers, float))
    if centers.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    relative = centers - np.asarray(robot_position, float)
    l = np.asarray(l, float)
    near = row_norms(relative) <= l + l_safe            # E_p1 (||zeta|| is the distance): most ticks none is
    if not near.any():
        return near
    robot_velocity = np.asarray(robot_velocity, float)
    v_e = vector_norm(robot_velocity)
    zeta = evader_frame(relative, robot_velocity)
    if v_e <= V_EVADER_MIN:
        return near
    s_bar = bup_angle(row_norms(np.atleast_2d(np.asarray(velocities, float))), v_e)
    return in_region(zeta, l, l_safe, s_bar)
