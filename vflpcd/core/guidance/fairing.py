"""Curvature bound for a planned path: fairing by bending energy around the repulsive regions.

The integral of eq. (xi_r) turns as sharply as the reactive margin lets it (a car on
``carsim_avoidance`` gets 0.5-0.8 1/m beside the parked car), and a car cannot follow a path
whose curvature exceeds its geometric limit tan(delta_max) / L at any speed, so the speed plan of
the centripetal limit alone cannot make such a path drivable. Where the peak curvature exceeds
``kappa_max`` the path, resampled at spacing h, is replaced by the minimiser of

    J(x) = (h / l)^4 sum_k |x_k - r_k|^2 + sum_k |x_{k-1} - 2 x_k + x_{k+1}|^2

(r the planned points, l the fairing length: the longer, the stiffer the path) subject to every
point staying outside every repulsive boundary Q_i, with the first two points kept (the start's
position and the robot's heading; the end is free, as the next plan starts from the robot, unless
it is the goal). A plan
whose start direction is more than ``HEADING_TOLERANCE`` off the robot's heading is faired too:
the field at a robot off the path points towards it, and a reference that starts at that angle
asks the car for a step in heading. Q_i is convex, so it is convexified by a supporting
half-plane per point: at the point where the gradient line through x_k meets the level
varphi_i = CLEAR_LEVEL c_i just outside Q_i (a few outer rounds re-take them at the new points).
A free end is faired with a lead-out: the path continued ``LEAD_OUT`` m on the circle of its end's
curvature, free of the half-planes, and cut off after the solve. A bending-energy minimiser's free
end has no curvature (its natural boundary condition), so without it a plan ending in a bend
straightened out of it over its last metres: on the 15 m ring of the road suite's roundabout the
faired path left the ring by up to 2.8 m at its end, the tight path anchored on it then broke the
curvature limit there (0.140 against 0.139 1/m) and the field's wide path stood (J_MC 0.31-0.93 with
the car's state at the replan).
Each convex problem is solved by the dual active set of ``active_set_kernel`` (a banded Cholesky
factorisation a round, compiled with numba where it is installed), started from the previous
problem's final active set (the next outer round, the next l): its rounds are about the number of
half-planes that end active, where a primal active set moved a contact point one path point a
round; a solve that reaches the ``ACTIVE_ROUNDS`` cap returns a point that keeps every
half-plane (not the minimiser). l is doubled from
``FAIR_MIN`` until the peak curvature is within kappa_max; if ``FAIR_MAX`` is reached the flattest
clear path found is kept and the speed plan does what it can. When the first length (l =
``FAIR_MIN``) already ends inside a region at its points' times (a mover sweeping across a swerve
into its lane), the stiffer ones are not tried and the path comes back resampled, for the
planner's mover checks to turn down; a stiffer length that came out clear but too curved would
have been kept instead. On `follow_slow_car` the last timing pass of each replan tried all six
lengths for nothing (its slower replan 61 -> 42 ms); every suite scene, the road variants,
carsim_avoidance and uav_3d gave the same numbers to the last digit.

A replan starts at the robot, and a robot that passes an obstacle close (braked beside it, a
recovery plan's narrow margins) can start inside the band between Q_i and the level its
half-planes touch: held to them from the third point on, with the first two pinned along the
heading, the path turned there in one step (0.32-0.37 1/m against the car's 0.17 limit in
chicane_boxes beside the second box, at every length: the replans were refused as undrivable for
four ticks). Over its first 1 / (2 kappa_max) m a faired path's half-planes are eased (``lead_in``)
down to what a path leaving the start along the heading and turning at half kappa_max can reach
(by at most ``LEAD_IN_DEPTH``), and those points are not held to the clear check; the path turns
away within the limit, and the tight path and the safety supervisor's exact-shape margin follow.

A faired path stays within one turning radius 1 / kappa_max of the points it fairs (point for
point, ``stray``): the fairing takes out the field's kinks, it does not re-route. As l grows the
pull back to r fades ((h / l)^4: 2e-10 at 64 m), and a stiff minimiser held by a few half-planes
and the start's heading swung out like a lever: a replan beside a slow car (bench variants seed 34)
was faired 625 m off the road, clear of every region there and flat, kept as the flattest clear
path, and driven into the slow car's lane; double_lane_change's exit had one that moved points by
14 m. A length whose path strays farther ends the doubling (a stiffer one strays further) and the
best path found before it stands; the fairings kept in the road suite and carsim_avoidance move
points by up to 6.4 m (double_lane_change; 1 / kappa_max is 7.2 m for the car).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
from scipy.linalg import LinAlgError
from scipy.linalg.lapack import dpbtrf, dpbtrs

from vflpcd.core.guidance.active_set_kernel import dual_step
from vflpcd.core.guidance.speed import arc_lengths, menger_curvature

FAIR_MIN, FAIR_MAX = 2.0, 64.0  # fairing length l, m
LEAD_OUT = 8.0  # m of lead-out beyond a free end (fair_path)
HEADING_TOLERANCE = np.radians(5.0)  # a planned start direction further off the robot's heading is faired
SPACING = 0.25  # resampling step h, m
LEAD_IN_USE = 0.5  # of kappa_max: the turn a plan's first metres are eased to (lead_in)
LEAD_IN_DEPTH = 0.3  # m a lead-in half-plane is eased by at most
CLEAR_LEVEL = 0.8  # half-planes touch varphi = CLEAR_LEVEL * c_i: just outside Q_i (c_i < 0)
NEWTON, NEWTON_TOL = 6, 1e-10  # Newton steps to that level (at most), and the miss in varphi that ends them
OUTER_ROUNDS = 3  # re-convexifications
PENALTY = 1e7  # spring holding an active half-plane or a pinned point: it gives way by ~1e-7 m
ACTIVE_ROUNDS = 200  # active-set rounds per convex problem (cap)
VIOLATION = 1e-6  # m: an inactive half-plane violated by more is added
RELEASE = 1e-13  # m: an active point held this far outside (multiplier -PENALTY gap < -1e-6) is released



@dataclass(frozen=True)
class Region:
    """One repulsive region: value_grad(points (K, d), times (K,)) -> (varphi (K,), grad (K, d))
    at the times the points are reached, and its repulsive level c < 0 (Q: varphi <= c);
    ``near(points, times)`` -> (K,) bool, a cheap bound: False only where the point is outside the
    reactive region (None: every point may be inside)."""

    value_grad: Callable[[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]
    c: float
    near: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None

    def values(self, x: np.ndarray, t: np.ndarray) -> np.ndarray:
        """varphi at points x (K, d) reached at t (K,); +inf where ``near`` rules a point out."""
        if self.near is None:
            return self.value_grad(x, t)[0]
        v = np.full(len(x), np.inf)
        idx = np.flatnonzero(self.near(x, t))
        if idx.size:
            v[idx] = self.value_grad(x[idx], t[idx])[0]
        return v


def resample(xy: np.ndarray, times: np.ndarray, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Points (K, d) and their times (K,) resampled at arc-length spacing h (both ends kept)."""
    s = arc_lengths(xy)
    n = max(int(np.ceil(s[-1] / h)), 6)
    si = np.linspace(0.0, s[-1], n + 1)
    pts = np.column_stack([np.interp(si, s, xy[:, j]) for j in range(xy.shape[1])])
    return pts, np.interp(si, s, times)


