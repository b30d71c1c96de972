"""Joining a late replan to the robot (the splice).

A replan is planned from the robot's state when it was asked for (time t_j) and installed between
two ticks some latency later (t_now). As planned, its reference at t_now is where the robot would
be had it driven the new plan since t_j; usually it nearly is (it kept driving its old plan at
about that speed). When it is not, when the robot stopped at the end of its old plan while a
loaded computer's worker planned, or was braked meanwhile, the reference at t_now lies far ahead
of it, and the horizon problem would chase it.

The splice keeps the new path and times it again as if it had been planned at t_now from the
robot: from the path's first point at or after the robot's projection onto it (at most one path
step ahead), with the robot's speed as the speed plan's start (section III-A: the forward and
backward passes again), passed at t_now. The path's points, and so its curvature, are the plan's
own. A re-timed plan that would meet a moving obstacle's repulsive region at its new times is
``None``: the caller keeps the plan's own timing, which is clear of them.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from vflpcd.core.guidance.speed import plan_speed
from vflpcd.core.guidance.trajectory import timed_trajectory


@dataclass(frozen=True)
class SpeedLimits:
    """The speed plan's limits: desired speed, lateral acceleration, longitudinal accel / decel."""

    v_desired: float
    a_lat_max: float
    a_accel: float
    a_decel: float


def nearest_on_polyline(xy: np.ndarray, point: np.ndarray) -> tuple[int, float, float]:
    """The point of the polyline xy (K, d) nearest ``point`` (d,): (segment k, fraction f in
    [0, 1] along xy[k] -> xy[k + 1], distance)."""
    a, d = xy[:-1], np.diff(xy, axis=0)
    dd = (d * d).sum(axis=1)
    f = np.clip(((point - a) * d).sum(axis=1) / np.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
    gap = a + f[:, None] * d - point
    dist2 = (gap * gap).sum(axis=1)
    k = int(np.argmin(dist2))
    return k, float(f[k]), float(np.sqrt(dist2[k]))


def splice(plan, anchor: np.ndarray, v_anchor: float, t_now: float, dt: float, limits: SpeedLimits,
           moving_values=None):
    """``plan`` (a ``GuidancePlan``) re-timed to start at ``anchor`` (d,), the robot, at ``t_now`` at
    speed ``v_anchor`` (module docstring); ``moving_values(pos (M, d), t (M,))`` gives, for each
    moving obstacle the plan was made around, (values, c): None when a re-timed point has value
    <= c (the re-timing would meet it). A plan with fewer than three points ahead of the anchor
    is returned as it is."""
    xy = plan.xy
    k, _, _ = nearest_on_polyline(xy, np.asarray(anchor, float))
    pts = xy[k + 1:]
    if len(pts) < 3:
        return plan
    v_end = 0.0 if plan.v[-1] <= 1e-9 else None
    s, kappa, v = plan_speed(pts, limits.v_desired, limits.a_lat_max, limits.a_accel, limits.a_decel,
                             max(float(v_anchor), 0.0), v_end=v_end)
    trajectory = timed_trajectory(pts, s, v, t_now, dt)
    if moving_values is not None:
        for values, c in moving_values(trajectory.pos, trajectory.t):
            if np.any(values <= c):
                return None
    return replace(plan, trajectory=trajectory, xy=pts, s=s, kappa=kappa, v=v)
