"""A threat's safety points and normals in the tick's window frame as one loop to compile, for the
shapes whose signed distance has a closed form (``Shape.closed_form``: "round", a circle or a sphere;
"box", a rectangle or a cuboid): ``barrier.safety_points`` (the obstacle taken at each step's time
by its constant velocity, the nearest point of its boundary grown by ``grow`` and the outward normal
there, ``Shape.distance_and_normal``) followed by ``ErrorModel.to_window`` of both. The numpy path
gives the same numbers to 1e-12 (tests/unit/core/control/test_barrier_kernel.py); it serves every
other shape.
"""

from __future__ import annotations

import math

import numpy as np

from vflpcd.core.control.tick_kernel import KIND_PLANAR, KIND_POSITION

FORM_ROUND, FORM_BOX = 1, 2
FORMS = {"round": FORM_ROUND, "box": FORM_BOX}      # Shape.closed_form -> the loop's code


def safety_points_loop(form, size, center, yaw, velocity, stamp, points, times, grow, kind, position, heading,
                       origin, x_p, normal):
    """form: ``FORMS``' code; size: the radius (1,) of a round shape, the half extents (d,) of a box;
    center (d,), yaw, velocity (d,), stamp: the obstacle (``ObstacleState``); points (T, d) world
    positions taken at times (T,); kind, position, heading: the window's ``PoseLayout`` (``_KINDS``'
    code), origin: the tick's world state; x_p, normal (T, d): written."""
    T, d = points.shape
    cy, sy = math.cos(yaw), math.sin(yaw)
    p = np.empty(d)
    n = np.empty(d)
    for t in range(T):
        dt = times[t] - stamp
        for j in range(d):                           # the obstacle at rest at its stamped pose, in its body frame
            p[j] = (points[t, j] - velocity[j] * dt) - center[j]
        bx = cy * p[0] + sy * p[1]
        by = -sy * p[0] + cy * p[1]
        p[0], p[1] = bx, by
        if form == FORM_ROUND:
            r = math.sqrt(p[0] * p[0] + p[1] * p[1]) if d == 2 else math.sqrt(p[0] * p[0] + p[1] * p[1] + p[2] * p[2])
            sd = r - size[0]
            for j in range(d):
                n[j] = p[j] / r if r > 1e-12 else (1.0 if j == 0 else 0.0)
        else:
            r2 = 0.0
            inner = -np.inf
            face = 0
            for j in range(d):
                q = abs(p[j]) - size[j]
                if q > inner:
                    inner, face = q, j
                if q > 0.0:
                    r2 += q * q
                n[j] = q                            # kept for the outside case below
            r = math.sqrt(r2)
            sd = r + min(inner, 0.0)
            for j in range(d):
                out = n[j] if n[j] > 0.0 else 0.0
                unit = out / r if r > 0.0 else (1.0 if j == face else 0.0)
                n[j] = -unit if p[j] < 0.0 else unit
        wx = cy * n[0] - sy * n[1]                   # the normal back in the world frame
        wy = sy * n[0] + cy * n[1]
        n[0], n[1] = wx, wy
        for j in range(d):
            x_p[t, j] = points[t, j] - (sd - grow) * n[j]
            normal[t, j] = n[j]
    if kind == KIND_PLANAR or kind == KIND_POSITION:
        for t in range(T):
            for j in range(position.shape[0]):
                x_p[t, j] = x_p[t, j] - origin[position[j]]
    if kind == KIND_PLANAR:
        c, s = math.cos(origin[heading]), math.sin(origin[heading])
        for a in (x_p, normal):
            for t in range(T):
                u, v = a[t, 0], a[t, 1]
                a[t, 0] = c * u + s * v
                a[t, 1] = -s * u + c * v
