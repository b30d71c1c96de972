"""Guidance: from a reference path and obstacles to a safe, timed reference trajectory.

1. A stretch of the reference path (at most ``horizon`` metres, short enough to be a graph in
   its chord frame) becomes the path implicit phi (``GraphPath``).
2. Every actual obstacle becomes an implicit varphi_i whose repulsive boundary encloses the
   shape grown by the robot's body radius + ``safety_margin`` and whose reactive boundary lies
   ``reactive_margin`` further out. Its side and direction gamma_i follow the rule: pass on the
   side that leaves the path least, i.e. the side where the repulsive region reaches less far
   across the path (measured along the path normal at the obstacle); gamma_i is then the sign
   that makes gamma_i E grad varphi_i point along the path on that side. A mover that crosses the
   path faster than ``CROSSING_SPEED`` (0.7 m/s: slow walkers too) is yielded to: the plan keeps to the
   route and slows before the crossing until its timed trajectory stays clear (``yielding``); where
   no such speed exists it is passed behind, on the side it comes from (swerving to the side it
   moves to puts the robot in its way).
3. Virtual obstacles (``virtual = "auto"``): for each static obstacle whose reactive region
   the stretch enters, a circle whose repulsive boundary Q_vrtl has the turning radius
   v_d^2 / a_max, touches the path ``r_q * lead`` metres before the entry into R_actl on the
   passing side, and is pushed outwards until in-Q_vrtl ∩ P ⊂ in-R_actl ∩ P (remark 1). It
   acts in its buffer region only outside every actual reactive region and only before the
   path's entry into R_actl (beyond the paper, whose remark 2 alone leaves a virtual obstacle
   acting on a robot that was turned past R_actl without entering it).
4. The static part of chi_c is evaluated on a grid; eq. (xi_r) is integrated from the robot.
5. The integrated points' offsets from the path are smoothed (Gaussian, ``smoothing`` m); where their curvature exceeds
   ``curvature_use`` times the robot's geometric limit (``kappa_limit``: tan(delta_max) / L for a
   car) they are faired (``fairing.py``); then they are speed-planned. A timed trajectory that still
   enters a mover's repulsive region (a slow car ahead that the path cannot pass beside oncoming
   traffic) is speed-planned slower until it does not (``followed``), on its lane (the path planned
   without the movers) where any speed does: the robot follows in its lane.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import partial
from typing import Callable, Sequence

import numpy as np

from vflpcd.core.guidance.fairing import Region, compiled_clear, compiled_half_planes, fair_path
from vflpcd.core.guidance.field import ActualTerm, GuidanceField, VirtualTerm
from vflpcd.core.guidance.grid import FieldGrid, Integration, integrate
from vflpcd.core.guidance.implicit import E, GraphPath, GuidanceError, ObstacleImplicit, graph_horizon
from vflpcd.core.guidance.params import GuidanceParams
from vflpcd.core.guidance.speed import arrival_times, plan_speed, smooth_path, step_times
from vflpcd.core.guidance.tighten import CLEAR_TOLERANCE, Body, Keepout, disc_gaps, tighten_path
from vflpcd.core.guidance.trajectory import Trajectory, timed_trajectory
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath, nearest_on_polyline
from vflpcd.core.safety.monitors import PlanLimits, check_plan

VIRTUAL_LEAD = np.radians(30.0)  # heading change the virtual obstacle gives before R_actl
# m/s across the path: a mover crossing faster (a walker, a cyclist, a car) is passed behind, on the
# side it comes from; passing in front of it holds only while both keep to the planned timing
# (mixed_urban: the car passed 0.3 s ahead of a 4 m/s cyclist and was hit at the rear), and a path
# that passes on the side a walker walks to follows its region across the road (bench tick's
# scaling road at 2.0: the plan left the road beside a 1.4 m/s walker and every replan then failed;
# pedestrian_appears: J_MC 2.09 at 2.0, 0.12 at 1.0). Slower movers are passed where they leave the
# path least (bench variants seed 46 at 0.5: passing behind a 0.87 m/s walker boxed the car in, before
# crossers were yielded to). At 1.0 a walker slowed to 0.99 m/s (a pedestrian_appears copy of
# `bench jitter --scale 3`) was neither yielded to nor passed behind: the car swerved 6.1 m across
# the road ahead of it as it walked on (J_MC 7.9; 0.014 at 0.7, 0.31 m off the route).
CROSSING_SPEED = 0.7
FOLLOW_SPEEDS = (0.8, 0.6, 0.45, 0.3, 0.2, 0.1)  # of v_desired: slower speed plans tried behind a mover
# A plan is slowed to follow only when it enters a mover's repulsive region deeper than this fraction
# of the level |c_i|: the movers placed by MOVER_PASSES at the last pass's times leave grazes of
# about 0.04 |c_i| (carsim_avoidance's overtake), and a plan that passes should not be made to follow.
FOLLOW_SLACK = 0.25
DRIVABLE_ROUNDING = 1e-9  # relative: the speed plan meets v^2 kappa = a_lat_max up to rounding
# merged_later: the joins to the lane tried every JOIN_STEP m along the start's line, each a quintic
# blend (peak curvature 5.77 d / L^2 for an offset d over a length L) at least JOIN_STEP m long
JOIN_STEP = 5.0
JOIN_CURVATURE = 5.78
MOVER_PASSES = 3  # re-integrations with moving obstacles placed at the previous pass's arrival times
STATIC_MEMO = 4096  # static obstacles whose implicit and term a planner keeps (``static_terms``)
SIDE_RAYS = np.column_stack([np.cos(np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False)),
                             np.sin(np.linspace(0.0, 2.0 * np.pi, 360, endpoint=False))])  # ``actual_term``'s boundary rays


@dataclass(frozen=True)
class Prepared:
    """The field of one path stretch with its static obstacles, and its grid."""

    field: GuidanceField
    grid: FieldGrid
    s0: float
    s_end: float
    x_end: float
    ends_path: bool
    statics: tuple[ObstacleState, ...] = ()


@dataclass(frozen=True)
class GuidancePlan:
    """trajectory: the timed reference; xy (K, 2), s, kappa, v (K,): the smoothed spatial path
    and its speed plan; raw (K, 2): the points of eq. (xi_r); reached: the stretch's end was
    reached; inherited: steps that reused the previous direction."""

    trajectory: Trajectory
    xy: np.ndarray
    s: np.ndarray
    kappa: np.ndarray
    v: np.ndarray
    raw: np.ndarray
    reached: bool
    inherited: int
    field: GuidanceField
    gammas: tuple = ()
    virtual_off: tuple = ()


@dataclass(frozen=True)
class GuidanceLoops:
    """The guidance's loops compiled (``vflpcd.controllers.loops.guidance_loops``), None each where
    its numpy path runs: the fairing's and tight path's active set (``active_set_kernel``), the
    steps of eq. (xi_r) (``integrate_kernel``), the fairing's half-planes and clear check
    (``half_plane_kernel``), the 3-D steps (``integrate3d_kernel``, run interpreted where None) and
    the path grid's fill (``path_grid_kernel``)."""

    active_set: Callable | None = None
    steps: Callable | None = None
    half_planes: Callable | None = None
    steps3d: Callable | None = None
    clear: Callable | None = None
    path_fill: Callable | None = None


