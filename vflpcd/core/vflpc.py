"""VF-LPC, paper Algorithm 1, as one steppable ``Controller``.

Every ``step(state, t, obstacles)``:
1. checks the input (finite state; obstacles with finite centres and velocities);
2. guidance (``Main``, lines "reaching the end of the guiding trajectory"): plans the GVF
   reference at once when none exists; a replan that is due (fewer than N dt + end_margin seconds
   of reference left, or the obstacle picture changed: an obstacle appeared, went or changed
   velocity) is handed out as a worker job (below), planned from the robot's state; a plan that
   arrives late is re-timed from the robot (``GuidancePlanner.splice``); a failed replan keeps
   the previous reference and is counted;
3. builds the horizon problem in the lifted error space (``error_model``), with the GP
   correction when an online compensator has a model;
4. switches the barrier on for every moving obstacle in the pursuer-evader region E_p (``game_region``;
   mu_o = 0 in E_c), at most ``max_threats`` of them, nearest first (``barrier``);
5. solves with the horizon solver (Eb-RHRL by default, warm-started from the previous tick's
   shifted weights; in the increment form of ``rate.py`` when ``r_rate`` is configured) and
   applies the first control u = u_r,0 + u~_0, clipped into the actuator magnitude and rate limits;
6. a solve that returns a non-finite command, or one beyond ``divergence`` times the actuator
   range, is counted in ``fallbacks`` and the solver's weights are reset; the last plan solved goes
   on in its place, a step a tick, and when its steps are spent the terminal LQR law
   u~ = -K_P x~ (K_P from the DARE that gives P).

GP samples are offered to the compensator every model step (``OnlineCompensator.observe``, cheap;
when the control period is a fraction 1/k of the model's dt, every k-th tick); the refit is worker
work too, run when due (``vflpcd.core.jobs.run_inline`` after each timed step offline).

Worker work as jobs (the daemon's workers, possibly in another process): ``take_replan()`` hands
out the due replan as a picklable ``ReplanJob``, ``plan_job(planner, job)`` runs it anywhere, and
``install_plan(job, result)`` (or ``replan_failed``) takes the result back between two ticks;
``take_refit()`` / ``refit_job`` / ``install_model`` do the same for the GP refit
(``WorkerJobs`` of ``vflpcd.core.ports``; ``vflpcd.core.jobs.run_inline`` is these steps in sequence).
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, replace
from typing import Protocol, Sequence

import numpy as np

from vflpcd.core.control.barrier import HorizonBarrier
from vflpcd.core.control.ebrhrl import EbRHRL, KernelFeatures
from vflpcd.core.control.error_model import ErrorModel, Limits, TickFrame
from vflpcd.core.control.game_region import threat_at
from vflpcd.core.control.horizon_reference import HorizonReference
from vflpcd.core.control.problem import HorizonProblem
from vflpcd.core.control.rate import RateForm
from vflpcd.core.control.tick_horizon import CompiledHorizon, ProblemHorizon
from vflpcd.core.dynamics.compensation import OnlineCompensator, RefitJob
from vflpcd.core.dynamics.lifted import LiftedLinearModel, PoseLayout
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.guidance.speed import heading_curvature
from vflpcd.core.guidance.tighten import CLEAR_TOLERANCE
from vflpcd.core.guidance.trajectory import timed_trajectory
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.norms import vector_norm
from vflpcd.core.path import nearest_on_polyline, unit_differences
from vflpcd.core.ports import ControllerBase, ControllerStatus

log = logging.getLogger("vflpcd.core.vflpc")

COURSE_MIN_SPEED = 0.5   # m/s: below it a replan leaves along the yaw (the course of a slow body is noise)
# The light weights' plan is refused when more than this fraction of its steps ride the rate limit
# (VFLPC._solve_increments). Measured (one run each): racing_track's start, 0.19 rad off the route's
# heading, rides it at 7 of 20 steps (refused from 5 down: RMS lateral 0.037 m, kept: 0.029 m);
# following a slow car the light plans ride it at up to 20 of 20 steps, and kept they weaved round
# it (follow_slow_car J_MC 5.4, least clearance 0.40 m; 0.058 and 1.50 m with 7 or 10; 0.063 and 1.42 m
# with 12 or 15).
LIGHT_SATURATION = 0.5
# s between replans while the plan followed has a stretch beyond the robot's limits: the safety gate
# admits a plan whose look-ahead is drivable (``plan_job``'s last resort when no plan keeps the
# limits), and without a new obstacle or the plan's end nothing asked again, so the car drove on
# to that stretch and the failsafe stopped it there (a jittered follow_slow_car).
UNDRIVABLE_RETRY = 0.5
# The slow bands' hysteresis (VFLPC._cruise_at): a speed this far past its band's edge takes the
# next band's weights; within it the weights stay.
SLOW_HYSTERESIS = 0.1   # m/s
# A replan from inside an obstacle's region is planned from a point on the robot's way ahead
# (``_led_out``): tried every LEAD_STEP m up to LEAD_MAX m, the way sampled every LEAD_SPACING m;
# not below LEAD_SPEED_MIN m/s (a robot at rest there waits for the supervisor and the monitors).
LEAD_STEP, LEAD_MAX, LEAD_SPACING, LEAD_SPEED_MIN = 1.0, 12.0, 0.25, 0.5


@dataclass(frozen=True)
class ReplanJob:
    """A due guidance replan: path arc length s of the robot, its position pos (d,), velocity
    vel (d,), heading (rad, 2-D only) at time t, and the obstacles it was due for."""

    s: float
    pos: np.ndarray
    vel: np.ndarray
    heading: float | None
    t: float
    obstacles: tuple[ObstacleState, ...]


@dataclass(frozen=True)
class PlanResult:
    """A replan's outcome: the plan and whether its stretch ends the (open) path."""

    plan: object
    ends_path: bool


def slow_rate(params: VFLPCParams, control_names: Sequence[str], speed: float) -> np.ndarray:
    """``R_rate`` at ``speed`` below the light band: the weights of the inputs in ``speed_scaled``
    (the steering) times (speed / light_speeds[0])^4. A steering step delta changes the lateral
    acceleration by about v^2 delta / L, so this keeps the weight on the lateral jerk that R_rate
    puts on it at the band's lower speed; with R_rate's weight at 1.5 m/s the car followed its plan
    0.40 m off at the median and touched a post in dense_corridor (docs/results.md)."""
    scale = np.array([(speed / params.light_speeds[0]) ** 4 if n in params.speed_scaled else 1.0
                      for n in control_names])
    return params.R_rate * np.sqrt(np.outer(scale, scale))


