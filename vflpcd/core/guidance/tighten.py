"""Tight paths: the planned path pulled back onto the reference path as far as the body's clearance
to the obstacles lets it.

The field's integral keeps out of the reactive regions' turn-in band and its repulsive regions are
conservative fits of the grown shapes (a box grown by 1.75 m gets a superellipse reaching 0.4 m
further at its sides), so a car on the field's path passes a parked car with 0.8-1.2 m to spare
and a lateral error the metric squares. The field decides *how* to pass (the side of every
obstacle, behind or ahead of a mover); this step decides *how close*: the path, resampled at
spacing h, is replaced by the minimiser of

    J(x) = (h / l)^4 sum_k |e_k|^2 + sum_k |e_{k-1} - 2 e_k + e_{k+1}|^2,   e_k = x_k - g_k

(g_k the reference path's point nearest the field's k-th point, l the stiffness length: the
longer, the gentler the detour; the bending is that of the offset from the reference path, so a
bend of the path costs nothing and a stiff detour still follows it) subject to every covering disc
of the body keeping its ``Keepout``'s clearance from each obstacle's exact shape, a moving one
taken where it is when the point is reached (and, as further keepouts, some time before and after:
the planner's window for the mover's uncertain timing), with the start and its heading (and the
goal) kept.

The body is its covering discs (``vflpcd.core.footprint``): disc j of radius r sits o_j along the
body's axis t_k from x_k (the path's tangent, turned out of the road's bend by the car's slip angle:
``Body.axes``). The signed distance of a convex shape is convex, so with n its
gradient at the disc centre c = x_k + o_j t_k the half-plane n'x_k >= n'x_k^0 + r + clearance -
sd(c) (t_k and the linearisation point x_k^0 held) keeps that disc clear: one supporting
half-plane per point and keepout, the most binding one kept, re-taken at the new points for a few
outer rounds (``fairing.solve_active_set`` solves each convex problem). Where the field's path
itself comes closer than the clearance (it starts at a robot that came close, it grazes a mover
as its timed check allows), the tight path comes no closer than it does. Points whose discs are
farther than ``REACH`` beyond every clearance are free. l starts at the configured length and
doubles until the peak curvature is within kappa_max and every disc keeps the clearance (to
``CLEAR_TOLERANCE``); when none does up to ``STIFFER`` times the length there is no tight path and
the field's path stands (it is safe; it is only wider).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vflpcd.core.guidance.fairing import FAIR_MIN, OUTER_ROUNDS, SPACING, resample, solve_active_set
from vflpcd.core.guidance.speed import arc_lengths, heading_curvature, menger_curvature
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import unit_differences

REACH = 2.0             # m: a disc this much farther than the clearance from a shape leaves its point free
CLEAR_TOLERANCE = 0.02  # m the final discs may sit inside the clearance (the tangent moves between rounds)
STIFFER = 4.0           # l is doubled up to this many times the configured length (a stiffer detour reaches
                        # ever farther along the path: past it the field's own path is the better one)


@dataclass(frozen=True)
class Body:
    """The robot as covering discs: centres ``offsets`` (n,) m along its heading from the
    reference point, each of ``radius`` m. ``rear_axle``: how far the axle that does not steer lies
    behind the reference point (a car's CoG to its rear axle, lr; 0: the heading is the path's
    tangent), ``slip_gain`` K (s^2/m) how the tyres' slip takes that lever down with the speed v.
    A car whose reference point follows a bend of curvature kappa is yawed out of the bend by its
    steady slip angle beta = asin(kappa (lr - K v^2)) (the linear single-track model,
    K = m lf / (C_r L) with C_r the rear axle's cornering stiffness; K = 0 is the kinematic
    bicycle), so its front swings out of the bend and its rear in: 0.25 m at the SUV's front bumper
    on a 15 m ring at 5 m/s."""

    offsets: np.ndarray
    radius: float
    rear_axle: float = 0.0
    slip_gain: float = 0.0

    @property
    def slips(self) -> bool:
        """Whether the body's axis turns in a bend (a car with a rear axle behind its reference point)."""
        return self.rear_axle > 0.0

    def slip_angle(self, kappa, speed) -> np.ndarray:
        """The steady slip angle beta = asin(kappa (lr - K v^2)) (rad; the lever lr - K v^2 held at 0
        or above) of a car whose reference point drives a curvature kappa (1/m, left positive) at
        speed v (m/s): its velocity points beta to the left of its heading (0 for a body that does
        not slip)."""
        lever = np.maximum(self.rear_axle - self.slip_gain * np.asarray(speed, float) ** 2, 0.0)
        return np.arcsin(np.clip(lever * np.asarray(kappa, float), -1.0, 1.0))

    def axes(self, x: np.ndarray, bend: np.ndarray | None = None, speed: np.ndarray | None = None) -> np.ndarray:
        """Unit body axes (K, d) at the points x (K, d) of a path the reference point follows: the
        path's tangents, turned by -beta in the plane where ``bend`` (K,) gives the curvature kappa
        of the road's bend at each point and ``speed`` (K,) the speed there (None: 0) (None: the
        tangents). The road's bend, not the path's own: a swerve past an obstacle lasts too short
        for the slip to build up (with the path's own curvature the tight detours of the road suite
        came out 0.05-0.25 m wider than the cars' measured clearances needed), a ring or a bend is
        driven at its steady slip."""
        t = unit_differences(x)
        if bend is None or not self.slips or x.shape[1] != 2 or not np.any(bend):
            return t
        beta = self.slip_angle(bend, 0.0 if speed is None else speed)
        c, s = np.cos(beta), np.sin(beta)
        return np.column_stack([c * t[:, 0] + s * t[:, 1], -s * t[:, 0] + c * t[:, 1]])


