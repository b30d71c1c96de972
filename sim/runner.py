"""Offline closed loop: plant + controller + safety guard + obstacles stepped as fast as possible.

Each control step k at t_k = k * control_period: the obstacle triggers are updated from
the robot position, the controller maps (x_k, t_k, perceived obstacles) to u_k (its wall
time is t_cal), the safety guard (``vflpcd.core.safety``, the same as in the daemon) passes u_k or
replaces it with the emergency manoeuvre (its wall time is t_sup), the controller does what its
command did not wait for (``settle``: VF-LPC's GP sample; its wall time is t_settle), everything is
recorded, and the plant integrates the command over one period. A controller with worker work (``jobs``: VF-LPC's
replans and GP refits, which the daemon runs on workers) has it run inline after the plant step
(``vflpcd.core.jobs.run_inline``), outside t_cal; its wall time is t_background. The objects alive
before the run (a bench's earlier records) are frozen out of the garbage collector while it runs
(``earlier_objects_frozen``), as the daemon keeps its start-up objects out of its collections.

The run ends when the robot's progress along the path reaches the goal (``completed``), when
t_max is reached (``timeout``), when the controller or the plant produces a non-finite value
(``diverged``), or when the guard gives up the mission or the controller raises (a failsafe: the
emergency manoeuvre is then applied until the body is at rest; without a guard a raising
controller ends the run at once: ``error``): ``stopped`` when the supervisor held the body at rest in front
of an obstacle for the monitors' ``blocked_s``, ``failsafe`` for the other monitors. A run in which
the body touched an obstacle ends ``collision``, whatever else happened.
"""

from __future__ import annotations

import gc
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from sim.metrics import summarize
from vflpcd.core.guidance.grid import forget_local_grids
from vflpcd.core.obstacle_world import ObstacleWorld
from sim.plants import make_plant
from vflpcd.config.scenarios import Scenario
from vflpcd.core.path import progress_delta
from vflpcd.core.ports import ControllerBase
from vflpcd.core.safety.guard import SafetyGuard
from vflpcd.core.jobs import run_inline
from vflpcd.config.safety import guard_for

REST_HOLD_S = 0.5      # after a failsafe, the run ends once the body has been at rest this long
# `vflpcd sim`'s exit code per outcome (the daemon's codes: 3 the safety layer stopped it, 5 a collision)
OUTCOME_EXIT = {"completed": 0, "timeout": 1, "diverged": 1, "error": 1, "stopped": 3, "failsafe": 3, "collision": 5}


@dataclass
class RunRecord:
    """Time series of one run; M steps, n_obs obstacles, d = 2 or 3.

    t (M,); state (M, n_x); position, velocity (M, d) world; psi (M,) yaw (ground) or course
    angle (aerial); command (M, n_u) from the controller; applied (M, n_u) after actuator
    limits; t_cal (M,) s; ref_point (M, d) and ref_heading (M,) nearest path point and its
    tangent yaw; lateral (M,); progress (M,) arc length covered; obstacle_center
    (M, n_obs, d); clearance (M, n_obs), NaN while an obstacle is absent; t_background (M,) s
    of worker work after each step (0 where no job ran); sent (M, n_u) the command
    after the safety guard; override (M,) 1 where the supervisor replaced it; t_sup (M,) s of the
    guard's work; t_settle (M,) s of the controller's ``settle`` after the command; failsafe: the guard's reason for giving up ("" if it did not).
    """

    scenario: str
    controller: str
    seed: int
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    t: np.ndarray
    state: np.ndarray
    position: np.ndarray
    velocity: np.ndarray
    psi: np.ndarray
    command: np.ndarray
    applied: np.ndarray
    t_cal: np.ndarray
    ref_point: np.ndarray
    ref_heading: np.ndarray
    lateral: np.ndarray
    progress: np.ndarray
    obstacle_center: np.ndarray
    clearance: np.ndarray
    t_background: np.ndarray
    sent: np.ndarray
    override: np.ndarray
    t_sup: np.ndarray
    t_settle: np.ndarray
    outcome: str
    t_com: float | None
    failsafe: str = ""
    interventions: int = 0
    metrics: dict = field(default_factory=dict)