def half_planes(x: np.ndarray, t: np.ndarray, regions: Sequence[Region]) -> tuple[np.ndarray, np.ndarray]:
    """Per point the supporting half-plane n_k' x >= b_k of the nearest-reaching repulsive region
    among those whose reactive region holds the point (n_k = 0, b_k = -inf: free)."""
    n = np.zeros_like(x)
    b = np.full(len(x), -np.inf)
    worst = np.full(len(x), np.inf)
    for region in regions:
        c = region.c
        v = region.values(x, t)
        near = np.nonzero((v < 0.0) & (v / c < worst))[0]  # v / c: 1 on Q_i, 0 on R_i
        if near.size == 0:
            continue
        q, tq = x[near], t[near]
        gq = np.zeros_like(q)
        going = np.arange(len(near))      # the points whose Newton has not ended
        for step in range(NEWTON + 1):    # Newton along the gradient to varphi_i = CLEAR_LEVEL c_i
            vg, gg = region.value_grad(q[going], tq[going])
            gq[going] = gg
            miss = CLEAR_LEVEL * c - vg
            if step == NEWTON:
                break
            on = np.abs(miss) > NEWTON_TOL
            going, miss, gg = going[on], miss[on], gg[on]
            if going.size == 0:
                break
            q[going] += (miss / np.maximum(np.einsum("ij,ij->i", gg, gg), 1e-12))[:, None] * gg
        nq = gq / np.maximum(np.linalg.norm(gq, axis=1, keepdims=True), 1e-12)
        n[near], b[near] = nq, np.einsum("ij,ij->i", nq, q)
        worst[near] = v[near] / c
    return n, b