class PlannerBase:
    """What the planar and the 3-D planner share: checked inputs and the obstacles' implicits."""

    dim = 2

    def __init__(self, path: ReferencePath, params: GuidanceParams, v_desired: float, a_lat_max: float,
                 body_radius: float, control_period: float, kappa_limit: float = np.inf,
                 body: Body | None = None, loops: Callable[[], GuidanceLoops | None] | None = None,
                 kappa_rate_limit: float = np.inf) -> None:
        """``kappa_rate_limit``: the steering's rate limit as a rate of curvature, delta_rate_max / L
        (1/(m s); inf: none), of which the speed plan uses ``curvature_use`` (``speed.plan_speed``).
        ``loops``: a function that returns the guidance's loops compiled (``GuidanceLoops``;
        ``vflpcd.controllers.loops.guidance_loops``), or None where there are none (their numpy
        paths run). The planner is sent to the worker processes, and a function travels there by
        name and loads the compiled loops from numba's cache (``warm``); a compiled loop sent itself
        arrives without its cache and compiles again at the first replan (about 7 s on this
        project's machines)."""
        if path.dim != self.dim:
            raise GuidanceError(f"{type(self).__name__} needs a {self.dim}-D path, got a {path.dim}-D one")
        for name, value in (("v_desired", v_desired), ("a_lat_max", a_lat_max), ("body_radius", body_radius),
                            ("control_period", control_period)):
            if not (np.isfinite(value) and value > 0):
                raise GuidanceError(f"{name} must be positive and finite, got {value}")
        self.path, self.params = path, params
        self.v_desired, self.a_lat_max = v_desired, a_lat_max
        if not kappa_limit > 0:
            raise GuidanceError(f"kappa_limit must be positive (inf: none), got {kappa_limit}")
        self.body_radius, self.dt = body_radius, control_period
        self.body = body if body is not None else Body(np.zeros(1), float(body_radius))
        self.kappa_limit = float(kappa_limit)
        self.kappa_max = params.curvature_use * kappa_limit
        if not kappa_rate_limit > 0:
            raise GuidanceError(f"kappa_rate_limit must be positive (inf: none), got {kappa_rate_limit}")
        self.kappa_rate_limit = float(kappa_rate_limit)
        self.kappa_rate_max = params.curvature_use * kappa_rate_limit
        self.loops = loops

    def warm(self) -> None:
        """Load what a replan runs (the compiled loops), so that a worker's first replan does not
        wait for it."""
        self._loops()

    def _loops(self) -> GuidanceLoops:
        """The compiled loops (``loops``), or a ``GuidanceLoops`` of None (the numpy paths)."""
        return (self.loops and self.loops()) or GuidanceLoops()

    def drivable(self, plan: "GuidancePlan") -> bool:
        """Whether the plan keeps the robot's curvature limit (``kappa_limit``) and its lateral
        acceleration: the safety monitors' ``check_plan``, without their tolerance."""
        return self.keeps_limits(plan.kappa, plan.v)

    def keeps_limits(self, kappa: np.ndarray, v: np.ndarray) -> bool:
        """``drivable`` for a path's curvature kappa (K,) and speed plan v (K,)."""
        return check_plan(kappa, v, PlanLimits(self.kappa_limit, self.a_lat_max), DRIVABLE_ROUNDING) is None

    def static_gap(self, plan: "GuidancePlan", statics: Sequence[ObstacleState]) -> float:
        """The least gap (m) between the body's covering discs along the plan's path and the static
        obstacles' shapes (+inf without any near it): negative where the path runs into one."""
        return float(np.min(disc_gaps(plan.xy, self.body, [Keepout(o, 0.0) for o in statics])))

    def recovery(self) -> "PlannerBase | None":
        """The same planner with the clearance beyond the body radius taken down to ``recovery_margin``
        and the reactive band to ``recovery_reactive_margin`` (None when they already are that small):
        a robot that ended up close to an obstacle (braked beside it, a pedestrian stepped near), or a
        gap between parked cars narrower than the full margins, may find no drivable path that keeps
        them (the overlapping reactive bands bend the field sharply), and the safety supervisor still
        keeps its own margin around the exact body."""
        p = self.params
        if (p.safety_margin <= p.recovery_margin and p.margin_per_speed == 0.0 and p.mover_margin_time == 0.0
                and p.reactive_margin <= p.recovery_reactive_margin and p.reactive_per_speed == 0.0):
            return None
        narrow = replace(p, safety_margin=min(p.safety_margin, p.recovery_margin), margin_per_speed=0.0,
                         mover_margin_time=0.0, reactive_margin=min(p.reactive_margin, p.recovery_reactive_margin),
                         reactive_per_speed=0.0)
        return self._with(narrow)

    def closers(self) -> tuple["PlannerBase", ...]:
        """The planners whose tight path keeps ``recovery_tight_margin``, then ``least_tight_margin``,
        instead of ``tight_margin`` (each only when smaller than the one before; none without a tight
        path): tried in turn after ``recovery`` when its plan too is undrivable. A 3 m gap between
        parked cars leaves the SUV's covering discs (2.06 m across) less than tight_margin on both
        sides: no tight path keeps it, and the field's own path, bent where the overlapping bands
        end, is undrivable at every margin; between rows 2.5 m apart the discs keep 0.18 m on the
        route itself."""
        p = self.params
        if p.tight_length <= 0.0:
            return ()
        out, last = [], p.tight_margin
        for margin in (p.recovery_tight_margin, p.least_tight_margin):
            if margin < last:
                out.append(self._with(replace(p, tight_margin=margin)))
                last = margin
        return tuple(out)

    def _with(self, params: GuidanceParams) -> "PlannerBase":
        """The same planner with other parameters."""
        return type(self)(self.path, params, self.v_desired, self.a_lat_max, self.body_radius, self.dt,
                          kappa_limit=self.kappa_limit, body=self.body, loops=self.loops,
                          kappa_rate_limit=self.kappa_rate_limit)

    def margin(self, o: ObstacleState) -> float:
        """The clearance kept beyond the body radius from obstacle o: ``safety_margin``, plus
        ``margin_per_speed`` s of the desired speed (the tracking error grows with speed), plus
        ``mover_margin_time`` s of the obstacle's own speed (its predicted position grows uncertain)."""
        p = self.params
        return (p.safety_margin + p.margin_per_speed * self.v_desired
                + p.mover_margin_time * float(np.linalg.norm(o.velocity)))

    def implicit(self, o: ObstacleState) -> ObstacleImplicit:
        """varphi_i of an obstacle: Q at body radius + ``margin(o)``, R ``reactive_margin`` plus
        ``reactive_per_speed`` s of the desired speed further out (room to turn in)."""
        p = self.params
        rep = self.body_radius + self.margin(o)
        reactive = rep + p.reactive_margin + p.reactive_per_speed * self.v_desired
        return ObstacleImplicit.around(o.id, o.shape, o.center, o.yaw, o.velocity, o.stamp,
                                       reactive_distance=reactive, repulsive_distance=rep)

    def static_terms(self, statics: Sequence[ObstacleState], lo: np.ndarray, hi: np.ndarray,
                     make: Callable[[ObstacleImplicit], object]) -> dict[str, object]:
        """The terms ``make(implicit)`` of the static obstacles whose reach comes within 1 m of the
        box [lo, hi] (the stretch's points), by id, in the order of ``statics``. A static obstacle's
        implicit and term depend on its id, shape and pose alone (the path and the margins are the
        planner's), so both are kept for the next replan (at most ``STATIC_MEMO`` obstacles):
        on a road with 40 posts they took two thirds of a replan's preparation."""
        memo = self.__dict__.setdefault("_static_memo", {})
        if len(memo) > STATIC_MEMO:
            memo.clear()
        terms = {}
        for o in statics:
            key = (o.id, o.shape, tuple(o.center.tolist()), float(o.yaw))
            entry = memo.get(key)
            if entry is None:
                entry = memo[key] = [self.implicit(o), None]
            imp = entry[0]
            if np.all(np.abs(np.clip(imp.center, lo, hi) - imp.center) <= imp.reach + 1.0):
                if entry[1] is None:
                    entry[1] = make(imp)
                terms[o.id] = entry[1]
        return terms

    def __getstate__(self) -> dict:
        """The planner as it travels to a worker: without the memo of ``static_terms``."""
        state = dict(self.__dict__)
        state.pop("_static_memo", None)
        return state

    def check_clear(self, point: np.ndarray, terms, t: float, what: str) -> np.ndarray:
        """point (d,) checked finite and outside every term's repulsive boundary at time t; GuidanceError
        naming the obstacle otherwise. ``what`` is "start" or "goal". Returns the point as floats."""
        point = np.asarray(point, float)
        if point.shape != (self.dim,) or not np.all(np.isfinite(point)):
            raise GuidanceError(f"{what} must be {self.dim} finite numbers, got {point!r}")
        for term in terms:
            if term.implicit.value(point[None, :], t)[0] <= term.implicit.c:
                raise GuidanceError(f"obstacle {term.implicit.name!r} covers the {what} at "
                                    f"{point.round(2).tolist()} (it is inside its repulsive boundary)")
        return point

    def safe_smooth(self, raw: np.ndarray, terms, t0: float, times: np.ndarray | None, graph) -> np.ndarray:
        """Smooth raw (K, d) with the configured std, halving it (down to none) while the smoothed
        points would cut into a repulsive boundary (moving obstacles at the points' times).

        The smoothing acts on the points' offset from the path (in the frame where the path
        ``graph`` is straight, ``straighten``/``bend``), not on the points themselves: the integrated
        path's kinks are smoothed, the reference path's own curvature is kept (plain Gaussian
        smoothing cuts every bend by sigma^2 kappa / 2, and a plan that starts on the path would
        leave it at its start, where the smoothing fades out)."""
        p = self.params
        t = self._point_times(len(raw), t0, times)
        sigma = p.smoothing / p.beta
        straight = graph.straighten(raw)
        while True:
            xy = graph.bend(smooth_path(straight, sigma)) if sigma >= 0.5 else raw
            if sigma < 0.5 or not self.reaches_any(terms, xy, t):
                return xy
            sigma /= 2.0

    def _point_times(self, n: int, t0: float, times: np.ndarray | None) -> np.ndarray:
        """Times at which the n integrated points are reached: the step times of the last pass, or
        (first pass) at v_desired."""
        k = np.arange(n)
        return t0 + k * self.params.beta / self.v_desired if times is None else np.interp(k, np.arange(len(times)), times)

    def faired(self, xy: np.ndarray, terms, t0: float, times: np.ndarray | None,
               heading: np.ndarray | None = None, pin_end: bool = False) -> np.ndarray:
        """xy (K, d) with its curvature brought within kappa_max around the terms' repulsive regions,
        leaving the start along ``heading`` (d,) when given, ending where it ends with ``pin_end``."""
        regions = [Region(partial(_value_grad_at_times, term.implicit), term.implicit.c,
                          partial(_within_reach, term.implicit)) for term in terms]
        loops = self._loops()
        planes = clears = None
        if loops.half_planes is not None and self.dim == 2:
            rows = _rows(terms)
            planes = partial(compiled_half_planes, loops.half_planes, rows)
            clears = partial(compiled_clear, loops.clear, rows) if loops.clear is not None else None
        return fair_path(xy, self._point_times(len(xy), t0, times), self.kappa_max, regions, heading, pin_end,
                         loops.active_set, planes, clears)

    def tight_clearance(self, o: ObstacleState) -> float:
        """The clearance the tight path keeps between the body's discs and o's shape: ``tight_margin``
        plus the speed and motion terms of ``margin``."""
        p = self.params
        return p.tight_margin + self.margin(o) - p.safety_margin

    def tightened(self, prepared: Prepared, movers: Sequence[ObstacleState], xy: np.ndarray, s: np.ndarray,
                  v: np.ndarray, t0: float, v0: float, heading: np.ndarray | None, goal: bool):
        """The speed-planned path xy (arc lengths s, speeds v, from t0 at v0) pulled onto the
        reference path as far as the body's clearance (``tight_clearance``) to the stretch's static
        obstacles and to the movers, ``tight_mover_window`` s before and after the time each point
        is reached, lets it (``tighten.py``, stiffness ``tight_length``), and speed-planned again:
        (xy, s, kappa, v). None when that is 0, when the stretch has no obstacle, when no tight path
        exists, or when the re-timed tight path (a shorter path is reached earlier) comes closer to
        a mover than the clearance and than the field's timed path does, or brings the body into a
        mover's shape (``touches_mover``) (the movers are taken at the tight path's own times for up
        to ``MOVER_PASSES`` rounds)."""
        p = self.params
        if p.tight_length <= 0.0 or not (prepared.statics or movers):
            return None
        anchor = partial(self.path.anchors, s0=prepared.s0 - 5.0, s1=prepared.s_end + 5.0)
        moving = self.mover_keepouts(movers)
        keepouts = [Keepout(o, self.tight_clearance(o)) for o in prepared.statics] + moving
        times = field_times = _arrivals(s, v, t0)
        if moving:      # the field's timed path may pass a mover closer than the clearance: no closer than it
            floor = min(0.0, self.least_gap(timed_trajectory(xy, s, v, t0, self.dt), moving)) - CLEAR_TOLERANCE
        for _ in range(MOVER_PASSES if moving else 1):
            out = tighten_path(xy, times, anchor, self.kappa_max, self.body, keepouts,
                               p.tight_length, heading, goal, field_times, self._loops().active_set)
            if out is None:
                return None
            s_t, kappa, v_t = self.speed_plan(out[0], self.v_desired, v0, goal)
            trajectory = timed_trajectory(out[0], s_t, v_t, t0, self.dt)
            if not moving or (self.least_gap(trajectory, moving) >= floor and not self.touches_mover(movers, trajectory)):
                return out[0], s_t, kappa, v_t
            # the shorter path is reached earlier: each field point is taken at the time the tight
            # path passes it (its nearest tight point's), and the movers there, next round
            nearest = np.argmin(((xy[:, None, :] - out[0][None, :, :]) ** 2).sum(axis=2), axis=1)
            times = _arrivals(s_t, v_t, t0)[nearest]
        return None

    def mover_keepouts(self, movers: Sequence[ObstacleState]) -> list[Keepout]:
        """The movers' tight clearances (``tight_clearance``), each mover taken where it is
        ``tight_mover_window`` s before and after the time a point is reached, and then."""
        w = self.params.tight_mover_window
        shifts = (0.0,) if w <= 0.0 else (-w, 0.0, w)
        return [Keepout(o, self.tight_clearance(o), dt) for o in movers for dt in shifts]

    def least_gap(self, trajectory: Trajectory, keepouts: Sequence[Keepout]) -> float:
        """The least gap (``disc_gaps``) of the body along a timed trajectory to the keepouts, m."""
        return float(np.min(disc_gaps(trajectory.pos, self.body, keepouts, trajectory.t)))

    def reaches_any(self, terms, xy: np.ndarray, t: np.ndarray, scale: float = 1.0) -> bool:
        """Whether some point of xy (K, d) reached at times t (K,) comes to the level ``scale`` c_i of
        some term's region (varphi_i <= scale c_i; scale 1: into its repulsive region), by
        ``half_plane_kernel.clear_loop`` compiled for planar regions, else by ``_reaches``."""
        loop = self._loops().clear
        if loop is not None and self.dim == 2:
            return bool(terms) and not loop(np.ascontiguousarray(xy, dtype=float), np.ascontiguousarray(t, dtype=float),
                                            _rows(terms), 0, len(xy), np.zeros(len(xy), dtype=bool), float(scale))
        return any(self._reaches(term.implicit, xy, t, scale * term.implicit.c) for term in terms)

    @staticmethod
    def _reaches(o: ObstacleImplicit, xy: np.ndarray, t: np.ndarray, level: float) -> bool:
        """Whether varphi <= level (< 0: inside the reactive region) at some point of xy (K, d)
        reached at times t (K,). Only the points within o's reach of its centre are evaluated:
        outside it varphi > 0 (``_within_reach``)."""
        t = np.broadcast_to(np.asarray(t, float), (len(xy),))
        near = _within_reach(o, xy, t)
        if not near.any():
            return False
        return bool(np.any(o.value(_at_stamp(o, xy[near], t[near]), o.stamp) <= level))

    def splice(self, plan: GuidancePlan, robot: np.ndarray, v_robot: float, t_now: float) -> GuidancePlan | None:
        """A late replan re-timed as if planned now from the robot (``robot`` (d,) at ``t_now`` at
        speed ``v_robot``): a replan is planned from the robot's state when it was asked for, and
        when the robot did not drive as it assumed while the worker planned (it stopped at the end
        of its old plan, was braked), the plan's reference at the installation lies far ahead of it.
        The path is kept from its first point at or after the robot's projection (at most one path
        step ahead), so its points and curvature are the plan's own; the speed plan starts again
        from v_robot. None when the re-timed plan would meet a moving obstacle's repulsive region (when
        overtaking, arriving later means merging back closer to the car overtaken). A plan with
        fewer than three points ahead of the robot is returned as it is."""
        k = nearest_on_polyline(np.asarray(robot, float), plan.xy)[1]
        pts = plan.xy[k + 1:]
        if len(pts) < 3:
            return plan
        s, kappa, v, trajectory = self.timed(pts, self.v_desired, max(float(v_robot), 0.0), t_now, _stops(plan.v))
        if self.meets_mover(plan.field.movers, trajectory):
            return None
        return replace(plan, trajectory=trajectory, xy=pts, s=s, kappa=kappa, v=v)

    def speed_plan(self, xy: np.ndarray, v_max, v0: float, at_rest: bool, kappa_cap: float = np.inf,
                   a_decel: float | None = None):
        """``plan_speed`` of the path xy up to v_max ((K,) or one number) from v0, ending at rest at the
        goal with ``at_rest``, braking at a_decel (default the params'): (s, kappa, v)."""
        p = self.params
        return plan_speed(xy, v_max, self.a_lat_max, p.a_accel, p.a_decel if a_decel is None else a_decel, v0,
                          v_end=0.0 if at_rest else None, kappa_cap=kappa_cap, kappa_rate_max=self.kappa_rate_max)

    def timed(self, xy: np.ndarray, v_max: float, v0: float, t0: float, at_rest: bool):
        """The path xy speed-planned up to v_max from v0 (ending at rest with ``at_rest``) and timed
        from t0: (s, kappa, v, trajectory)."""
        s, kappa, v = self.speed_plan(xy, v_max, v0, at_rest)
        return s, kappa, v, timed_trajectory(xy, s, v, t0, self.dt)

    def meets_mover(self, movers, trajectory: Trajectory, slack: float = 0.0) -> bool:
        """Whether the timed trajectory enters a moving obstacle's repulsive region (terms ``movers``)
        deeper than ``slack`` times its level |c_i| (0: at all)."""
        return self.reaches_any(movers, trajectory.pos, trajectory.t, 1.0 + slack)

    def touches_mover(self, movers: Sequence[ObstacleState], trajectory: Trajectory) -> bool:
        """Whether the body's covering discs along the timed trajectory come into a moving obstacle's
        shape (``movers``' states, constant velocity) closer than they are at its start (a plan that
        starts beside a mover may stay as close, not come closer). The field's regions are fits of
        the grown shapes, and a path that enters them by less than ``FOLLOW_SLACK`` of their level
        can still bring the car's corner onto a slow car's rear: `bench variants` seed 22 planned a
        late swerve past a slow car whose discs entered it by 0.46 m, and the car came within
        0.10 m of it."""
        moving = [Keepout(o, 0.0) for o in movers if o.moving]
        if not moving:
            return False
        gaps = disc_gaps(trajectory.pos, self.body, moving, trajectory.t)
        return bool(np.min(gaps) < min(0.0, float(gaps[0])) - CLEAR_TOLERANCE)

    def followed(self, movers, paths, t0: float, v0: float, states: Sequence[ObstacleState] = ()):
        """The first of ``paths`` ((xy, whether it ends at rest), best first) that, speed-planned
        slower (``FOLLOW_SPEEDS`` of v_desired, fastest first), has a trajectory from t0 at v0 that
        meets no mover: a slow car ahead that the path cannot pass is followed. The planner gives
        the lane (its path without the movers) first, the field's path round them second: the
        robot follows in its lane at whatever speed that takes, and crawls along a swerve only when
        the lane is blocked at every speed (a mover coming the other way in it). (xy, s, kappa, v,
        trajectory), or None when no such speed exists. ``states``: the movers' states, whose shapes
        the body must not come into either (``touches_mover``). Where no path at any speed keeps
        out of the movers' regions (the fits of their grown shapes), the ones that entered them are
        taken again, in the same order, on the shapes alone (with ``states`` given): oncoming cars
        driven near the centre line reach into the lane with their regions at every speed, and the
        field's swerve past the slow car, which then stood, put the car in the oncoming lane (a
        jittered follow_slow_car: braked to rest there by the failsafe when its replans failed,
        and hit head-on). A slowed plan beyond the robot's limits (``keeps_limits``) is never
        taken: a swerve the field wove between the movers (0.46 1/m against the car's 0.17) stood
        against the lane that only met the region of an oncoming car passing beside it, and the
        car followed the swerve off the road until its undrivable stretch came near."""
        entered = []        # (xy, slowed) whose trajectory enters a mover's region
        for xy, at_rest in paths:
            for f in FOLLOW_SPEEDS:
                slower = self.timed(xy, f * self.v_desired, v0, t0, at_rest)
                if not self.keeps_limits(slower[1], slower[2]):
                    continue
                if self.meets_mover(movers, slower[3]):
                    entered.append((xy, slower))
                elif not self.touches_mover(states, slower[3]):
                    return (xy,) + slower
        for xy, slower in entered if states else ():
            if not self.touches_mover(states, slower[3]):
                return (xy,) + slower
        return None