@contextmanager
def earlier_objects_frozen():
    """The objects alive before a run (a bench's records of its earlier runs) collected and frozen
    out of the garbage collector while it runs, as the daemon freezes its start-up objects
    (``ManualGC``), and given back after. Else a full collection over them falls inside whatever
    tick or inline replan it interrupts: 43 ms over 36 runs' records, a tight_s_curve_cones replan
    of 9-10 ms timed at 50 and 90 ms as the last of `bench suite`'s 70 runs, where a daemon's
    worker collects only its own small heap."""
    gc.collect()
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def run_closed_loop(scenario: Scenario, controller: ControllerBase, seed: int = 0, *,
                    supervised: bool = True, guard: SafetyGuard | None = None) -> RunRecord:
    """Run ``controller`` on ``scenario`` behind the safety guard (``guard``, default: the route's
    from config/safety.toml; ``supervised=False`` runs without any, for comparison) and return the
    record with its metrics; the objects alive before it are kept out of its collections
    (``earlier_objects_frozen``)."""
    with earlier_objects_frozen():
        return _run(scenario, controller, seed, supervised, guard)


def _run(scenario: Scenario, controller: ControllerBase, seed: int, supervised: bool,
         guard: SafetyGuard | None) -> RunRecord:
    plant = make_plant(scenario, seed)
    world = ObstacleWorld(scenario.obstacles)
    forget_local_grids()        # each run starts with no obstacle grid kept, as a daemon's workers do
    controller.reset()
    dt = scenario.control_period
    if supervised and guard is None:
        guard = guard_for(scenario, dt, plant.state_names)
    if guard is not None:
        guard.reset()
    n_steps = int(np.ceil(scenario.t_max / dt)) + 1
    rows: dict[str, list] = {k: [] for k in ("t", "state", "position", "velocity", "psi", "command", "applied",
                                             "t_cal", "ref_point", "ref_heading", "lateral", "progress",
                                             "obstacle_center", "clearance", "t_background", "sent",
                                             "override", "t_sup", "t_settle")}
    s_prev, progress, outcome, t_com = None, 0.0, "timeout", None
    failsafe, rest_since = "", None
    jobs = controller.jobs
    for k in range(n_steps):
        t = k * dt
        x = plant.state
        pos, vel, yaw = plant.position(), plant.velocity_world(), plant.heading()
        psi = yaw if scenario.dim == 2 else float(np.arctan2(vel[1], vel[0])) if np.hypot(vel[0], vel[1]) > 0.1 else None
        proj = scenario.path.project(pos, s_prev)
        progress += 0.0 if s_prev is None else progress_delta(scenario.path, proj.s, s_prev)
        s_prev = proj.s
        world.update(t, pos)
        perceived = world.snapshot(t)
        if failsafe:
            u, t_cal = guard.emergency(x, perceived, t), 0.0
        else:
            t0 = time.perf_counter_ns()
            try:
                u = np.asarray(controller.step(x, t, perceived), dtype=float)
            except Exception as exc:      # as in the daemon: the controller failed, the guard stops the body
                failsafe = f"controller_error: {type(exc).__name__}: {exc}"[:300]
                if guard is None:         # nothing to stop it with: the run ends here
                    outcome = "error"
                    u = np.full(len(plant.control_names), np.nan)
                else:
                    u = guard.emergency(x, perceived, t)
            t_cal = (time.perf_counter_ns() - t0) * 1e-9
        finite = u.shape == (len(plant.control_names),) and bool(np.all(np.isfinite(u)))
        sent, override, t_sup = u, False, 0.0
        if guard is not None and finite and not failsafe:
            t0 = time.perf_counter_ns()
            gs = guard.step(t, x, u, perceived, controller, route_error=abs(proj.lateral))
            t_sup = (time.perf_counter_ns() - t0) * 1e-9
            sent, override = gs.command, gs.verdict.override
            failsafe = gs.trip or ""
        t_settle = 0.0
        if not failsafe:
            t0 = time.perf_counter_ns()
            controller.settle()
            t_settle = (time.perf_counter_ns() - t0) * 1e-9

        centers = np.array([world.center(i, t) for i in range(len(world.specs))]).reshape(-1, scenario.dim)
        clear = np.array([scenario.footprint.clearance(o.shape, centers[i], o.yaw, pos, yaw)
                          if world.present(i) else np.nan for i, o in enumerate(scenario.obstacles)])
        heading_ref = float(np.arctan2(proj.tangent[1], proj.tangent[0]))
        for key, value in (("t", t), ("state", x), ("position", pos), ("velocity", vel),
                           ("psi", heading_ref if psi is None else psi), ("command", u),
                           ("t_cal", t_cal), ("ref_point", proj.point), ("ref_heading", heading_ref),
                           ("lateral", proj.lateral), ("progress", progress),
                           ("obstacle_center", centers), ("clearance", clear), ("sent", sent),
                           ("override", float(override)), ("t_sup", t_sup), ("t_settle", t_settle)):
            rows[key].append(value)
        rows["t_background"].append(0.0)

        if progress >= scenario.goal_progress:
            outcome, t_com = "completed", t
            rows["applied"].append(np.full(len(plant.control_names), np.nan))
            break
        if not finite:
            outcome = "diverged" if outcome != "error" else outcome
            rows["applied"].append(np.full(len(plant.control_names), np.nan))
            break
        if failsafe:
            rest_since = (rest_since if rest_since is not None else t) if SafetyGuard.at_rest(
                float(np.linalg.norm(vel))) else None
            if rest_since is not None and t - rest_since >= REST_HOLD_S:
                outcome = "stopped" if failsafe.startswith("blocked") else "failsafe"
                rows["applied"].append(np.full(len(plant.control_names), np.nan))
                break
        plant.step(sent, dt)
        rows["applied"].append(plant.applied_control)
        if jobs is not None and not failsafe:
            t0 = time.perf_counter_ns()
            if run_inline(jobs):                        # t_background stays 0 on ticks that ran no job
                rows["t_background"][-1] = (time.perf_counter_ns() - t0) * 1e-9
        if not np.all(np.isfinite(plant.state)):
            outcome = "diverged"
            break

    arr = {k: np.asarray(v, dtype=float) for k, v in rows.items()}
    arr["obstacle_center"] = arr["obstacle_center"].reshape(len(arr["t"]), len(scenario.obstacles), scenario.dim)
    arr["clearance"] = arr["clearance"].reshape(len(arr["t"]), len(scenario.obstacles))
    record = RunRecord(scenario=scenario.name, controller=controller.name, seed=seed,
                       state_names=tuple(plant.state_names), control_names=tuple(plant.control_names),
                       outcome=outcome, t_com=t_com, failsafe=failsafe,
                       interventions=guard.interventions if guard is not None else 0, **arr)
    record.metrics = evaluate(record, scenario)
    return record


