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

The maths is written per pursuer, in floats (``*_at``): a tick asks about a handful of movers,
and on one pursuer the same steps on numpy arrays took 44 us, most of it numpy's cost per call.
The array functions apply them row by row.
"""

from __future__ import annotations

import math
import operator

import numpy as np

V_EVADER_MIN = 1e-3  # m/s: below this the evader has no velocity frame


def bup_angle_at(v_p: float, v_e: float) -> float:
    """s_bar = arccos(-v_p / v_e) in [pi/2, pi] of one pursuer at speed |v_p| and the evader at
    speed v_e >= 0. A pursuer as fast as or faster than the evader (or an evader at rest) gives pi."""
    if not v_e > V_EVADER_MIN:
        return math.pi
    return math.acos(-min(max(abs(v_p) / v_e, 0.0), 1.0))


def bup_angle(v_p, v_e) -> np.ndarray:
    """``bup_angle_at`` of pursuer speeds v_p (K,) (or a scalar)."""
    v_p = np.asarray(v_p, float)
    return np.array([bup_angle_at(v, float(v_e)) for v in v_p.ravel().tolist()]).reshape(v_p.shape)


def in_region_at(X: float, Y: float, l: float, l_safe: float, s_bar: float) -> bool:
    """Whether a pursuer at (X_e, Y_e) in the evader frame lies in E_p, for safety distance l,
    margin l_safe and BUP angle s_bar (module docstring)."""
    if math.hypot(X, Y) > l + l_safe:                                   # E_p1
        return False
    sin_s, cos_s = math.sin(s_bar), math.cos(s_bar)
    l_sin, y_cos, x_sin = l * sin_s, Y * cos_s, X * sin_s
    if X <= -l_sin and y_cos - x_sin <= l:                              # H1
        return True
    if X >= l_sin and y_cos + x_sin <= l:                               # H2
        return True
    return abs(X) < l_sin and Y >= -math.sqrt(max(l * l - X * X, 0.0))  # H3


def in_region(zeta: np.ndarray, l, l_safe: float, s_bar) -> np.ndarray:
    """Membership of E_p for pursuers at zeta (K, 2) in the evader frame, safety distances l (K,)
    (or scalar), margin l_safe and BUP angles s_bar (K,) (or scalar). Returns (K,) bool."""
    zeta = np.atleast_2d(np.asarray(zeta, float))
    K = len(zeta)
    l = np.broadcast_to(np.asarray(l, float), (K,)).tolist()
    s_bar = np.broadcast_to(np.asarray(s_bar, float), (K,)).tolist()
    return np.array([in_region_at(X, Y, l[k], float(l_safe), s_bar[k]) for k, (X, Y) in enumerate(zeta.tolist())],
                    dtype=bool)


def evader_frame_at(relative: list[float], evader_velocity: list[float]) -> tuple[float, float]:
    """A pursuer's position relative to the evader (d,) world (d = 2 or 3) -> (X_e, Y_e) in the
    evader frame: Y_e along the evader velocity (d,), X_e >= 0 the distance off that axis. E_p is
    mirror-symmetric in X_e (H1 and H2 mirror each other), so the side is not needed, and the same
    (X_e, Y_e) serves the planar and the 3-D robot (E_p rotated about the velocity axis)."""
    speed = math.hypot(*evader_velocity)
    if speed > V_EVADER_MIN:
        ey = [v / speed for v in evader_velocity]
    else:
        ey = [0.0, 1.0, 0.0][: len(evader_velocity)]
    Y = sum(map(operator.mul, relative, ey))
    return math.hypot(*[r - Y * e for r, e in zip(relative, ey)]), Y


def evader_frame(relative: np.ndarray, evader_velocity: np.ndarray) -> np.ndarray:
    """``evader_frame_at`` of pursuer positions relative to the evader (K, d): zeta (K, 2)."""
    v = np.asarray(evader_velocity, float).tolist()
    rel = np.atleast_2d(np.asarray(relative, float))
    return np.array([evader_frame_at(r, v) for r in rel.tolist()]).reshape(len(rel), 2)


def threat_at(relative: list[float], evader_velocity: list[float], v_e: float, v_p: float, l: float,
              l_safe: float) -> bool:
    """Whether one pursuer is in E_p: its position relative to the evader (d,) world, the evader's
    velocity (d,) world and speed v_e, the pursuer's speed v_p, safety distance l, margin l_safe."""
    if math.hypot(*relative) > l + l_safe:                           # E_p1 (||zeta|| is the distance)
        return False
    if v_e <= V_EVADER_MIN:                   # no velocity frame: inside E_p1 is a threat
        return True
    X, Y = evader_frame_at(relative, evader_velocity)
    return in_region_at(X, Y, l, l_safe, bup_angle_at(v_p, v_e))


def threats(robot_position: np.ndarray, robot_velocity: np.ndarray, centers: np.ndarray,
            velocities: np.ndarray, l: np.ndarray, l_safe: float) -> np.ndarray:
    """``threat_at`` of pursuers: robot position/velocity (d,) world, pursuer centres and velocities
    (K, d) world, safety distances l (K,) (or scalar). Returns (K,) bool."""
    position = np.asarray(robot_position, float)
    centers = np.asarray(centers, float).reshape(-1, len(position))
    K = centers.shape[0]
    relative = (centers - position).tolist()
    l = np.broadcast_to(np.asarray(l, float), (K,)).tolist()
    vel = np.asarray(robot_velocity, float).tolist()
    v_e = math.hypot(*vel)
    v_p = np.asarray(velocities, float).reshape(K, -1).tolist()
    return np.array([threat_at(relative[k], vel, v_e, math.hypot(*v_p[k]), l[k], l_safe)
                     for k in range(K)], dtype=bool)