@dataclass(frozen=True)
class Keepout:
    """An obstacle's shape that every disc must clear by ``clearance`` m; a moving one where it is
    ``shift`` s after the time each point is reached (constant velocity)."""

    obstacle: ObstacleState
    clearance: float
    shift: float = 0.0


def _near(k: Keepout, body: Body, x: np.ndarray, centres: np.ndarray, beyond: float) -> np.ndarray:
    """Whether some disc of the body at each of the points x (K, d) may come within ``beyond`` m of
    k's clearance (by the shape's bounding circle), k's shape centred at ``centres`` (K, d) (K,):
    the signed distances at the other points are never needed."""
    far = float(np.max(np.abs(body.offsets))) + body.radius + k.clearance + beyond + k.obstacle.shape.bounding_radius()
    return np.einsum("ij,ij->i", d := x - centres, d) <= far * far


def _disc_distances(keepouts: Sequence[Keepout], body: Body, x: np.ndarray, axes: np.ndarray, times: np.ndarray,
                    beyond: float, normals: bool) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Every disc's signed distance to every keepout's shape at the points x (K, d) with body axes
    ``axes`` (K, d), reached at ``times`` (K,): (near (M, K) the ``_near`` masks for ``beyond``,
    sd (M, J, K) with +inf where a point is not near, and with ``normals`` their unit gradients
    (M, J, K, d) in the world frame, else None). The keepouts of one shape are evaluated in one
    call of the shape's distance (the same numbers as ``Shape.signed_distance`` and
    ``distance_and_normal`` one keepout at a time): a road with 40 posts and 8 walkers in
    three time shifts asks for 64 of them at every outer round."""
    M, K, d = len(keepouts), len(x), x.shape[1]
    J = len(body.offsets)
    discs = x[None] + body.offsets[:, None, None] * axes[None]             # (J, K, d) disc centres, disc by disc
    near = np.zeros((M, K), dtype=bool)
    sd = np.full((M, J, K), np.inf)
    grad = np.zeros((M, J, K, d)) if normals else None
    groups: dict[object, list[int]] = {}
    for m, k in enumerate(keepouts):
        groups.setdefault(k.obstacle.shape, []).append(m)
    for shape, members in groups.items():
        ks = [keepouts[m] for m in members]
        obs = [k.obstacle for k in ks]
        shift, stamp = np.array([k.shift for k in ks])[:, None], np.array([o.stamp for o in obs])[:, None]
        travel = (times[None, :] + shift - stamp)[..., None] * np.array([o.velocity for o in obs])[:, None, :]
        center = np.array([o.center for o in obs])                             # (G, d)
        mask = np.stack([_near(k, body, x, center[g] + travel[g], beyond) for g, k in enumerate(ks)])
        near[members] = mask
        if not mask.any():
            continue
        gi, ji, ki = np.nonzero(np.broadcast_to(mask[:, None, :], (len(ks), J, K)))   # the near (keepout, disc, point)s
        cy = np.array([math.cos(float(o.yaw)) for o in obs])[gi]
        sy = np.array([math.sin(float(o.yaw)) for o in obs])[gi]
        rel = (discs[ji, ki] - travel[gi, ki]) - center[gi]                 # (P, d): ``Shape._to_body``
        body_pts = rel.copy()
        body_pts[:, 0] = cy * rel[:, 0] + sy * rel[:, 1]
        body_pts[:, 1] = -sy * rel[:, 0] + cy * rel[:, 1]
        rows = np.asarray(members)[gi]
        if normals:
            dist, n = shape._sd_normal_body(body_pts)
            world = n.copy()
            world[:, 0] = cy * n[:, 0] - sy * n[:, 1]
            world[:, 1] = sy * n[:, 0] + cy * n[:, 1]
            grad[rows, ji, ki] = world
        else:
            dist = shape._sd_body(body_pts)
        sd[rows, ji, ki] = dist
    return near, sd, grad


def disc_gaps(x: np.ndarray, body: Body, keepouts: Sequence[Keepout], times: np.ndarray | None = None,
              bend: np.ndarray | None = None, speed: np.ndarray | None = None) -> np.ndarray:
    """Per point of x (K, d), reached at ``times`` (K,) (only moving keepouts need them), the least
    sd(disc centre) - radius - clearance over the discs and keepouts (K,): negative where a disc is
    closer than the clearance. A keepout whose shape's bounding circle keeps every disc of a point
    beyond the clearance is not evaluated there (its gap is positive); +inf where none is.
    ``bend``, ``speed``: the road's curvature and the speed at each point (``Body.axes``)."""
    if not keepouts:
        return np.full(len(x), np.inf)
    times = np.zeros(len(x)) if times is None else times
    near, sd, _ = _disc_distances(keepouts, body, x, body.axes(x, bend, speed), times, 0.0, normals=False)
    clearance = np.array([k.clearance for k in keepouts])[:, None]
    gap = np.where(near, sd.min(axis=1) - body.radius - clearance, np.inf)
    return gap.min(axis=0)