def _band_of(bands, speed: float) -> int:
    """The first of the slow ``bands`` ((band speed, mode), increasing) whose speed is at least
    ``speed``; len(bands) above them all."""
    return next((i for i, (b, _) in enumerate(bands) if speed <= b), len(bands))


def plan_job(planner, job: ReplanJob) -> PlanResult:
    """Run a replan (worker side; raises GuidanceError when no plan exists). A plan beyond the
    robot's curvature limit, or whose body runs into a static obstacle's shape (``_usable``), is
    planned again by the planner's ``recovery`` (narrower margins) and then by the recovery's
    ``closers`` (its tight path at ``recovery_tight_margin``, then at ``least_tight_margin``); the
    first usable plan is taken, else the first plan stands when it keeps clear of the static
    obstacles (and the safety gate judges its limits), and no plan exists when it does not. A
    robot inside an obstacle's repulsive region (a tight path passes closer than the field's
    margin), or a plan that leaves the field's grid (``within_grid``), is planned for by the
    recovery at once (and by its closers when that plan is not usable)."""
    statics = [o for o in job.obstacles if not o.moving]
    narrow = planner.recovery()
    try:
        first, result = planner, _plan_once(planner, job)
    except GuidanceError as exc:    # the robot is inside a repulsive region (a tight path passes closer
        if narrow is None:              # than the field's margin), or the plan left the field's grid:
            raise                       # planned with the recovery's narrow margins
        log.info("event=recovery_plan t=%.2f margin=%.2f reason=%s", job.t, narrow.params.safety_margin, exc)
        try:
            first, result = narrow, _plan_once(narrow, job)
        except GuidanceError:          # the start is inside a region at the narrow margins too
            led = _led_out(narrow, job, statics)
            if led is None:
                raise
            return led
    if _usable(first, result, statics):
        return result
    fallbacks = () if narrow is None else ((narrow,) if narrow is not first else ()) + narrow.closers()
    return _first_usable(fallbacks, job, statics) or _clear(first, result, statics)


def _led_out(planner, job: ReplanJob, statics: Sequence[ObstacleState]) -> PlanResult | None:
    """For a robot inside an obstacle's region at every margin (beside a truck it passes close, on a
    tight path): its straight way ahead along its heading, at its speed, to the first point (every
    ``LEAD_STEP`` m, at most ``LEAD_MAX`` m on) from which ``planner`` plans, and that plan after it;
    the first such plan that is usable and keeps the body out of the movers' shapes, None when none
    is, or when the robot has no heading (2-D only) or is slower than ``LEAD_SPEED_MIN``. The replans beside a parked truck failed until the
    robot had passed it, and the failsafe braked it to rest there (a jittered double_lane_change)."""
    speed = float(np.linalg.norm(job.vel))
    if job.heading is None or speed < LEAD_SPEED_MIN:
        return None
    h = np.array([math.cos(job.heading), math.sin(job.heading)])
    movers = [o for o in job.obstacles if o.moving]
    for d in np.arange(LEAD_STEP, LEAD_MAX + 1e-9, LEAD_STEP):
        try:
            result = _plan_once(planner, replace(job, s=job.s + d, pos=job.pos + d * h, t=job.t + d / speed))
        except GuidanceError:
            continue
        plan = result.plan
        if abs(plan.v[0] - speed) > 1e-6:
            return None         # the way ahead is driven at the robot's speed: a plan that joins it
        lead_s = np.linspace(0.0, d, max(int(math.ceil(d / LEAD_SPACING)), 1) + 1)[:-1]
        xy = np.vstack([job.pos + lead_s[:, None] * h, plan.xy])
        s = np.concatenate([lead_s, d + plan.s])
        v = np.concatenate([np.full(len(lead_s), speed), plan.v])
        kappa = np.concatenate([np.zeros(len(lead_s)), plan.kappa])
        led = replace(plan, xy=xy, s=s, v=v, kappa=kappa, raw=np.vstack([xy[:len(lead_s)], plan.raw]),
                      trajectory=timed_trajectory(xy, s, v, job.t, planner.dt))
        if _usable(planner, PlanResult(led, result.ends_path), statics) and not planner.touches_mover(movers, led.trajectory):
            log.info("event=recovery_plan t=%.2f led_out_m=%.1f", job.t, d)
            return PlanResult(led, result.ends_path)
    return None


def _usable(planner, result: PlanResult, statics: Sequence[ObstacleState]) -> bool:
    """Whether the plan is drivable (``PlannerBase.drivable``) and keeps the body's covering discs out
    of the static obstacles' shapes (to ``CLEAR_TOLERANCE``): in a clutter of parked cars the field's
    paths ran into them (discs 0.6-1.0 m deep) while the route itself kept 0.18 m."""
    return planner.drivable(result.plan) and planner.static_gap(result.plan, statics) >= -CLEAR_TOLERANCE


def _first_usable(planners, job: ReplanJob, statics: Sequence[ObstacleState]) -> PlanResult | None:
    """The plan of the first of ``planners`` that finds a usable one for ``job`` (None if none does)."""
    for planner in planners:
        try:
            result = _plan_once(planner, job)
        except GuidanceError:
            continue
        if _usable(planner, result, statics):
            log.info("event=recovery_plan t=%.2f margin=%.2f tight_margin=%.2f", job.t,
                     planner.params.safety_margin, planner.params.tight_margin)
            return result
    return None


def _clear(planner, result: PlanResult, statics: Sequence[ObstacleState]) -> PlanResult:
    """The plan (beyond the limits: the safety gate judges it) when it keeps clear of the static
    obstacles; GuidanceError naming how deep it runs into one otherwise."""
    gap = planner.static_gap(result.plan, statics)
    if gap < -CLEAR_TOLERANCE:
        raise GuidanceError(f"every plan runs into a static obstacle (the body {-gap:.2f} m into its shape)")
    return result