def _crossing_spans(xy: np.ndarray, s: np.ndarray, crossing: Sequence[ObstacleImplicit], t0: float) -> list:
    """For each crossing mover whose line of motion the path xy (K, d) crosses, nearest first: the
    arc lengths (of s (K,)) of the path's first point within the mover's reach of that line (where
    yielding must be done by) and of its first point on the far side of the line (the yielding's
    end), and the mover's index in ``crossing``. A mover whose line the path does not cross (one
    it has passed already) is not yielded to."""
    spans = []
    for i, o in enumerate(crossing):
        v = o.velocity / max(float(np.linalg.norm(o.velocity)), 1e-12)
        rel = xy - o.center_at(t0)
        side = rel[:, 0] * v[1] - rel[:, 1] * v[0]
        near = np.flatnonzero(np.abs(side) < o.reach)
        if not near.size:
            continue
        flip = np.flatnonzero(np.sign(side[near[0]:]) != np.sign(side[near[0]]))
        if flip.size:
            spans.append((float(s[near[0]]), float(s[near[0] + flip[0]]), i))
    return sorted(spans)


def _beyond_grid(prepared: Prepared, xy: np.ndarray) -> np.ndarray:
    """How far each point of xy (K, 2) lies beyond the stretch's field grid (K,) (<= 0 inside)."""
    xmin, xmax, ymin, ymax = prepared.grid.bounds
    x, y = xy[:, 0], xy[:, 1]
    return np.maximum.reduce([xmin - x, x - xmax, ymin - y, y - ymax])


