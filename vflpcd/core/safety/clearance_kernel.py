"""The safety supervisor's clearance tests as loops to compile (``Supervisor`` runs them when it is
given them; its numpy paths give the same numbers to 1e-12 and the same obstacles and decisions,
tests/unit/core/safety/test_clearance_kernel.py).

``within_reach_loop`` is ``Supervisor._within_reach``'s pre-filter (``ObstacleArrays.gap_bound``
less each obstacle's own motion, against the manoeuvre's reach). ``clearances_loop`` takes the
body's poses along a manoeuvre and ``ObstacleArrays``' two arrays, and returns the least signed
distance of the body's covering discs to the static obstacles and to the movers, each with the
obstacle's row that sets it: the operations of ``_clearances``,
``ObstacleArrays.signed_distance`` and ``ObstacleArrays._box`` in their order, one pose, disc and
obstacle at a time, in place of the (obstacles, poses, discs, d) temporaries whose fixed cost
dominated a tick. It knows the closed forms only (round and box shapes, ``ObstacleArrays.closed``);
the supervisor keeps its numpy path for the others.

A loop compiler (numba's ``njit``: ``vflpcd.controllers.loops``) turns each into one machine-code
function; run as Python they are slow.
"""

from __future__ import annotations

import math

from vflpcd.core.safety.obstacle_arrays import ROUND     # ObstacleArrays' form code of a round shape


def clearances_loop(pos, yaw, times, offsets, motion, shape, heading, statics, movers, behind, middle, reach,
                    release):
    """pos (K, d), yaw (K,), times (K,) absolute: the body's poses; offsets (n,): its discs along
    (cos yaw, sin yaw); motion (M, 2d + 1), shape (M, 4 + d): ``ObstacleArrays``' rows; heading
    (K, d): the direction of travel at each pose (read for the movers when not ``behind``);
    ``statics``/``movers``: whether to test the obstacles at rest / in motion; ``middle``: the body's
    middle ahead of its reference point (m); a mover whose bounding circle lies ``reach`` +
    ``release`` (m) or more from a pose leaves it free. Returns (static gap, its row, mover gap,
    its row): the least signed distance of a disc centre (the disc's radius not taken off), inf and
    -1 where none counts."""
    K, d = pos.shape
    n = offsets.shape[0]
    M = motion.shape[0]
    s_best, s_row = math.inf, -1
    m_best, m_row = math.inf, -1
    for m in range(M):
        moving = False
        for j in range(d):
            if motion[m, d + j] != 0.0:
                moving = True
        if (moving and not movers) or (not moving and not statics):
            continue
        least = math.inf
        for k in range(K):
            sx, sy, sz = 0.0, 0.0, 0.0
            if moving:
                dt = times[k] - motion[m, 2 * d]
                sx, sy = motion[m, d] * dt, motion[m, d + 1] * dt
                rx, ry = pos[k, 0] - motion[m, 0] - sx, pos[k, 1] - motion[m, 1] - sy
                r2 = rx * rx + ry * ry
                rz = 0.0
                if d == 3:
                    sz = motion[m, d + 2] * dt
                    rz = pos[k, 2] - motion[m, 2] - sz
                    r2 += rz * rz
                if not math.sqrt(r2) < shape[m, 0] + reach + release:
                    continue
                if not behind:
                    hx, hy = heading[k, 0], heading[k, 1]
                    vx, vy = motion[m, d], motion[m, d + 1]
                    along = vx * hx + vy * hy
                    speed2 = vx * vx + vy * vy
                    ahead = (rx + middle * hx) * hx + (ry + middle * hy) * hy
                    if d == 3:
                        hz, vz = heading[k, 2], motion[m, d + 2]
                        along += vz * hz
                        speed2 += vz * vz
                        ahead += (rz + middle * hz) * hz
                    if not (ahead < 0.0 or speed2 - along * along > along * along):
                        continue
            c, s = math.cos(yaw[k]), math.sin(yaw[k])
            for i in range(n):
                x = (pos[k, 0] + offsets[i] * c - sx) - motion[m, 0]
                y = (pos[k, 1] + offsets[i] * s - sy) - motion[m, 1]
                z = 0.0
                if d == 3:
                    z = (pos[k, 2] - sz) - motion[m, 2]
                gap = _signed_distance(x, y, z, shape, m, d)
                if gap < least:
                    least = gap
        if moving:
            if least < m_best:
                m_best, m_row = least, m
        elif least < s_best:
            s_best, s_row = least, m
    return s_best, s_row, m_best, m_row


def within_reach_loop(p, motion, shape, t_now, t_end, limit, out):
    """out (M,) bool: whether obstacle m may come within ``limit`` (m) of the point p (d,) between
    t_now and t_end (s): the larger of its bounding-circle and oriented-box distance from p at its
    stamp, less the distance its speed covers from the stamp to the farther of the two times."""
    d = p.shape[0]
    for m in range(motion.shape[0]):
        x, y = p[0] - motion[m, 0], p[1] - motion[m, 1]
        r2 = x * x + y * y
        v2 = motion[m, d] * motion[m, d] + motion[m, d + 1] * motion[m, d + 1]
        z = 0.0
        if d == 3:
            z = p[2] - motion[m, 2]
            r2 += z * z
            v2 += motion[m, d + 2] * motion[m, d + 2]
        gap = max(math.sqrt(r2) - shape[m, 0], _box_distance(x, y, z, shape, m, d))
        stamp = motion[m, 2 * d]
        travel = math.sqrt(v2) * max(abs(t_end - stamp), abs(t_now - stamp))
        out[m] = gap - travel <= limit


def _signed_distance(x, y, z, shape, m, d):
    """``ObstacleArrays.signed_distance`` of the offset (x, y[, z]) from obstacle m's centre."""
    if shape[m, 3] == ROUND:
        r2 = x * x + y * y
        if d == 3:
            r2 += z * z
        return math.sqrt(r2) - shape[m, 0]
    return _box_distance(x, y, z, shape, m, d)


def _box_distance(x, y, z, shape, m, d):
    """``ObstacleArrays._box``: the signed distance of the offset (x, y[, z]) from obstacle m's centre
    to its oriented bounding box."""
    co, si = shape[m, 1], shape[m, 2]
    qx = abs(co * x + si * y) - shape[m, 4]
    qy = abs(co * y - si * x) - shape[m, 5]
    inside = max(qx, qy)
    outside = max(qx, 0.0) ** 2 + max(qy, 0.0) ** 2
    if d == 3:
        qz = abs(z) - shape[m, 6]
        inside = max(inside, qz)
        outside += max(qz, 0.0) ** 2
    return math.sqrt(outside) + min(inside, 0.0)