def body_half_planes(x: np.ndarray, times: np.ndarray, body: Body, keepouts: Sequence[Keepout],
                     slack: np.ndarray | float = 0.0, bend: np.ndarray | None = None,
                     speed: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per point the most binding disc half-plane n_k' x >= b_k (module docstring) for the
    clearances less ``slack`` (K,) m, (n (K, d), b (K,)); n_k = 0, b_k = -inf where every disc is
    farther than ``REACH`` beyond its clearance. ``bend``, ``speed``: the road's curvature and the
    speed at each point (``Body.axes``). The most binding disc of a keepout is its first of equals,
    the most binding keepout the first of equals in ``keepouts``' order."""
    n = np.zeros_like(x)
    b = np.full(len(x), -np.inf)
    if not keepouts:
        return n, b
    slack = np.broadcast_to(np.asarray(slack, float), (len(x),))
    near, sd, grad = _disc_distances(keepouts, body, x, body.axes(x, bend, speed), times, REACH, normals=True)
    reserve = np.array([body.radius + k.clearance for k in keepouts])[:, None, None]
    want = reserve - slack[None, None, :] - sd                # (M, J, K): how far each disc must move out
    disc = np.argmax(want, axis=1)                            # (M, K) the most binding disc of each keepout
    best = np.take_along_axis(want, disc[:, None, :], axis=1)[:, 0, :]
    best = np.where(near, best, -np.inf)
    keep = np.argmax(best, axis=0)                            # (K,) the most binding keepout
    cols = np.arange(len(x))
    want_k = best[keep, cols]
    rows = np.flatnonzero(want_k > -REACH)
    g = grad[keep[rows], disc[keep[rows], rows], rows]
    n[rows] = g
    b[rows] = np.einsum("ij,ij->i", g, x[rows]) + want_k[rows]
    return n, b


def tighten_path(xy: np.ndarray, times: np.ndarray, anchor: Callable[[np.ndarray], np.ndarray], kappa_max: float,
                 body: Body, keepouts: Sequence[Keepout], length: float, heading: np.ndarray | None = None,
                 pin_end: bool = False, field_times: np.ndarray | None = None,
                 loop=None) -> tuple[np.ndarray, np.ndarray] | None:
    """The tight path of xy (K, d), reached at times (K,) (module docstring): (points, their times)
    resampled at ``SPACING``, or None when no stiffness up to ``STIFFER`` x length gives one within
    kappa_max that keeps the clearances. ``anchor`` maps points to the reference path's nearest
    points; moving keepouts are taken where they are when each point is reached (at ``times``; the
    field's own path, whose closeness the tight path may match, at ``field_times``, default times);
    ``loop``: ``fairing.solve_active_set``'s."""
    if len(xy) < 7 or not length > 0:
        return None
    r, t = resample(xy, times, SPACING)
    if heading is not None:  # the second point keeps the start heading
        r[1] = r[0] + SPACING * np.asarray(heading, float) / np.linalg.norm(heading)
    road = anchor(r)
    bend, speed = (heading_curvature(road), _speeds(r, t)) if body.slips else (None, None)   # Body.axes
    t_field = t if field_times is None else resample(xy, field_times, SPACING)[1]
    slack = -np.minimum(disc_gaps(r, body, keepouts, t_field, bend, speed), 0.0)   # where the field's path comes closer, no closer
    fair = max(float(length), FAIR_MIN)
    while fair <= STIFFER * max(float(length), FAIR_MIN) * (1 + 1e-9):
        eps = (SPACING / fair) ** 4
        x, active = r, None
        for _ in range(OUTER_ROUNDS + 1):
            n, b = body_half_planes(x, t, body, keepouts, slack, bend, speed)
            x, active = solve_active_set(road, eps, n, b, pin_end, active, shape=road, pins=r, loop=loop)
        clear = np.all(disc_gaps(x, body, keepouts, t, bend, speed)[2:] + slack[2:] > -CLEAR_TOLERANCE)
        if clear and np.max(menger_curvature(x)) <= kappa_max:
            return x, t
        fair *= 2.0
    return None


def _speeds(x: np.ndarray, times: np.ndarray) -> np.ndarray:
    """The speed (K,) at the points x (K, d) reached at times (K,): the chords over the time steps
    (0 where the time does not advance)."""
    if len(x) < 2:
        return np.zeros(len(x))
    ds = np.diff(arc_lengths(x))
    dt = np.diff(times)
    v = np.where(dt > 0.0, ds / np.where(dt > 0.0, dt, 1.0), 0.0)
    return np.concatenate([v[:1], 0.5 * (v[:-1] + v[1:]), v[-1:]])