def _plan_once(planner, job: ReplanJob) -> PlanResult:
    statics = [o for o in job.obstacles if not o.moving]
    movers = [o for o in job.obstacles if o.moving]
    prepared = planner.prepare(job.s, statics)
    speed = float(np.linalg.norm(job.vel))
    if job.heading is not None:
        plan = planner.plan(prepared, job.pos, job.t, speed, movers, heading=job.heading)
    else:
        plan = planner.plan(prepared, job.pos, job.t, speed, movers)
    return PlanResult(plan, bool(prepared.ends_path))


@dataclass(frozen=True)
class VFLPCParams:
    """The numbers of config/controllers/vflpc.toml for one platform (see that file)."""

    Q_x: np.ndarray
    R: np.ndarray
    q_lift: float
    gamma: float
    horizon_s: float
    i_max: int
    tol: float
    eta_a: float
    divergence: float
    error_std: np.ndarray
    samples: int
    size: int
    nu: float
    ell_factor: float
    seed: int
    mu: float
    barrier_length: float
    l_safe: float
    max_threats: int
    end_margin: float
    velocity_change: float
    join_tolerance: float = 0.5
    stale_distance: float = 1.0
    refit_every: int = 100
    refit_min_samples: int = 60
    R_rate: np.ndarray | None = None
    R_rate_threat: np.ndarray | None = None
    R_rate_light: np.ndarray | None = None
    light_hold: float = 2.0
    light_speeds: tuple[float, float] = (0.0, np.inf)
    light_offsets: tuple[float, float] = (np.inf, np.inf)
    slow_speeds: tuple[float, ...] = ()
    speed_scaled: tuple[str, ...] = ()
    command_increments: tuple[str, ...] = ()
    gp_channels: tuple[str, ...] = ("Y", "psi", "vx", "vy", "omega")
    gp_ell: float = 3.0
    gp_sf2: float = 0.05
    gp_sn2: float = 1e-4
    gp_nu: float = 0.05
    gp_m_max: int = 48
    gp_n_max: int = 400
    gp_linearisation: str = "nominal"
    gp_bounds: tuple[tuple[float, float], ...] = ((1e-6, 0.1), (0.3, 10.0), (1e-6, 1e-3))   # sf2, ell, sn2
    vehicle_params: str = "nominal"     # the car's parameter set the controller knows (its body's slip)



def _check_obstacles(obstacles: Sequence[ObstacleState], dim: int) -> None:
    """Raise ValueError unless every obstacle's centre and velocity are ``dim`` finite numbers."""
    for o in obstacles:
        if (o.center.shape != (dim,) or o.velocity.shape != (dim,)
                or not all(map(math.isfinite, o.center.tolist() + o.velocity.tolist()))):
            raise ValueError(f"obstacle {o.id!r}: centre and velocity must be {dim} finite numbers")


def _velocities(obstacles: Sequence[ObstacleState]) -> dict[str, list[float]]:
    """The obstacle picture a replan is made for: each obstacle's velocity by id (floats)."""
    return {o.id: o.velocity.tolist() for o in obstacles}


class HorizonSolver(Protocol):
    """What VF-LPC needs of a horizon solver (Eb-RHRL or a baseline QP)."""

    def solve(self, problem: HorizonProblem, barrier: HorizonBarrier | None): ...

    def shift(self) -> None: ...

    def reset(self) -> None: ...


def rl_features(model: LiftedLinearModel, error_std: np.ndarray, v_max: float, samples: int, size: int,
                nu: float, ell_factor: float, seed: int, u_std: np.ndarray | None = None) -> KernelFeatures:
    """The RL dictionary: physical errors ~ N(0, error_std) at random reference states (speed up to
    v_max along the body x, small rates), lifted, with control deviations ~ N(0, u_std) appended
    for the increment form; ALD over them, length scales ell_factor * std."""
    rng = np.random.default_rng(seed)
    ref = np.zeros((samples, model.n_x))
    names = model.state_names
    if "vx" in names:
        ref[:, names.index("vx")] = rng.uniform(0.0, v_max, samples)
    if "omega" in names:
        ref[:, names.index("omega")] = rng.uniform(-0.3, 0.3, samples)
    x = ref + rng.normal(size=ref.shape) * error_std
    err = (model.lift(x) - model.lift(ref))[:, :-1]
    if u_std is not None:
        err = np.hstack([err, rng.normal(size=(samples, len(u_std))) * u_std])
    ell = ell_factor * np.maximum(err.std(axis=0), 1e-3)
    return KernelFeatures.from_samples(err, ell, nu, size)


