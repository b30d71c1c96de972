"""Tight paths: the planned path pulled back onto the reference path as far as the body's clearance
to the obstacles lets it.

The field's integral keeps out of the reactive regions' turn-in band and its repulsive regions are
conservative fits of the grown shapes (a box grown by 1.75 m gets a superellipse reaching 0.4 m
further at its sides), so a car on the field's path passes a parked car with 0.8-1.2 m to spare
and a lateral error the metric squares. The field decides *how* to pass (the side of every
obstacle, behind or ahead of a mover); this step decides *how close*: the path, resampled at
spacing h, is replaced by the minimiser of

    J(x) = (h / l)^4 sum_k |x_k - a_k|^2 + sum_k |e_{k-1} - 2 e_k + e_{k+1}|^2,   e_k = x_k - g_k

(g_k the reference path's point nearest the field's k-th point, a_k = g_k but beside movers
(below), l the stiffness length: the longer, the gentler the detour; the bending is that of the
offset from the reference path, so a bend of the path costs nothing and a stiff detour still
follows it) subject to the body keeping ``clearance`` from every static obstacle's exact
shape, and staying out of every moving obstacle's repulsive region Q_i (its margin covers the
motion's uncertainty), with the start and its heading (and the goal) kept. Where the field's path
lies in a mover's reactive region (at the time it is reached) a_k is the field's own point: the
room the field leaves to pass a mover is kept, as the mover may not keep to its prediction (and
where the field's path grazes Q_i, as its timed check allows, the tight path stays on it).

The body is its covering discs (``vflpcd.core.footprint``): disc j of radius r sits o_j along the
path's tangent t_k from x_k. The signed distance of a convex shape is convex, so with n its
gradient at the disc centre c = x_k + o_j t_k the half-plane n'x_k >= n'x_k^0 + r + clearance -
sd(c) (t_k and the linearisation point x_k^0 held) keeps that disc clear: one supporting
half-plane per point and obstacle, the most binding one kept, re-taken at the new points for a
few outer rounds (``fairing.solve_active_set`` solves each convex problem). Where the field's
path itself comes closer than the clearance (it starts at a robot that came close), the tight
path comes no closer than it does. Points whose discs are
farther than ``REACH`` from every shape are free. l starts at the configured length and doubles
until the peak curvature is within kappa_max and every disc keeps the clearance (to
``CLEAR_TOLERANCE``); when none does up to ``STIFFER`` times the length there is no tight path and
the field's path stands (it is safe; it is only wider).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vflpcd.core.guidance.fairing import FAIR_MIN, OUTER_ROUNDS, SPACING, Region, half_planes, \
    resample, solve_active_set
from vflpcd.core.guidance.speed import menger_curvature
from vflpcd.core.obstacles import ObstacleState

REACH = 2.0             # m: a disc this much farther than the clearance from a shape leaves its point free
CLEAR_TOLERANCE = 0.02  # m the final discs may sit inside the clearance (the tangent moves between rounds)
MOVER_LEVEL = 0.97      # the movers' half-planes touch varphi_i = MOVER_LEVEL c_i: on the edge of Q_i
FD_STEP = 1e-4          # m: central differences of the signed distance
STIFFER = 4.0           # l is doubled up to this many times the configured length (a stiffer detour reaches
                        # ever farther along the path: past it the field's own path is the better one)


@dataclass(frozen=True)
class Body:
    """The robot as covering discs: centres ``offsets`` (n,) m along its heading from the
    reference point, each of ``radius`` m."""

    offsets: np.ndarray
    radius: float


@dataclass(frozen=True)
class Keepout:
    """A static obstacle's shape that every disc must clear by ``clearance`` m."""

    obstacle: ObstacleState
    clearance: float


def _tangents(x: np.ndarray) -> np.ndarray:
    """Unit tangents (K, d) of the polyline x by central differences (one-sided at the ends)."""
    g = np.gradient(x, axis=0)
    return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-12)


