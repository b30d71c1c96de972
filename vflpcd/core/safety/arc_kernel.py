"""The ground supervisor's predicted manoeuvre as a loop to compile (``GroundSupervisor._poses_moving``
runs it when it is given it; its numpy path gives the same numbers to 1e-12,
tests/unit/core/safety/test_clearance_kernel.py).

``arcs_loop`` samples the two arcs of a kinematic-bicycle manoeuvre (``supervisor._arc_into`` and
``supervisor._time_at`` at each sample, in their order of operations): n samples every ds m, the
first n1 on the arc of curvature k1 driven from speed v0 at a1 for up to t1 s, the rest on the arc
of curvature k2 from its end, driven from v1 at a2 for up to t2 s. A loop compiler (numba's
``njit``: ``vflpcd.controllers.loops``) turns it into machine code; run as Python it is slow.
"""

from __future__ import annotations

import math

# below this |kappa s| an arc is taken as its chord along the mean heading (error s (kappa s)^2 / 24,
# under 1e-8 m for s <= 40 m); above it the closed form loses at most ~1e-10 m to cancellation
STRAIGHT = 1e-4


def arcs_loop(X, Y, course, psi, k1, k2, s1, ds, n1, v0, a1, t1, v1, a2, t2, pos, yaw, times):
    """Write the n = len(yaw) samples into pos (n, 2), yaw (n,) and times (n,) (s from now): the
    reference point leaves (X, Y) along ``course``, the body's yaw starts at psi."""
    n = yaw.shape[0]
    last = (n1 - 1) * ds
    for i in range(n1):
        s = i * ds
        pos[i, 0], pos[i, 1] = arc_point(X, Y, course, k1, s, last)
        yaw[i] = psi + k1 * s
        times[i] = _time_at(s, v0, a1, t1)
    if n1 < n:
        Xb, Yb = arc_point(X, Y, course, k1, s1, s1)
        cb = course + k1 * s1
        last = (n - 1) * ds - s1
        for i in range(n1, n):
            s = i * ds - s1
            pos[i, 0], pos[i, 1] = arc_point(Xb, Yb, cb, k2, s, last)
            yaw[i] = psi + k1 * s1 + k2 * s
            times[i] = t1 + _time_at(s, v1, a2, t2)


def arc_point(x, y, heading, kappa, s, last):
    """The point s m along the arc of curvature kappa from (x, y, heading), taken as its chord along
    the mean heading when |kappa last| < STRAIGHT (``last``: the arc's last sample, which decides
    for all of them, as ``supervisor._arc_into`` does; s itself for a single point)."""
    if abs(kappa * last) < STRAIGHT:
        mid = heading + 0.5 * kappa * s
        return x + s * math.cos(mid), y + s * math.sin(mid)
    end = heading + kappa * s
    return x + (math.sin(end) - math.sin(heading)) / kappa, y - (math.cos(end) - math.cos(heading)) / kappa


def _time_at(s, v0, a, t_max):
    """``supervisor._time_at`` of one distance s."""
    if abs(a) > 1e-9:
        t = (-v0 + math.sqrt(max(v0 * v0 + 2.0 * a * s, 0.0))) / a
    else:
        t = s / max(v0, 1e-9)
    return min(t, t_max)