def _arrivals(s: np.ndarray, v: np.ndarray, t0: float) -> np.ndarray:
    """When the speed-planned points (arc lengths s, speeds v) are reached from t0; points beyond a
    stop when the stop is."""
    t = t0 + arrival_times(s, v)
    t[~np.isfinite(t)] = np.max(t[np.isfinite(t)])
    return t


def _rows(terms) -> np.ndarray:
    """The planar regions of ``terms`` as the compiled loops' rows (R, 12) (``ObstacleImplicit.row``)."""
    return np.array([term.implicit.row() for term in terms], dtype=float).reshape(-1, 12)


def _stops(v: np.ndarray) -> bool:
    """Whether the speed plan v (K,) stops at its end (the goal)."""
    return bool(v[-1] <= 1e-9)


def _at_stamp(o: ObstacleImplicit, pts: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Points (K, d) reached at times t (K,) moved into the frame of the obstacle at its stamp: a
    centre moving at constant velocity gives varphi(p, t) = varphi(p - v (t - stamp), stamp)."""
    return pts - (np.asarray(t)[:, None] - o.stamp) * o.velocity


def _within_reach(o: ObstacleImplicit, pts: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Whether points (K, d) reached at times (K,) lie within o's reach of its centre then (outside
    it they are outside its reactive region)."""
    return np.einsum("ij,ij->i", d := _at_stamp(o, pts, t) - o.center, d) < o.reach ** 2


def _value_grad_at_times(o: ObstacleImplicit, pts: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """varphi and its gradient at points (K, d) reached at times (K,) (``_at_stamp``)."""
    return o.value_grad(_at_stamp(o, pts, t), o.stamp)


class GuidancePlanner(PlannerBase):
    """Plans the reference for one robot on one reference path (2-D)."""

    def actual_term(self, o: ObstacleImplicit, t: float = 0.0) -> ActualTerm:
        """Side (+1 left, -1 right) and gamma_i by the rule in the module docstring, for the obstacle
        where it is at time t; a mover crossing the path faster than ``CROSSING_SPEED`` is passed
        behind, on the side it comes from."""
        center = o.center_at(t)
        proj = self.path.project(center)
        tangent = proj.tangent
        normal = E @ tangent
        r_q = (1.0 + o.c) / o.norm(SIDE_RAYS)
        boundary = center + (SIDE_RAYS * r_q[:, None]) @ o.Rz.T
        lateral = (boundary - proj.point) @ normal
        side = 1.0 if np.max(lateral) <= np.max(-lateral) else -1.0
        crossing = float(o.velocity @ normal)
        if abs(crossing) > CROSSING_SPEED:      # pass behind a mover crossing the path: on the side it comes from
            side = -float(np.sign(crossing))
        u = o.Rz.T @ (side * normal)
        p_pass = center + o.Rz @ (u / o.norm(u[None, :])[0])
        _, g = o.value_grad(p_pass[None, :], t)
        along = float(tangent @ (E @ g[0]))
        gamma = np.sign(along) if along != 0.0 else -side
        return ActualTerm(implicit=o, gamma=float(gamma), side=side, crosses=abs(crossing) > CROSSING_SPEED)

    def virtual_for(self, term: ActualTerm, s0: float, s_end: float, graph: GraphPath) -> VirtualTerm | None:
        """The automatic virtual obstacle of an actual one (None if the stretch does not enter R_actl
        or there is no room before it)."""
        o = term.implicit
        s = np.arange(s0, s_end, 0.25)
        pts = self.path.point_at(s)
        inside = np.nonzero(o.value(pts) < 0.0)[0]
        if inside.size == 0 or inside[0] == 0:
            return None
        r_q = self.v_desired ** 2 / self.a_lat_max
        r_R = r_q + self.params.virtual_buffer
        s_t = s[inside[0]] - r_q * VIRTUAL_LEAD
        if s_t <= s0:
            return None
        p_t, t_t = self.path.point_at(s_t), self.path.tangent_at(s_t)
        n_t = term.side * (E @ t_t)
        offset = r_q
        for _ in range(40):  # remark 1: the path enters Q_vrtl only inside R_actl
            center = p_t + n_t * offset
            v = ObstacleImplicit(f"virtual:{o.name}", center, 0.0, np.zeros(2), 0.0, np.array([r_R, r_R]),
                                 2.0, None, r_q / r_R - 1.0)
            in_q = v.value(pts) < v.c
            if not np.any(in_q & (o.value(pts) >= 0.0)):
                break
            offset *= 1.05
        else:
            return None
        _, g = v.value_grad((p_t + n_t * (offset - r_q))[None, :])  # the point of Q_vrtl nearest the path
        along = float(t_t @ (E @ g[0]))
        x_stop = float(graph.progress(pts[inside[0]][None, :])[0])
        return VirtualTerm(implicit=v, gamma=float(np.sign(along) or term.side), parent=o, x_stop=x_stop)

    def manual_virtual(self, spec, terms: dict[str, ActualTerm], graph: GraphPath, s0: float,
                       s_end: float) -> VirtualTerm:
        if spec.parent not in terms:
            raise GuidanceError(f"virtual obstacle at {spec.center.tolist()}: parent {spec.parent!r} is not an "
                                f"obstacle near this stretch (have: {', '.join(sorted(terms)) or 'none'})")
        parent = terms[spec.parent]
        pts = self.path.point_at(np.arange(s0, s_end, 0.25))
        inside = np.nonzero(parent.implicit.value(pts) < 0.0)[0]
        x_stop = float(graph.progress(pts[inside[0]][None, :])[0]) if inside.size else np.inf
        v = ObstacleImplicit(f"virtual:{spec.parent}", spec.center, 0.0, np.zeros(2), 0.0,
                             np.array([spec.radius, spec.radius]), 2.0, None, spec.c)
        if spec.gamma:
            return VirtualTerm(implicit=v, gamma=float(spec.gamma), parent=parent.implicit, x_stop=x_stop)
        proj = self.path.project(spec.center)
        _, g = v.value_grad(proj.point[None, :])
        return VirtualTerm(implicit=v, gamma=float(np.sign(proj.tangent @ (E @ g[0])) or 1.0), parent=parent.implicit,
                           x_stop=x_stop)

    # ------------------------------------------------------------------ planning
    def prepare(self, s0: float, statics: Sequence[ObstacleState]) -> Prepared:
        """Field and grid of the stretch starting at arc length s0 with the static obstacles."""
        p = self.params
        s0 = float(self.path.wrap_s(s0)) if self.path.closed else float(np.clip(s0, 0.0, self.path.length))
        s_end = graph_horizon(self.path, s0, p.horizon)
        ends_path = (not self.path.closed) and s_end >= self.path.length - 1e-9
        back = min(5.0, s0) if not self.path.closed else 5.0
        graph = GraphPath.from_reference(self.path, s0 - back, s_end)
        pts = self.path.point_at(np.linspace(s0, s_end, 200))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        terms: dict[str, ActualTerm] = self.static_terms(statics, lo, hi, self.actual_term)
        lo, hi = lo - p.corridor, hi + p.corridor
        for t in terms.values():  # lo/hi cover every relevant reactive region
            lo = np.minimum(lo, t.implicit.center - t.implicit.reach - 2.0)
            hi = np.maximum(hi, t.implicit.center + t.implicit.reach + 2.0)
        pad = 0.0
        field = GuidanceField(path=graph, gamma0=-1.0, k_p=p.k_p, k_r=p.k_r, l1=p.l1, l2=p.l2, k_c=p.k_c,
                              statics=list(terms.values()))
        if p.virtual_obstacles:
            field.virtuals = [self.manual_virtual(spec, terms, graph, s0, s_end) for spec in p.virtual_obstacles]
        elif p.virtual == "auto":
            field.virtuals = [v for t in terms.values() if (v := self.virtual_for(t, s0, s_end, graph)) is not None]
        if ends_path:
            self.check_clear(self.path.point_at(self.path.length), terms.values(), 0.0, "goal")
        grid = FieldGrid.build(field, (lo[0] - pad, hi[0] + pad, lo[1] - pad, hi[1] + pad), p.grid_resolution,
                               self._loops().path_fill)
        x_end = float(graph.progress(self.path.point_at(s_end)[None, :])[0]) - (p.beta if ends_path else 0.0)
        return Prepared(field=field, grid=grid, s0=s0, s_end=s_end, x_end=x_end, ends_path=ends_path,
                        statics=tuple(o for o in statics if o.id in terms))

    def _integrate_and_time(self, field, prepared: Prepared, start, t0, v0, heading, steps, fair: bool = True,
                            integration: Integration | None = None):
        """Eq. (xi_r), smoothing and speed planning: (integration, xy, s, kappa, v). Without ``fair``
        (a pass that only times the points) the path is not faired and its speed plan takes the
        curvature at most kappa_max, as the faired path's would. ``integration``: eq. (xi_r)'s result
        for these step times when it is known already."""
        p = self.params
        length = prepared.s_end - prepared.s0
        res: Integration = integration or integrate(
            field, prepared.grid, start, prepared.x_end, p.beta, p.epsilon, max_steps=int(4 * (length + 20.0) / p.beta),
            t0=t0, speed=max(v0, 0.5 * self.v_desired), heading=heading, step_times=steps, loop=self._loops().steps)
        times = steps if steps is not None and len(steps) else None
        xy = self.safe_smooth(res.xy, field.statics + field.movers, t0, times, field.path)
        goal = prepared.ends_path and res.reached
        if fair:
            xy = self.faired(xy, field.statics + field.movers, t0, times, heading, pin_end=goal)
        s, kappa, v = self.speed_plan(xy, self.v_desired, v0, goal, kappa_cap=np.inf if fair else self.kappa_max)
        return res, xy, s, kappa, v

    def plan(self, prepared: Prepared, start: np.ndarray, t0: float, v0: float,
             movers: Sequence[ObstacleState] = (), heading: float | None = None) -> GuidancePlan:
        """Integrate from start (2,) at time t0 and speed v0, with moving obstacles, and time the
        result. Movers that cross the route are yielded to where that is possible (``yielding``)."""
        field = prepared.field
        if movers:
            field = replace(field, movers=[self.actual_term(self.implicit(o), t0) for o in movers])
        start = self.check_clear(start, field.statics + field.movers, t0, "start")
        h = None if heading is None else np.array([np.cos(heading), np.sin(heading)])
        crossing = [o for o, term in zip(movers, field.movers) if term.crosses]
        yielded = self.yielding(prepared, field, start, t0, v0, h, movers, crossing) if crossing else None
        return self.within_grid(prepared, yielded or self._planned(prepared, field, start, t0, v0, h, movers))

    def within_grid(self, prepared: Prepared, plan: GuidancePlan) -> GuidancePlan:
        """plan, checked to lie within the stretch's field grid (``corridor`` m beside the route and
        2 m beyond every static obstacle's reach): the field and the obstacles are known only
        there, and eq. (xi_r)'s integration cannot leave it. A GuidanceError naming how far and
        where otherwise (the replan fails, the plan before stays). The steps after the integration
        (fairing, the tight path) are held near the integrated path; this is the check that they
        were."""
        beyond = _beyond_grid(prepared, plan.xy)
        k = int(np.argmax(beyond))
        if not beyond[k] <= 0.0:
            xmin, xmax, ymin, ymax = prepared.grid.bounds
            raise GuidanceError(f"the plan leaves the field's grid: {beyond[k]:.1f} m beyond it at "
                                f"{plan.xy[k].round(1).tolist()} (grid x {xmin:.1f}..{xmax:.1f}, "
                                f"y {ymin:.1f}..{ymax:.1f})")
        return plan

    def _planned(self, prepared: Prepared, field: GuidanceField, start: np.ndarray, t0: float, v0: float,
                 h: np.ndarray | None, movers: Sequence[ObstacleState], may_follow: bool = True) -> GuidancePlan | None:
        """The field's plan with ``field``'s movers (``movers`` their states): integrated, placed at the
        last pass's times, then slowed to follow a mover it cannot pass (None instead without
        ``may_follow``), or made tight."""
        passes = MOVER_PASSES if movers else 0
        res, xy, s, kappa, v = self._integrate_and_time(field, prepared, start, t0, v0, h, None, fair=passes == 0)
        steps = None
        for k in range(passes):     # place moving obstacles at the last pass's times; fair the last two
            before, steps = steps, step_times(s, v, t0, self.params.beta)
            same = before is not None and np.array_equal(steps, before)     # the same integration again
            res, xy, s, kappa, v = self._integrate_and_time(field, prepared, start, t0, v0, h, steps,
                                                            fair=k >= passes - 2, integration=res if same else None)
        trajectory = timed_trajectory(xy, s, v, t0, self.dt)
        if field.movers and (self.meets_mover(field.movers, trajectory, FOLLOW_SLACK)
                             or self.touches_mover(movers, trajectory)):
            if not may_follow:
                return None
            lane = self._integrate_and_time(replace(field, movers=[]), prepared, start, t0, v0, h, None)
            slower = self.followed(field.movers, [(lane[1], _stops(lane[4])), (xy, _stops(v))], t0, v0, movers)
            if slower is None:
                slower = self.merged_later(prepared, movers, lane, t0, v0, h)
            if slower is not None:
                if slower[0] is lane[1]:
                    res = lane[0]
                xy, s, kappa, v, trajectory = slower
        else:       # a path the field found to pass: as tight as the clearances let it
            tight = self.tightened(prepared, movers, xy, s, v, t0, v0, h, prepared.ends_path and res.reached)
            if tight is not None:
                xy, s, kappa, v = tight
                trajectory = timed_trajectory(xy, s, v, t0, self.dt)
        return GuidancePlan(trajectory=trajectory, xy=xy, s=s, kappa=kappa, v=v, raw=res.xy,
                            reached=res.reached, inherited=res.inherited, field=field, gammas=res.gammas,
                            virtual_off=res.virtual_off)

    def merged_later(self, prepared: Prepared, movers: Sequence[ObstacleState], lane, t0: float, v0: float,
                     h: np.ndarray | None):
        """A car passing a slower one whose route turns back into its lane (a merge, the end of an
        overtake) cannot fall behind it by braking beside it, and the lane (``lane``:
        ``_integrate_and_time``'s result without the movers) cuts in ahead of it: the plan, when no
        slower one keeps clear of the movers, goes on along the start's line at full speed and joins
        the lane only where the movers, taken ``tight_mover_window`` s before and after, leave the
        body their tight clearance (no less than it has now) all along, within the field's grid.
        The join is a quintic blend long enough to keep half of kappa_max and of the lateral
        acceleration limit at full speed (``JOIN_CURVATURE``; the lane's own bends add to it); the
        joins are tried every ``JOIN_STEP`` m, nearest first; when none does, the start's line braked to rest (``_held``). (xy, s, kappa,
        v, trajectory) like ``followed``'s, or None when neither keeps clear, or the lane does not
        leave the start's line."""
        _, lane_xy, lane_s, _, _ = lane
        ahead = h if h is not None else lane_xy[1] - lane_xy[0]
        line = lane_xy[0] + np.outer(lane_s, ahead / np.linalg.norm(ahead))       # the start's line
        apart = np.linalg.norm(line - lane_xy, axis=1)
        if not np.any(apart > CLEAR_TOLERANCE):
            return None
        keepouts = (self.mover_keepouts([o for o in movers if o.moving])
                    + [Keepout(o, self.tight_clearance(o)) for o in prepared.statics])
        bend = min(self.kappa_max, self.a_lat_max / self.v_desired ** 2) / 2.0    # the join's own, at full speed
        for join in np.arange(JOIN_STEP, lane_s[-1], JOIN_STEP):
            k = int(np.searchsorted(lane_s, join))
            length = max(JOIN_STEP, float(np.sqrt(JOIN_CURVATURE * np.max(apart[k:]) / bend)))
            u = np.clip((lane_s - join) / length, 0.0, 1.0)
            w = (u ** 3 * (10.0 - 15.0 * u + 6.0 * u * u))[:, None]
            xy = (1.0 - w) * line + w * lane_xy
            if np.max(_beyond_grid(prepared, xy)) > 0.0:       # the plan must stay on the field's grid (``within_grid``)
                continue
            s, kappa, v, trajectory = self.timed(xy, self.v_desired, v0, t0, _stops(lane[4]))
            if not self.keeps_limits(kappa, v) or np.max(np.abs(kappa)) > self.kappa_max * (1 + DRIVABLE_ROUNDING):
                continue
            if self._keeps_clear(keepouts, movers, trajectory):
                return xy, s, kappa, v, trajectory
        return self._held(prepared, movers, keepouts, line, t0, v0)

    def _held(self, prepared: Prepared, movers: Sequence[ObstacleState], keepouts: Sequence[Keepout],
              line: np.ndarray, t0: float, v0: float):
        """``merged_later``'s last resort when no join keeps clear: the start's line braked to rest
        before the first static obstacle on it (or the field's grid's edge), so the slower car
        goes by beside and the next plan joins behind it. (xy, s, kappa, v, trajectory), or None
        when that stop does not keep clear either."""
        statics = [k for k in keepouts if not k.obstacle.moving]
        free = disc_gaps(line, self.body, statics) if statics else np.full(len(line), np.inf)
        ahead = (free >= min(0.0, float(free[0])) - CLEAR_TOLERANCE) & (_beyond_grid(prepared, line) <= 0.0)
        end = int(np.argmin(ahead)) if not np.all(ahead) else len(line)
        if end < 3:
            return None
        xy = line[:end]
        s, kappa, v, trajectory = self.timed(xy, self.v_desired, v0, t0, True)
        return (xy, s, kappa, v, trajectory) if self._keeps_clear(keepouts, movers, trajectory) else None

    def _keeps_clear(self, keepouts: Sequence[Keepout], movers: Sequence[ObstacleState], trajectory: Trajectory) -> bool:
        """Whether the timed trajectory keeps the keepouts' clearances, no less than at its start,
        and lets the body into no mover."""
        gaps = disc_gaps(trajectory.pos, self.body, keepouts, trajectory.t)
        return np.min(gaps) >= min(0.0, float(gaps[0])) - CLEAR_TOLERANCE and not self.touches_mover(movers, trajectory)

    def _yield_caps(self, s: np.ndarray, entry: float, across: float, v0: float):
        """The speed caps (K,) over arc lengths s that ``yielding`` tries, with the deceleration the
        speed plan brakes at, comfortable ones first; each holds until ``across`` (the path has crossed
        the mover's line) and is free after it: for each of ``FOLLOW_SPEEDS`` of
        v_desired the slow speed reached at ``entry`` by an even deceleration from v0 (v^2 falling
        linearly with s: the gentlest), and the same slow speed from the start (braked to at
        a_decel: the earliest); then the slow speeds from the start braked to at ``a_yield``, where
        no comfortable plan yields (a walker close ahead of a fast car)."""
        p, v_d = self.params, self.v_desired
        before = s < across
        for f in FOLLOW_SPEEDS:
            slow2 = (f * v_d) ** 2
            if v0 * v0 > slow2:
                ramp = np.sqrt(np.maximum(slow2, v0 * v0 - (v0 * v0 - slow2) * s / max(entry, 1e-9)))
                yield np.where(before, np.minimum(ramp, v_d), v_d), p.a_decel
            yield np.where(before, f * v_d, v_d), p.a_decel
        if p.a_yield > p.a_decel:
            for f in FOLLOW_SPEEDS:
                yield np.where(before, f * v_d, v_d), p.a_yield

    def yielding(self, prepared: Prepared, field: GuidanceField, start: np.ndarray, t0: float, v0: float,
                 h: np.ndarray | None, movers: Sequence[ObstacleState], crossing: Sequence[ObstacleState]):
        """The plan that yields to the movers crossing the route: planned as if they were not there
        (no swerve round them) and taken as it is when its timed trajectory meets no crossing
        mover; else slowed (``_yield_caps``, comfortable first) from its start until its path has
        crossed the line of motion of the first crosser it meets (then of that one and the next,
        ...), until its timed trajectory meets no crossing mover and comes no closer to the others
        than the unslowed plan (or than their tight clearance); beyond that line it speeds up
        again. None when the plan must follow another mover or no slowing yields (the field's plan
        passes behind the crossers then)."""
        ids = {o.id for o in crossing}
        others = [o for o in movers if o.id not in ids]
        own = replace(field, movers=[term for term in field.movers if term.implicit.name not in ids])
        plan = self._planned(prepared, own, start, t0, v0, h, others, may_follow=False)
        if plan is None:
            return None                  # it must follow another mover: the field's plan decides
        crossers = [term for term in field.movers if term.implicit.name in ids]
        near = [Keepout(o, self.tight_clearance(o)) for o in others]
        if near:                # slowed, it comes no closer to the others than the plan does (or their clearance)
            floor = min(0.0, self.least_gap(plan.trajectory, near)) - CLEAR_TOLERANCE
        if not self.meets_mover(crossers, plan.trajectory):
            return replace(plan, field=field)
        spans = _crossing_spans(plan.xy, plan.s, [term.implicit for term in crossers], t0)
        first = next((k for k, (_, _, i) in enumerate(spans) if self.meets_mover([crossers[i]], plan.trajectory)), 0)
        for entry, across, _ in spans[first:]:          # through the first crosser met, then the next
            for cap, a_decel in self._yield_caps(plan.s, entry, across, v0):
                s, kappa, v = self.speed_plan(plan.xy, cap, v0, _stops(plan.v), a_decel=a_decel)
                trajectory = timed_trajectory(plan.xy, s, v, t0, self.dt)
                if self.meets_mover(crossers, trajectory):
                    continue
                if near and self.least_gap(trajectory, near) < floor:
                    continue
                return replace(plan, trajectory=trajectory, s=s, kappa=kappa, v=v, field=field)
        return None