def _sd_grad(o: ObstacleState, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance of pts (M, d) to o's shape and its unit gradient (central differences)."""
    sd = o.signed_distance(pts)
    d = pts.shape[1]
    grad = np.empty_like(pts)
    for j in range(d):
        e = np.zeros(d)
        e[j] = FD_STEP
        grad[:, j] = (o.signed_distance(pts + e) - o.signed_distance(pts - e)) / (2 * FD_STEP)
    grad /= np.maximum(np.linalg.norm(grad, axis=1, keepdims=True), 1e-12)
    return sd, grad


def disc_gaps(x: np.ndarray, body: Body, keepouts: Sequence[Keepout]) -> np.ndarray:
    """Per point the least sd(disc centre) - radius - clearance over the discs and keepouts (K,)
    (+inf without keepouts): negative where a disc is closer than the clearance."""
    t = _tangents(x)
    gap = np.full(len(x), np.inf)
    for k in keepouts:
        for o_j in body.offsets:
            sd = k.obstacle.signed_distance(x + o_j * t)
            gap = np.minimum(gap, sd - body.radius - k.clearance)
    return gap


def body_half_planes(x: np.ndarray, body: Body, keepouts: Sequence[Keepout],
                     slack: np.ndarray | float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Per point the most binding disc half-plane n_k' x >= b_k (module docstring) for the
    clearances less ``slack`` (K,) m, (n (K, d), b (K,)); n_k = 0, b_k = -inf where every disc is
    farther than ``REACH`` beyond its clearance."""
    t = _tangents(x)
    n = np.zeros_like(x)
    b = np.full(len(x), -np.inf)
    need = np.full(len(x), -np.inf)          # b_k - n_k' x_k: how far the point must move along n_k
    for k in keepouts:
        for o_j in body.offsets:
            c = x + o_j * t
            sd, g = _sd_grad(k.obstacle, c)
            want = body.radius + k.clearance - slack - sd
            near = (want > -REACH) & (want > need)
            need[near] = want[near]
            n[near] = g[near]
            b[near] = np.einsum("ij,ij->i", g[near], x[near]) + want[near]
    return n, b


def _merged(x, t, body, keepouts, movers, slack, grazed):
    """The disc half-planes and the movers' Q_i half-planes (not at the ``grazed`` points), per
    point the one that asks more."""
    n, b = body_half_planes(x, body, keepouts, slack)
    if movers:
        n_m, b_m = half_planes(x, t, movers, MOVER_LEVEL)
        more = np.isfinite(b_m) & ~grazed & (b_m - np.einsum("ij,ij->i", n_m, x) > b - np.einsum("ij,ij->i", n, x))
        n[more], b[more] = n_m[more], b_m[more]
    return n, b


def tighten_path(xy: np.ndarray, times: np.ndarray, anchor: Callable[[np.ndarray], np.ndarray], kappa_max: float,
                 body: Body, keepouts: Sequence[Keepout], movers: Sequence[Region], length: float,
                 heading: np.ndarray | None = None, pin_end: bool = False) -> tuple[np.ndarray, np.ndarray] | None:
    """The tight path of xy (K, d), reached at times (K,) (module docstring): (points, their times)
    resampled at ``SPACING``, or None when no stiffness up to ``STIFFER`` x length gives one within kappa_max
    that keeps the clearances. ``anchor`` maps points to the reference path's points at their
    progress; ``movers``: the moving obstacles' repulsive regions at the points' times."""
    if len(xy) < 7 or not length > 0:
        return None
    r, t = resample(xy, times, SPACING)
    if heading is not None:  # the second point keeps the start heading
        r[1] = r[0] + SPACING * np.asarray(heading, float) / np.linalg.norm(heading)
    road = anchor(r)
    a = road.copy()
    slack = -np.minimum(disc_gaps(r, body, keepouts), 0.0)   # where the field's path is closer, no closer than it
    grazed = np.zeros(len(r), bool)     # points where the field's path grazes a mover's Q_i: it stays there
    for m in movers:          # beside a mover the field's path stays: its reactive band is the room to pass it
        v = m.value_grad(r, t)[0]
        a[v < 0.0] = r[v < 0.0]
        grazed |= v <= MOVER_LEVEL * m.c
    fair = max(float(length), FAIR_MIN)
    while fair <= STIFFER * max(float(length), FAIR_MIN) * (1 + 1e-9):
        eps = (SPACING / fair) ** 4
        x, active = r, None
        for _ in range(OUTER_ROUNDS + 1):
            n, b = _merged(x, t, body, keepouts, movers, slack, grazed)
            x, active = solve_active_set(a, eps, n, b, x, pin_end, active, shape=road, pins=r)
        clear = np.all(disc_gaps(x, body, keepouts)[2:] + slack[2:] > -CLEAR_TOLERANCE) and all(
            np.all((m.value_grad(x, t)[0] > m.c)[2:] | grazed[2:]) for m in movers)
        if clear and np.max(menger_curvature(x)) <= kappa_max:
            return x, t
        fair *= 2.0
    return None