class VFLPC(ControllerBase):
    """Algorithm 1 (module docstring). ``planner``: a guidance planner (2-D or 3-D) on the
    reference path; ``model``: the lifted Koopman model; ``limits``: actuator limits (per step
    for the rate); ``body_radius`` and ``safety_margin``: the safety distance of the barrier and
    the game region; ``solver``: a horizon solver (default: Eb-RHRL); ``compensator``: the online
    GP (None: w/o ML); ``state_names``: the platform's state order (default the model's), of which
    the model's states are picked by name (the quadrotor's 13 -> X, Y, Z, vx, vy, vz). It follows
    a plan of its own (``planning`` is itself, for the safety monitors) and has background work
    (``jobs`` is itself: replans and GP refits, ``WorkerJobs``)."""

    name = "vflpc"

    def __init__(self, planner, model: LiftedLinearModel, params: VFLPCParams, limits: Limits,
                 body_radius: float, safety_margin: float, solver: HorizonSolver | None = None,
                 compensator: OnlineCompensator | None = None, name: str = "vflpc",
                 state_names: Sequence[str] | None = None, period: float | None = None, solve_loop=None,
                 path_loop=None, problem_loop=None, tick_loops=None) -> None:
        self.planner, self.model, self.params, self.limits = planner, model, params, limits
        """``period``: the control tick period (default the model's dt); ``limits.du_max`` is per tick;
        ``solve_loop``: Eb-RHRL's iterations compiled (``EbRHRL``'s ``loop``; None: its numpy path);
        ``path_loop``: the path projection's search compiled (``ReferencePath.arc_length_of``'s ``loop``);
        ``problem_loop``: the horizon of a scheduled model compiled (``ErrorModel``'s ``problem_loop``);
        ``tick_loops``: the tick's window and nominal linearisation compiled (``ErrorModel``'s)."""
        self._path_loop = path_loop
        self._command_loop = tick_loops.command if tick_loops is not None else None
        self._reference_loop = tick_loops.reference if tick_loops is not None else None
        self.state_names = tuple(state_names) if state_names is not None else tuple(model.state_names)
        missing = [n for n in model.state_names if n not in self.state_names]
        if missing:
            raise ValueError(f"the platform state {self.state_names} lacks the model's {missing}")
        select = [self.state_names.index(n) for n in model.state_names]
        self._select = np.array(select) if select != list(range(len(self.state_names))) else None   # None: all, in order
        self.name = name
        self.dt = model.dt
        self.period = float(period) if period is not None else self.dt
        every = self.dt / self.period
        if self.period <= 0 or (compensator is not None and abs(every - round(every)) > 1e-6):
            raise ValueError(f"the control period {self.period} s must divide the model step {self.dt} s "
                             f"for the GP to learn model-step transitions")
        self._observe_every = max(1, int(round(every)))
        self.N = max(1, int(round(params.horizon_s / self.dt)))
        self._horizon_offsets = self.dt * np.arange(self.N + 1)     # tau dt, tau = 0 .. N
        self._body = planner.body
        self._road_bend = None                    # the route's bend at its points, for _road_slip
        if self._body.slips:
            limit = planner.kappa_limit
            self._road_bend = np.clip(heading_curvature(planner.path.points), -limit, limit)
        self.dim = planner.dim
        names, layout = model.state_names, PoseLayout.of(model.state_names)
        self._pos_index = np.array(layout.position)
        first, count = layout.position[0], len(layout.position)
        runs_on = tuple(layout.position) == tuple(range(first, first + count))
        self._pos_slice = slice(first, first + count) if runs_on else self._pos_index     # a view where they run on
        d = planner.dim                 # the barrier without a threat: zero (its reference positions are not used)
        self._no_threat = HorizonBarrier(self._pos_index, np.zeros((self.N + 1, d)), np.zeros((0, self.N + 1, d)),
                                         np.zeros((0, self.N + 1, d)), np.zeros(0))
        if layout.kind == "planar":                     # heading, body velocities
            self._vel_index = (layout.heading, names.index("vx"), names.index("vy"))
        else:                                           # world velocities
            self._vel_index = tuple(names.index(n) for n in ("vx", "vy", "vz")[: self.dim])
        span = limits.u_max - limits.u_min        # a first command beyond this bound is a divergence (_solve_with)
        self._divergence_bound = (params.divergence * np.where(np.isfinite(span), span, 1e6)).tolist()
        if model.scheduled and model.schedule != "vx":
            raise ValueError(f"VF-LPC schedules a model's input matrix on the speed vx, not {model.schedule!r}")
        self.errors = em = ErrorModel(model, params.Q_x, params.q_lift, params.R, params.gamma, self.N, limits,
                                      compensator.comp if compensator is not None else None,
                                      gp_jacobians=params.gp_linearisation == "gp",
                                      schedule_at=planner.v_desired if model.scheduled else None,
                                      problem_loop=problem_loop, tick_loops=tick_loops)
        unknown = set(params.command_increments) - set(model.control_names)
        if unknown:
            raise ValueError(f"command_increments: {', '.join(sorted(unknown))} is not an input of the model "
                             f"{model.control_names}")
        self._command = np.array([n in params.command_increments for n in model.control_names])
        self.rate = None
        self._threat_mode = None      # (rate form, solver) while a mover is in E_p (R_rate_threat)
        self._light_mode = None       # (rate form, solver) while its plans keep the rate limit (R_rate_light)
        self._slow_modes: tuple = ()  # (band speed, (rate form, solver)) below the light band (``slow_rate``)
        if solver is None:
            increment_loop = tick_loops.increment if tick_loops is not None else None
            u_std = None
            A, B, Q, R, P = em.A, em.B, em.Q, em.R, em.P
            if params.R_rate is not None:
                self.rate = rf = RateForm.of(em.A, em.B, em.Q, em.R, params.R_rate, em.gamma, self._command,
                                             increment_loop)
                A, B, Q, R, P = rf.A, rf.B, rf.Q, rf.R, rf.P
                span = limits.u_max - limits.u_min
                u_std = 0.25 * np.where(np.isfinite(span), span, 1.0)
            feats = rl_features(model, params.error_std, planner.v_desired, params.samples, params.size,
                                params.nu, params.ell_factor, params.seed, u_std)
            solver = EbRHRL(A, B, Q, R, P, em.gamma, feats, self.N, params.eta_a, params.i_max, params.tol,
                            loop=solve_loop)
            def mode(R_rate):
                rf = RateForm.of(em.A, em.B, em.Q, em.R, R_rate, em.gamma, self._command, increment_loop)
                return rf, EbRHRL(rf.A, rf.B, rf.Q, rf.R, rf.P, em.gamma, feats, self.N, params.eta_a,
                                  params.i_max, params.tol, loop=solve_loop)
            if self.rate is not None and params.R_rate_threat is not None:
                self._threat_mode = mode(params.R_rate_threat)
            if self.rate is not None and params.R_rate_light is not None:
                self._light_mode = mode(params.R_rate_light)
            if self.rate is not None and params.speed_scaled:
                self._slow_modes = tuple((v, mode(slow_rate(params, model.control_names, v)))
                                         for v in params.slow_speeds if v < params.light_speeds[0])
        self.solver, self.compensator = solver, compensator
        self._cruise_mode = (self.rate, solver)
        self._tick_horizon = (CompiledHorizon(em) if CompiledHorizon.applies(em)
                              else ProblemHorizon(em, self._command_loop))
        self.plan_gate = None          # set by the safety guard (vflpcd.core.safety): refuses undrivable replans
        self.planning, self.jobs = self, self
        self.body_radius, self.safety_margin = float(body_radius), float(safety_margin)
        self.reset()

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        for m in (self._threat_mode, self._light_mode, *(m for _, m in self._slow_modes)):
            if m is not None:
                m[1].reset()
        self.rate, self.solver = self._cruise_mode
        self._threatened = False
        self._band = len(self._slow_modes)      # the cruise weights' slow band (``_cruise_at``; the last: none)
        self._heavy_until = -np.inf     # the light mode is left until then (its last plan rode the rate limit)
        self._light = False
        self.solver.reset()
        self._plan = None
        self._horizon = None            # the plan's reference rows (_reference_rows)
        self._ends_path = False
        self._ticks = 0
        self._signature: dict[str, list[float]] = {}
        self._s = None
        self._unprojected = None        # the last step's position, not yet projected (``_arc_length``)
        self._unguided = None           # the last step's inputs, not yet checked for a replan (``_guide``)
        self._u_prev: np.ndarray | None = None
        self._last: tuple[TickFrame, np.ndarray] | None = None
        self._sample: tuple[tuple[TickFrame, np.ndarray], TickFrame] | None = None   # for ``settle``
        self._unshifted = None          # the solver whose weights ``settle`` shifts
        self._since_refit = 0
        self._pending: ReplanJob | None = None
        self._asked: tuple[ReplanJob, dict[str, np.ndarray], int] | None = None
        self._last_inputs = None
        self._t_last: float | None = None       # the time of the last step
        self.fallbacks = 0
        self._held: np.ndarray | None = None     # the last plan ``_solve`` solved, and the tick it was solved at
        self._held_tick = 0
        self._retry_at = np.inf         # when a replan is asked again for a plan beyond the limits (UNDRIVABLE_RETRY)
        self.replans = 0
        self.replan_failures = 0
        self.stale_replans = 0
        self.last_info = None
        self.last_threats: tuple[str, ...] = ()
        self.refits = 0

    def prepare(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> None:
        """Plan the first reference now if there is none (the daemon does it before its first
        tick; ``step`` does it otherwise). Raises GuidanceError when no plan exists."""
        if self._plan is None:
            state, obstacles, pos, vel = self._inputs(state, obstacles)
            self._guidance(pos, vel, state, t, obstacles)

    def step(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> np.ndarray:
        self.settle()                   # a sample that nobody settled after the last step
        state, obstacles, pos, vel = self._inputs(state, obstacles)
        self._t_last = float(t)
        if self._plan is None:          # no reference yet: planned at once
            self._guidance(pos, vel, state, t, obstacles)
        else:                           # whether a replan is due: after the command (``_guide``)
            self._unguided = (pos, vel, state, t, obstacles)
        ref = self._reference(t)
        frame = self.errors.frame(state, ref)
        observe_now = self._ticks % self._observe_every == 0
        self._ticks += 1
        u_prev = self._u_prev if self._u_prev is not None else np.clip(np.zeros(self.model.n_u), self.limits.u_min,
                                                                          self.limits.u_max)
        gp = self.compensator.model if self.compensator is not None else None
        horizon = self._tick_horizon.begin(frame, u_prev, gp)
        barrier = self._barrier(frame, ref, pos, vel, t, obstacles)
        speed = vector_norm(vel)
        self._select_mode(speed)
        if self.rate is not None:
            u = self._solve_increments(horizon, barrier, t, speed, frame)
        else:
            u = horizon.command(None, self._solve(horizon, None, barrier))
        self._unshifted = self.solver           # its warm start shifted in ``settle``
        self._u_prev = u
        if observe_now:
            if self.compensator is not None and self._last is not None:
                self._sample = (self._last, frame)
            self._last = (frame, u)
        return u

    def settle(self) -> None:
        """Shift the last step's solver's weights one step along the horizon (its warm start for the
        next tick), check whether a replan is due (``_guide``), find the path's arc length of its
        position (``_arc_length``), and offer the transition the last step saw (the previous sampled
        lifted state, the command applied there, the current state in that window frame) to the GP:
        work the command does not wait for, done after it is sent (``ControllerBase.settle``), else at
        the next step's start.
        The GP of a step is the one before its own transition's sample (the sample is folded in
        before the next step), and the command goes out without waiting for the sample's lift,
        residual, dictionary test and rank-one update (a quarter of a learning tick)."""
        solver, self._unshifted = self._unshifted, None
        if solver is not None:
            solver.shift()
        self._guide()
        self._arc_length()
        sample, self._sample = self._sample, None
        if sample is not None:
            self._observe(*sample)

    def reference_at(self, t: float) -> np.ndarray | None:
        """The current plan's reference position (d,) at time t; None before the first plan."""
        if self._plan is None:
            return None
        return self._plan.trajectory.sample(np.array([t]))["pos"][0]

    @property
    def current_plan(self):
        """The plan being followed (a ``GuidancePlan``), None before the first."""
        return self._plan

    def status(self) -> ControllerStatus:
        return ControllerStatus(self.replans, self.replan_failures, self.refits, self.fallbacks, self.last_threats,
                                self.stale_replans)

    # ------------------------------------------------------------------ worker jobs (WorkerJobs)
    def take_replan(self, force_at: float | None = None) -> ReplanJob | None:
        """The due replan, handed out once (None when none is due). ``force_at``: a time t at which
        a replan is wanted even if none is due (a periodic refresh): it is made from the last state."""
        self._guide()
        job, self._pending = self._pending, None
        if job is None and force_at is not None:
            job = self._fresh_job(float(force_at))
        return job

    def _fresh_job(self, t: float) -> ReplanJob | None:
        """A replan at time t from the last state and obstacles seen (None before the first step)."""
        if self._last_inputs is None:
            return None
        pos, vel, heading, obstacles = self._last_inputs
        return ReplanJob(self._arc_length(), pos, vel, heading, t, obstacles)

    def install_plan(self, job: ReplanJob, result: PlanResult) -> None:
        """Take a finished replan (between two ticks); the next step uses it, joined to the robot
        (``_joined``). A stale replan is set aside (counted in ``stale_replans`` and asked again at
        once from the present state; no planning failure: the old plan stays, and where it ends the
        robot stops, from where the next plan is not stale); a replan that ``plan_gate`` refuses is a
        failed one (the previous plan stays)."""
        self._guide()                   # the last step's check first, as it ran before this install
        plan = self._joined(job, result.plan)
        if plan is None:
            self.stale_replans += 1
            fresh = self._fresh_job(self._t_last)
            if fresh is not None:
                self._ask(fresh)
            return
        if self.plan_gate is not None and self._plan is not None:
            refused = self.plan_gate(plan)
            if refused is not None:
                self.replan_failed(job, f"refused: {refused}")
                return
        self._plan, self._ends_path = plan, result.ends_path
        now = job.t if self._t_last is None else self._t_last
        self._retry_at = np.inf if self.planner.drivable(plan) else now + UNDRIVABLE_RETRY
        self._horizon = self._reference_rows(plan)      # between ticks, not in the next tick
        self._signature = _velocities(job.obstacles)
        if self._asked is not None and self._asked[0] is job:
            self._asked = None              # the newest picture asked for is the one now planned
        self.replans += 1

    def _joined(self, job: ReplanJob, plan):
        """A finished plan checked against the robot at the last tick, for one that arrives late
        (the robot did not drive as it assumed while the worker planned): None (stale) when its
        path lies farther than ``stale_distance`` from the robot; re-timed from the robot
        (``GuidancePlanner.splice``) when its reference lies farther from the robot than
        ``join_tolerance`` and than the old reference does, unless the re-timed plan would meet a
        moving obstacle (then it keeps the timing it was planned with, clear of them)."""
        if self._plan is None or self._t_last is None:
            return plan
        pos, vel = self._last_inputs[0], self._last_inputs[1]
        off = nearest_on_polyline(pos, plan.xy)[0]
        if off > self.params.stale_distance:
            log.warning("event=replan_stale t=%.2f job_t=%.2f reason=the robot is %.2f m from its path",
                        self._t_last, job.t, off)
            return None
        t = np.array([self._t_last])
        d_new = float(np.linalg.norm(plan.trajectory.sample(t)["pos"][0] - pos))
        d_old = float(np.linalg.norm(self._plan.trajectory.sample(t)["pos"][0] - pos))
        if d_new > max(self.params.join_tolerance, d_old):
            return self.planner.splice(plan, pos, float(np.linalg.norm(vel)), self._t_last) or plan
        return plan

    def replan_failed(self, job: ReplanJob, reason: str) -> None:
        """A replan found no plan: the previous reference stays; counted and logged."""
        self._guide()                   # the last step's check first, as it ran before this news
        self.replan_failures += 1
        log.warning("event=replan_failed t=%.2f reason=%s", job.t, reason)

    def take_refit(self) -> RefitJob | None:
        """The GP refit when enough samples have come in since the last one (None otherwise)."""
        c = self.compensator
        if c is None or self._since_refit < self.params.refit_every or c.n_buffered < self.params.refit_min_samples:
            return None
        job = c.refit_job()
        if job is not None:
            self._since_refit = 0
        return job

    def install_model(self, job: RefitJob, model) -> None:
        """Take a finished GP refit (between two ticks)."""
        self.compensator.install(job, model)
        self.refits += 1

    # ------------------------------------------------------------------ pieces
    def _inputs(self, state: np.ndarray, obstacles: Sequence[ObstacleState]):
        """Checked model state, obstacles, position and velocity; remembers them for a forced replan."""
        state = np.asarray(state, float)
        values = state.tolist() if state.shape == (len(self.state_names),) else None
        if values is None or not all(map(math.isfinite, values)):
            raise ValueError(f"state must be {len(self.state_names)} finite numbers {self.state_names}, got {state!r}")
        if self._select is not None:
            state = state[self._select]
            values = state.tolist()
        else:
            state = state.copy()
        obstacles = tuple(obstacles)
        if obstacles:
            _check_obstacles(obstacles, self.dim)
        pos, vel = state[self._pos_slice], self._velocity(values)
        self._unprojected = pos                 # its arc length when a replan asks for it, else in ``settle``
        heading = values[self.errors.layout.heading] if self.dim == 2 else None
        self._last_inputs = (pos, vel, heading, obstacles)
        return state, obstacles, pos, vel

    def _guide(self) -> None:
        """The last step's guidance check (``_guidance``), which the command does not wait for: run
        in ``settle``, or before a replan is taken, installed or reported failed, whichever comes
        first (in the order it ran in when it was part of the step)."""
        args, self._unguided = self._unguided, None
        if args is not None:
            self._guidance(*args)

    def _arc_length(self) -> float | None:
        """The path's arc length s of the last step's position (None before the first step),
        searched near the one before it (``ReferencePath.arc_length_of``): a replan's start. The
        command does not wait for it: it is found when a replan asks for it, else in ``settle``, so
        every step's position is projected once and in turn."""
        if self._unprojected is not None:
            self._s = self.planner.path.arc_length_of(self._unprojected, self._s, loop=self._path_loop)
            self._unprojected = None
        return self._s

    def _course(self, state: np.ndarray, vel: np.ndarray) -> float:
        """The direction a replan leaves the body along: its velocity's (the course angle) when it
        moves forward, else its yaw. In a bend the body slips (v_y != 0): a plan leaving along the yaw
        would bend back onto the course within its first metres, a curvature blip that the speed plan
        answers with a dip."""
        psi = float(state[self.errors.layout.heading])
        speed = float(np.hypot(vel[0], vel[1]))
        if speed < COURSE_MIN_SPEED or float(np.dot(vel, [np.cos(psi), np.sin(psi)])) <= 0.0:
            return psi
        return float(np.arctan2(vel[1], vel[0]))

    def _velocity(self, state) -> np.ndarray:
        """The world velocity (d,) of a model state (n_x,) (an array, or its values as a list)."""
        if self.errors.layout.kind == "planar":
            h, i, j = self._vel_index
            psi, vx, vy = float(state[h]), float(state[i]), float(state[j])
            c, s = math.cos(psi), math.sin(psi)
            return np.array([vx * c - vy * s, vx * s + vy * c])
        return np.array([float(state[i]) for i in self._vel_index])

    def _changed(self, obstacles: Sequence[ObstacleState]) -> bool:
        """Whether the obstacle picture differs (an obstacle appeared or went, or its velocity changed
        by more than velocity_change) from the newest one a replan was asked for: the job pending or
        being planned, else the installed plan's. So a replan is asked once per change, not once per
        tick while the worker plans it; an asked replan that has failed since (``replan_failures``
        grew) counts as not asked, and is asked again."""
        ref = self._signature
        if self._asked is not None and self._asked[2] == self.replan_failures:
            ref = self._asked[1]
        sig = _velocities(obstacles)
        if sig.keys() != ref.keys():
            return True
        return any(math.dist(sig[k], ref[k]) > self.params.velocity_change for k in sig)

    def _guidance(self, pos, vel, state, t: float, obstacles) -> None:
        """Replan now if there is no reference yet, else leave a due replan to ``background``: due
        when the obstacle picture changed (``_changed``), when the plan is about to run out, and every
        ``UNDRIVABLE_RETRY`` s while the plan followed has a stretch beyond the robot's limits."""
        plan = self._plan
        left = -np.inf if plan is None else plan.trajectory.t[-1] - t
        finished = plan is not None and plan.reached and self._ends_path
        due = plan is None or self._changed(obstacles) or t >= self._retry_at or (
            not finished and left < self.N * self.dt + self.params.end_margin)
        if not due:
            return
        if np.isfinite(self._retry_at):
            self._retry_at = t + UNDRIVABLE_RETRY
        heading = self._course(state, vel) if self.dim == 2 else None
        job = ReplanJob(self._arc_length(), pos, vel, heading, t, obstacles)
        if plan is None:
            self.install_plan(job, plan_job(self.planner, job))   # no reference yet: plan at once
        else:
            self._ask(job)

    def _ask(self, job: ReplanJob) -> None:
        """Hand ``job`` out at the next ``take_replan`` (the newest replaces any older one) and
        remember the obstacle picture it was asked for (``_changed``)."""
        self._pending = job
        self._asked = (job, _velocities(job.obstacles), self.replan_failures)

    def _reference(self, t: float) -> np.ndarray:
        """World reference states (N + 1, n_x) at t + tau dt, in the model's state order
        (``_reference_rows``; a buffer rewritten by the next tick)."""
        return self._horizon.at(t)

    def _reference_rows(self, plan) -> HorizonReference:
        """The plan's reference states at its trajectory's times, in the model's state order, as a
        ``HorizonReference`` (read at every tick). A car's heading and body velocities are those it
        has on the path at its steady slip in the road's bends (``_road_slip``): the path gives the
        course, the car's yaw lies beta off it. A quadrotor's velocity is the speed along the path's
        tangent."""
        traj = plan.trajectory
        if self.errors.layout.kind == "planar":
            psi, vx, vy = traj.psi, traj.v, np.zeros_like(traj.v)
            slip = self._road_slip(plan)
            if slip is not None:
                psi, vx, vy = psi - slip, traj.v * np.cos(slip), traj.v * np.sin(slip)
            cols = {"X": traj.pos[:, 0], "Y": traj.pos[:, 1], "psi": psi, "yaw": psi,
                    "vx": vx, "vy": vy, "omega": traj.omega}
        else:
            v = unit_differences(traj.pos) * traj.v[:, None] if len(traj.t) > 1 else np.zeros_like(traj.pos)
            cols = {"X": traj.pos[:, 0], "Y": traj.pos[:, 1], "Z": traj.pos[:, 2],
                    "vx": v[:, 0], "vy": v[:, 1], "vz": v[:, 2]}
        names = self.model.state_names
        rows = np.zeros((len(traj.t), self.model.n_x))
        for j, name in enumerate(names):
            if name in cols:
                rows[:, j] = cols[name]
        stopped = np.array([n in ("vx", "vy", "vz", "omega") for n in names])
        return HorizonReference(traj.t, rows, stopped, self.dt, self.N, self._reference_loop)

    def _road_slip(self, plan) -> np.ndarray | None:
        """The car's steady slip angle beta (rad, ``Body.slip_angle``) at each point of ``plan``'s
        trajectory, in the road's bend there (the route's curvature at the same distance along it)
        at the planned speed; None for a body that does not slip, or where the road is straight
        (the tick then skips it). The road's bend, not the plan's
        own curvature: with the plan's own, the slip of every swerve entered the reference heading
        (carsim_avoidance J_MC 1.62 -> 1.87, a supervisor intervention), where a bend held for
        seconds is driven at its steady slip (racing_track: 0.05 rad at 6 m/s). The road's bend is
        its heading's change over ``CURVATURE_WINDOW`` of arc (a corner of a polyline road is not a
        spike), at most the car's curvature limit. Computed once per plan, when it is installed."""
        if self._road_bend is None:
            return None
        traj, path = plan.trajectory, self.planner.path
        s0 = path.arc_length_of(traj.pos[0], self._arc_length())
        bend = np.interp(path.wrap_s(s0 + traj.s - traj.s[0]), path.s, self._road_bend)
        return self._body.slip_angle(bend, traj.v) if np.any(bend) else None

    def _select_mode(self, speed: float) -> None:
        """The increment weights of the tick: ``R_rate_threat`` while a mover threatens (the barrier
        is on: braking and swerving must not be slowed by the cruise smoothing), else ``R_rate``, or
        below the light band the slow band's (``_cruise_at``; the body's ``speed``, m/s). A switch
        starts the other solver afresh; the applied command stays continuous (u_prev)."""
        threatened = self._threat_mode is not None and bool(self.last_threats)
        rate, solver = self._threat_mode if threatened else self._cruise_at(speed)
        self._threatened = threatened
        if solver is self.solver:
            return
        self.rate, self.solver = rate, solver
        self.solver.reset()

    def _cruise_at(self, speed: float):
        """The cruise weights' (rate form, solver) at ``speed``: the first slow band whose speed is at
        least it (``slow_rate``), the plain ``R_rate`` above them; the band held while the speed
        stays within ``SLOW_HYSTERESIS`` of it."""
        bands = self._slow_modes
        if not bands or (self._band == len(bands) and speed - SLOW_HYSTERESIS > bands[-1][0]):
            return self._cruise_mode                # above the bands (the common case: one comparison)
        if not _band_of(bands, speed - SLOW_HYSTERESIS) <= self._band <= _band_of(bands, speed + SLOW_HYSTERESIS):
            self._band = _band_of(bands, speed)
        return bands[self._band][1] if self._band < len(bands) else self._cruise_mode

    def _offset(self, frame: TickFrame) -> float:
        """How far the reference at the tick lies from the robot (m): across a car's heading (its
        window frame's second axis), else the distance."""
        if self.errors.layout.kind == "planar":
            return abs(float(frame.x_r[0, self._pos_index[1]]))
        return vector_norm(frame.x_r[0, self._pos_index])

    def _solve_increments(self, horizon, barrier: HorizonBarrier, t: float, speed: float,
                          frame: TickFrame) -> np.ndarray:
        """The command u of the increment form (rate.py) of the tick's ``horizon`` (``tick_horizon``)
        in the tick's mode. Cruising with ``R_rate_light`` given, at a ``speed`` (the body's, m/s)
        within ``light_speeds`` (where the model's steering response is close to the vehicle's) and on
        the reference (``_offset`` of ``frame``, within the first of ``light_offsets`` to take the
        light weights up, within the second to keep them: they track tightly, and a car brought back
        from a swerve by them, 0.16 m off the road behind a crossing pedestrian, swung across it for
        5 s at +-0.15 rad before it settled), the light weights are tried first, their increments
        bounded by the actuator's rate limit (``RateForm.increments``: the solver clips its rollout
        and projects its targets onto them); their plan is kept unless it rides that limit at more
        than ``LIGHT_SATURATION`` of the horizon's steps (a manoeuvre the light weights ask too much
        of: following a slow car they weaved round it), else the tick is solved again with
        ``R_rate`` and the light weights are left for ``light_hold`` s. The light weights track
        tightly where the reference asks for gentle steering, and with the bounds a transient (a
        start off the route's heading) no longer sends them away; the heavy ones keep a solver
        without bounds from asking for steps the actuator cannot make (rate.py: the loop then
        oscillates behind the rate clip)."""
        lo, hi = self.params.light_speeds
        light = (self._light_mode is not None and not self._threatened and t >= self._heavy_until
                 and lo <= speed <= hi
                 and self._offset(frame) <= self.params.light_offsets[1 if self._light else 0])
        if light:
            rate, solver = self._light_mode
            if not self._light:
                solver.reset()
            v = self._solve_with(solver, horizon, rate, barrier, bounded=True)
            if v is not None and self.last_info.saturated <= LIGHT_SATURATION * self.N:
                self._light = True
                return horizon.command(rate, v[0])
            self._heavy_until = t + self.params.light_hold
        if self._light:                # back on the heavy weights: their solver starts afresh
            self.solver.reset()
            self._light = False
        return horizon.command(self.rate, self._solve(horizon, self.rate, barrier))

    def _barrier(self, frame: TickFrame, ref: np.ndarray, pos, vel, t: float, obstacles) -> HorizonBarrier:
        """The barrier of the movers in E_p (module docstring, step 4); ``ref``: the world reference
        states. Each mover is tested in floats (``threat_at``); without a threat the barrier is zero
        (``_no_threat``)."""
        self.last_threats = ()
        p = self.params
        if p.mu == 0.0 or p.max_threats == 0 or not obstacles:
            return self._no_threat
        grow = self.body_radius + self.safety_margin
        vel_l, pos_l = vel.tolist(), pos.tolist()
        v_e = math.hypot(*vel_l)
        near = []
        for o in obstacles:
            v_o = o.velocity.tolist()
            if not any(v_o):                                # static obstacles are the guidance's
                continue
            dt = t - o.stamp            # relative: ``ObstacleState.center_at`` less pos, in floats
            relative = [c + v * dt - q for c, v, q in zip(o.center.tolist(), v_o, pos_l)]
            if threat_at(relative, vel_l, v_e, math.hypot(*v_o), o.shape.bounding_radius() + grow, p.l_safe):
                near.append((math.hypot(*relative), len(near), o))
        if not near:
            return self._no_threat
        chosen = [o for _, _, o in sorted(near)[: p.max_threats]]
        self.last_threats = tuple(o.id for o in chosen)
        times = t + self._horizon_offsets
        p_world = ref[:, self._pos_index]
        xs, ns = np.empty((2, len(chosen)) + p_world.shape)
        for k, o in enumerate(chosen):
            self.errors.safety_points_in_window(frame, o, p_world, times, grow, xs[k], ns[k])
        return HorizonBarrier(self._pos_index, frame.x_r[:, self._pos_index], xs, ns,
                              np.full(len(chosen), p.mu), p.barrier_length)

    def _solve(self, horizon, rate: RateForm | None, barrier: HorizonBarrier) -> np.ndarray:
        """The solver's first input of the tick's ``horizon`` (in ``rate``'s increment form, or the
        problem itself when None). On a failure the plan of the last solve that succeeded goes on, a
        step a tick since it was solved (its inputs are deviations from the time-indexed reference,
        which moves on with it), for as many ticks as it has steps; then the terminal LQR law
        -K_terminal x0 (the rate form's, or the error model's). The LQR law of the lifted error alone
        knows nothing of the obstacles and of the rate limits: the Koopman-MPC, whose OSQP met its
        iteration cap on three ticks while it passed the slow car of carsim_avoidance, turned into
        the slow car's lane on it at 0.33 rad of steering and +3 m/s^2, where its last plan drove on
        past it."""
        u_tilde = self._solve_with(self.solver, horizon, rate, barrier)
        if u_tilde is not None:
            self._held, self._held_tick = u_tilde, self._ticks
            return u_tilde[0]
        k = self._ticks - self._held_tick
        if self._held is not None and 0 < k < len(self._held):
            return self._held[k]
        K_terminal = self.errors.K_terminal if rate is None else rate.K_terminal
        return -K_terminal @ horizon.start(rate)

    def _solve_with(self, solver, horizon, rate: RateForm | None, barrier: HorizonBarrier,
                    bounded: bool = False) -> np.ndarray | None:
        """``solver``'s plan u~ (N, n_u) of the tick's ``horizon`` in ``rate``'s form (``bounded``: its
        increments within the rate limit, an ``EbRHRL``'s); None (counted in ``fallbacks``, the solver
        reset) when it fails or diverges."""
        try:
            u_tilde, info = horizon.solve(rate, solver, barrier, bounded)
            self.last_info = info
        except (ArithmeticError, ValueError, np.linalg.LinAlgError) as exc:
            log.warning("event=solver_error reason=%s", exc)
            u_tilde = None
        if u_tilde is None or not all(abs(v) <= b for v, b in zip(u_tilde[0].tolist(), self._divergence_bound)):   # NaN: fails
            self.fallbacks += 1
            solver.reset()
            return None
        return u_tilde

    def _observe(self, last: tuple[TickFrame, np.ndarray], frame: TickFrame) -> None:
        """Offer the transition from ``last`` (its frame and the command applied there) to ``frame``
        (previous lifted state, applied command, current state in the previous window frame) to the GP."""
        prev, u = last
        self.compensator.observe(prev.U, u, self.errors.lifted_next(prev.origin, frame.origin))
        self._since_refit += 1