def evaluate(record: RunRecord, scenario: Scenario) -> dict:
    """The paper's metrics of a run (sim.metrics), over the steps whose control was applied."""
    ok = np.all(np.isfinite(record.applied), axis=1)
    w = scenario.weights
    metrics = summarize(
        t=record.t, positions=record.position, velocity=record.velocity,
        psi=record.psi[ok], psi_r=record.ref_heading[ok], e_lat=record.lateral[ok],
        u_tilde=record.applied[ok], t_cal=record.t_cal, clearance=record.clearance,
        q1=w.q1, q2=w.q2, R=w.R, t_com=record.t_com, t_applied=record.t[ok],
        a_x=record.applied[ok][:, record.control_names.index("a_x")] if "a_x" in record.control_names else None)
    jobs = job_stats(job_times(record.t_background))
    metrics["t_background_max"], metrics["t_background_median"] = jobs["max"], jobs["median"]
    metrics["t_background_p99"], metrics["background_jobs"] = jobs["p99"], jobs["jobs"]
    if metrics.get("collisions", 0) > 0:
        record.outcome = "collision"
    metrics["outcome"] = record.outcome
    metrics["failsafe"] = record.failsafe
    metrics["steps"] = int(len(record.t))
    metrics["interventions"] = int(record.interventions)
    metrics["override_ticks"] = int(np.sum(record.override))
    sup = record.t_sup[record.t_sup > 0]
    metrics["t_sup_median"] = float(np.median(sup)) if sup.size else 0.0
    metrics["t_sup_p99"] = float(np.percentile(sup, 99)) if sup.size else 0.0
    settle = record.t_settle[record.t_cal > 0]
    metrics["t_settle_median"] = float(np.median(settle)) if settle.size else 0.0
    metrics["t_settle_p99"] = float(np.percentile(settle, 99)) if settle.size else 0.0
    metrics["impact_speed"] = impact_speed(record)
    return metrics


def job_times(t_background) -> np.ndarray:
    """The background jobs' wall times (s) of a run's t_background (M,): the ticks that ran one."""
    t = np.asarray(t_background, float)
    return t[t > 0.0]


def job_stats(jobs) -> dict:
    """Count, median, p99 and max (s) of background job times (all 0 when none ran)."""
    t = np.asarray(jobs, float)
    if not t.size:
        return {"jobs": 0, "median": 0.0, "p99": 0.0, "max": 0.0}
    return {"jobs": int(t.size), "median": float(np.median(t)), "p99": float(np.percentile(t, 99)),
            "max": float(np.max(t))}


def impact_speed(record: RunRecord) -> float | None:
    """The body's speed (m/s) at its first contact with an obstacle, None without contact."""
    with np.errstate(invalid="ignore"):
        touching = np.any(record.clearance <= 0.0, axis=1) if record.clearance.size else np.zeros(len(record.t), bool)
    hits = np.flatnonzero(touching)
    return float(np.linalg.norm(record.velocity[hits[0]])) if hits.size else None