def regions_clear(x: np.ndarray, t: np.ndarray, regions: Sequence[Region], eased: np.ndarray) -> bool:
    """Whether the points x (K, d) reached at t (K,), but their first two and last two and the
    ``eased`` ones (K,) (``lead_in``), lie outside every repulsive region."""
    return all(np.all((g.values(x, t) > g.c)[2:-2] | eased[2:-2]) for g in regions)


def compiled_clear(loop, rows: np.ndarray, x: np.ndarray, t: np.ndarray, eased: np.ndarray) -> bool:
    """``regions_clear`` by ``half_plane_kernel.clear_loop`` compiled (``loop``), for the planar regions
    whose ``ObstacleImplicit.row`` are ``rows`` (R, 12)."""
    return bool(loop(np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(t, dtype=float), rows, 2,
                     len(x) - 2, np.ascontiguousarray(eased), 1.0))


def compiled_half_planes(loop, rows: np.ndarray, x: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``half_planes`` by ``half_plane_kernel.half_planes_loop`` compiled (``loop``), for the planar
    regions whose ``ObstacleImplicit.row`` are ``rows`` (R, 12)."""
    n, b = np.empty((len(x), 2)), np.empty(len(x))
    loop(np.ascontiguousarray(x, dtype=float), np.ascontiguousarray(t, dtype=float), rows, CLEAR_LEVEL, NEWTON,
         NEWTON_TOL, n, b)
    return n, b


def _hessian_bands(K: int, d: int, eps: float) -> np.ndarray:
    """kron(D2'D2 + eps I, I_d) over the interleaved coordinates x[k d + j], in LAPACK's lower band
    layout with 2 d + 1 sub-diagonals: ab[i - j, j] = M[i, j] (i >= j). D2'D2 is the
    pentadiagonal [1 -2 1]' [1 -2 1] sum: main diagonal 1, 5, 6 .. 6, 5, 1, first off-diagonal
    -2, -4 .. -4, -2, second 1; in the interleaved matrix they sit at offsets 0, d and 2 d."""
    main = np.full(K, 6.0)
    main[[0, -1]], main[[1, -2]] = 1.0, 5.0
    off1 = np.full(K - 1, -4.0)
    off1[[0, -1]] = -2.0
    ab = np.zeros((2 * d + 2, K * d))
    ab[0] = np.repeat(main + eps, d)
    ab[d, :-d] = np.repeat(off1, d)
    ab[2 * d, :-2 * d] = 1.0
    return ab


def _banded_factor(ab: np.ndarray) -> np.ndarray:
    """The Cholesky factor of the symmetric positive definite banded matrix ab (lower layout of
    ``_hessian_bands``) by LAPACK's dpbtrf (ab consumed), for ``_banded_solve``."""
    c, info = dpbtrf(ab, lower=1, overwrite_ab=1)
    if info != 0:
        raise LinAlgError(f"fairing system not positive definite (dpbtrf info {info})")
    return c


def _banded_solve(c: np.ndarray, f: np.ndarray) -> np.ndarray:
    """M x = f (N,) by LAPACK's dpbtrs, M's factor c from ``_banded_factor``."""
    x, info = dpbtrs(c, f[:, None], lower=1)
    if info != 0:
        raise LinAlgError(f"fairing solve failed (dpbtrs info {info})")
    return x[:, 0]


def bending(g: np.ndarray) -> np.ndarray:
    """D2' D2 g for points g (K, d): the bending energy's gradient (half of it) at g."""
    y = g[:-2] - 2.0 * g[1:-1] + g[2:]
    out = np.zeros_like(g)
    out[:-2] += y
    out[1:-1] -= 2.0 * y
    out[2:] += y
    return out


def solve_active_set(r: np.ndarray, eps: float, n: np.ndarray, b: np.ndarray, pin_end: bool,
                     active0: np.ndarray | None = None,
                     shape: np.ndarray | None = None, pins: np.ndarray | None = None,
                     loop=None) -> tuple[np.ndarray, np.ndarray]:
    """min eps |x - r|^2 + |D2 (x - g)|^2 (g = ``shape``, default 0: the bending of x itself; a path g
    makes it the bending of x's offset from g) subject to n_k' x_k >= b_k, with the first two points
    (and with pin_end the last) pinned (where ``pins`` (K, d) has them, default r) by a stiff spring
    (PENALTY), by the dual active set of ``active_set_kernel`` (x is then the minimiser to
    ~1e-7 m). Stopped by ``ACTIVE_ROUNDS``, it returns a point that violates no half-plane.
    The active set starts from ``active0`` (the previous solve's); returns (x, its active set).
    ``loop``: ``active_set_kernel.solve_loop`` compiled (``vflpcd.controllers.loops``); without it
    the same steps run on numpy and LAPACK."""
    K, d = r.shape
    base = _hessian_bands(K, d, eps)
    f0 = eps * r.ravel()
    if shape is not None:
        f0 += bending(shape).ravel()
    pinned = [0, 1, K - 1] if pin_end else [0, 1]
    cols = (np.array(pinned)[:, None] * d + np.arange(d)).ravel()
    base[0, cols] += PENALTY
    f0[cols] += PENALTY * (r if pins is None else pins)[pinned].ravel()
    constrained = np.isfinite(b)
    constrained[pinned] = False
    active = np.zeros(K, dtype=bool) if active0 is None else constrained & active0
    x = np.zeros(K * d)
    n = np.ascontiguousarray(n, dtype=float)
    if loop is not None:
        done = loop(base, f0, n, np.where(constrained, b, 0.0), constrained, active, x, ACTIVE_ROUNDS, PENALTY,
                    VIOLATION, RELEASE)
        if done < 0:
            raise LinAlgError("fairing system not positive definite")
    else:
        _solve_numpy(base, f0, n, b, constrained, active, x)
    return x.reshape(K, d), active


def _solve_numpy(low0: np.ndarray, f0: np.ndarray, n: np.ndarray, b: np.ndarray, constrained: np.ndarray,
                 active: np.ndarray, x: np.ndarray) -> int:
    """``active_set_kernel.solve_loop``'s steps on numpy, each round's factor by LAPACK;
    active and x (N,) written in place; the rounds taken (0: stopped by ``ACTIVE_ROUNDS``)."""
    K, d = n.shape
    pairs = [(j1, j2) for j1 in range(d) for j2 in range(j1, d)]
    bc = np.where(constrained, b, 0.0)
    p, force, dual = -1, 0.0, True
    for r in range(ACTIVE_ROUNDS + K + 1):
        dual = dual and r < ACTIVE_ROUNDS
        low, f = low0.copy(), f0.copy()
        k = np.nonzero(active)[0]
        for j1, j2 in pairs:
            low[j2 - j1, k * d + j1] += PENALTY * n[k, j1] * n[k, j2]
        f.reshape(K, d)[k] += PENALTY * b[k, None] * n[k]
        c = _banded_factor(low)
        xa = _banded_solve(c, f)
        gaps = np.where(constrained, np.einsum("ij,ij->i", n, xa.reshape(K, d)) - bc, 0.0)
        if not dual:                     # restoring: every violated half-plane made active
            x[:] = xa
            open_ = constrained & ~active & (gaps < -VIOLATION)
            if not np.any(open_):
                return 0
            active |= open_
            continue
        if p < 0:
            held = active & (gaps > RELEASE)
            if np.any(held):             # a warm start's half-planes held from outside
                active &= ~held
                continue
            open_ = np.where(constrained & ~active, gaps, np.inf)
            p = int(np.argmin(open_))
            if not open_[p] < -VIOLATION:
                x[:] = xa
                return r + 1
            force = 0.0
        e = np.zeros(K * d)
        e[p * d:(p + 1) * d] = n[p]
        z = _banded_solve(c, e).reshape(K, d)
        x[:] = xa + force * z.ravel()
        g = np.einsum("ij,ij->i", n, x.reshape(K, d)) - bc
        a = np.einsum("ij,ij->i", n, z)
        full = -g[p] / a[p] if a[p] > 0.0 else np.inf
        t = np.where(active & (a > 0.0), np.maximum(-g / np.where(a > 0.0, a, 1.0), 0.0), np.inf)
        drop = int(np.argmin(t))
        p, force, restore = dual_step(full, t[drop], p, drop, active, force)
        dual = not restore
    return 0


def fair_path(xy: np.ndarray, times: np.ndarray, kappa_max: float, regions: Sequence[Region],
              heading: np.ndarray | None = None, pin_end: bool = False, loop=None, planes=None,
              clears=None) -> np.ndarray:
    """The path xy (K, d) (reached at times (K,)) with its peak curvature brought within kappa_max
    and, with ``heading`` (d,), leaving the start in the robot's heading (module docstring); with
    ``pin_end`` the last point stays where it is (the goal);
    returned unchanged (not resampled) if it already does both.
    ``regions``: the repulsive regions to stay out of; ``loop``: ``solve_active_set``'s;
    ``planes``: (points, times) -> the regions' half-planes (default ``half_planes``; the planner
    passes ``compiled_half_planes``); ``clears``: (points, times, eased) -> whether they are clear
    (default ``regions_clear``; the planner passes ``compiled_clear``)."""
    if not np.isfinite(kappa_max) or len(xy) < 7:
        return xy
    first = xy[min(int(np.ceil(SPACING / max(np.linalg.norm(xy[1] - xy[0]), 1e-9))), len(xy) - 1)] - xy[0]
    aligned = heading is None or first @ heading >= np.cos(HEADING_TOLERANCE) * np.linalg.norm(first)
    if aligned and np.max(menger_curvature(xy)) <= kappa_max:
        return xy
    r, t = resample(xy, times, SPACING)
    if heading is not None:  # the second point pins the start heading to the robot's
        r[1] = r[0] + SPACING * np.asarray(heading, float) / np.linalg.norm(heading)
    K = len(r)
    if not pin_end:         # a free end is faired with a lead-out beyond it (``lead_out``), cut off after
        r, t = lead_out(r, t, LEAD_OUT, kappa_max)
    best, best_kappa = r[:K], np.max(menger_curvature(r[:K]))
    fair, active, eased = FAIR_MIN, None, np.zeros(K, dtype=bool)
    while fair <= FAIR_MAX * (1 + 1e-9):
        eps = (SPACING / fair) ** 4
        x = r
        for _ in range(OUTER_ROUNDS):
            n, b = half_planes(x[:K], t[:K], regions) if planes is None else planes(x[:K], t[:K])
            if len(x) > K:          # the lead-out is free
                n = np.vstack([n, np.zeros((len(x) - K, n.shape[1]))])
                b = np.concatenate([b, np.full(len(x) - K, -np.inf)])
            if heading is not None:
                b[:K], eased = lead_in(n[:K], b[:K], r[0], heading, kappa_max)
            x, active = solve_active_set(r, eps, n, b, pin_end, active, loop=loop)
        kept, tk = x[:K], t[:K]
        if stray(kept, r[:K], 1.0 / kappa_max):
            return best
        clear = regions_clear(kept, tk, regions, eased) if clears is None else clears(kept, tk, eased)
        kappa = np.max(menger_curvature(kept))
        if clear and kappa < best_kappa:
            best, best_kappa = kept, kappa
        if clear and kappa <= kappa_max:
            return kept
        if not clear and fair == FAIR_MIN:      # the first length stays in a region: none is tried stiffer
            return best
        fair *= 2.0
    return best


def lead_in(n: np.ndarray, b: np.ndarray, x0: np.ndarray, heading: np.ndarray,
            kappa_max: float) -> tuple[np.ndarray, np.ndarray]:
    """The half-planes n_k' x >= b_k (K,) of a path resampled at SPACING whose first two points leave
    x0 (d,) along ``heading`` (d,), eased over its first 1 / (2 kappa_max) m where a path turning at
    LEAD_IN_USE kappa_max from there cannot reach them (module docstring): b_k is taken down to
    n_k' x0 + s_k n_k' h + kappa s_k (s_k - h) |n_k x h| / 2 (s_k = k h: the polyline's offset when
    each of its points from the second on turns it by kappa h), by at most ``LEAD_IN_DEPTH`` m.
    Returns (b, the eased points' mask (K,))."""
    b, eased = b.copy(), np.zeros(len(b), dtype=bool)
    m = min(int(0.5 / (kappa_max * SPACING)) + 1, len(b))
    s = SPACING * np.arange(2, m)
    nk = n[2:m]
    h = np.asarray(heading, float) / np.linalg.norm(heading)
    along = nk @ h
    across = np.sqrt(np.maximum(np.einsum("ij,ij->i", nk, nk) - along * along, 0.0))
    reach = nk @ x0 + s * along + 0.5 * LEAD_IN_USE * kappa_max * s * (s - SPACING) * across
    short = np.isfinite(b[2:m]) & (reach < b[2:m])
    eased[2:m] = short
    b[2:m] = np.where(short, np.maximum(reach, b[2:m] - LEAD_IN_DEPTH), b[2:m])
    return b, eased


def stray(x: np.ndarray, r: np.ndarray, reach: float) -> bool:
    """Whether a point of the faired path x (K, d) lies farther than ``reach`` m from its own
    point of r (K, d), the path it fairs (module docstring); non-finite points stray too."""
    d2 = np.einsum("ij,ij->i", x - r, x - r)
    return not bool(np.all(d2 <= reach * reach))


def lead_out(r: np.ndarray, t: np.ndarray, length: float, kappa_max: float) -> tuple[np.ndarray, np.ndarray]:
    """A planar r (K, 2) at times t (K,), resampled at SPACING, continued by ``length`` m on the circle
    of its end's curvature (its heading's change over the last metre, at most kappa_max), the times at
    the last step's rate; other paths are returned as they are."""
    if r.shape[1] != 2:
        return r, t
    m = max(int(round(1.0 / SPACING)), 1)   # the end's heading change between its segments' midpoints:
    seg = np.diff(r[-m - 1:], axis=0)       # speed.heading_curvature is one-sided there (a quarter low)
    ang = np.unwrap(np.arctan2(seg[:, 1], seg[:, 0]))
    kappa = float(np.clip((ang[-1] - ang[0]) / max(SPACING * (len(ang) - 1), 1e-9), -kappa_max, kappa_max))
    n = int(np.ceil(length / SPACING))
    theta = ang[-1] + kappa * SPACING * np.arange(1, n + 1)
    step = SPACING * np.column_stack([np.cos(theta), np.sin(theta)])
    ext = r[-1] + np.cumsum(step, axis=0)
    dt = (t[-1] - t[-2]) if len(t) > 1 else 0.0
    return np.vstack([r, ext]), np.concatenate([t, t[-1] + dt * np.arange(1, n + 1)])
