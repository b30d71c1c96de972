"""Offline closed loop: plant + controller + obstacles stepped as fast as possible.

Each control step k at t_k = k * control_period: the obstacle triggers are updated from
the robot position, the controller maps (x_k, t_k, perceived obstacles) to u_k (its wall
time is t_cal), everything is recorded, and the plant integrates u_k over one period. A
controller with worker work (``background()``: VF-LPC's replans and GP refits, which the daemon
runs on workers) does it after the plant step, outside t_cal; its wall time is t_background.
The run ends when the robot's progress along the path reaches the goal (``completed``),
when t_max is reached (``timeout``), or when the controller or the plant produces a
non-finite value (``diverged``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from sim.metrics import summarize
from sim.obstacle_world import ObstacleWorld
from sim.plants import make_plant
from sim.scenarios import Scenario
from vflpcd.core.path import progress_delta
from vflpcd.core.ports import Controller


@dataclass
class RunRecord:
    """Time series of one run; M steps, n_obs obstacles, d = 2 or 3.

    t (M,); state (M, n_x); position, velocity (M, d) world; psi (M,) yaw (ground) or course
    angle (aerial); command (M, n_u) from the controller; applied (M, n_u) after actuator
    limits; t_cal (M,) s; ref_point (M, d) and ref_heading (M,) nearest path point and its
    tangent yaw; lateral (M,); progress (M,) arc length covered; obstacle_center
    (M, n_obs, d); clearance (M, n_obs), NaN while an obstacle is absent; t_background (M,) s
    of worker work after each step (0 for a controller without any).
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
    outcome: str
    t_com: float | None
    metrics: dict = field(default_factory=dict)


def run_closed_loop(scenario: Scenario, controller: Controller, seed: int = 0) -> RunRecord:
    """Run ``controller`` on ``scenario`` and return the record with its metrics."""
    plant = make_plant(scenario, seed)
    world = ObstacleWorld(scenario.obstacles)
    controller.reset()
    dt = scenario.control_period
    n_steps = int(np.ceil(scenario.t_max / dt)) + 1
    rows: dict[str, list] = {k: [] for k in ("t", "state", "position", "velocity", "psi", "command", "applied",
                                             "t_cal", "ref_point", "ref_heading", "lateral", "progress",
                                             "obstacle_center", "clearance", "t_background")}
    s_prev, progress, outcome, t_com = None, 0.0, "timeout", None
    background = getattr(controller, "background", None)
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
        t0 = time.perf_counter_ns()
        u = np.asarray(controller.step(x, t, perceived), dtype=float)
        t_cal = (time.perf_counter_ns() - t0) * 1e-9

        centers = np.array([world.center(i, t) for i in range(len(world.specs))]).reshape(-1, scenario.dim)
        clear = np.array([scenario.footprint.clearance(o.shape, centers[i], o.yaw, pos, yaw)
                          if world.present(i) else np.nan for i, o in enumerate(scenario.obstacles)])
        heading_ref = float(np.arctan2(proj.tangent[1], proj.tangent[0]))
        for key, value in (("t", t), ("state", x), ("position", pos), ("velocity", vel),
                           ("psi", heading_ref if psi is None else psi), ("command", u),
                           ("t_cal", t_cal), ("ref_point", proj.point), ("ref_heading", heading_ref),
                           ("lateral", proj.lateral), ("progress", progress),
                           ("obstacle_center", centers), ("clearance", clear)):
            rows[key].append(value)
        rows["t_background"].append(0.0)

        if progress >= scenario.goal_progress:
            outcome, t_com = "completed", t
            rows["applied"].append(np.full(len(plant.control_names), np.nan))
            break
        if u.shape != (len(plant.control_names),) or not np.all(np.isfinite(u)):
            outcome = "diverged"
            rows["applied"].append(np.full(len(plant.control_names), np.nan))
            break
        plant.step(u, dt)
        rows["applied"].append(plant.applied_control)
        if background is not None:
            t0 = time.perf_counter_ns()
            background()
            rows["t_background"][-1] = (time.perf_counter_ns() - t0) * 1e-9
        if not np.all(np.isfinite(plant.state)):
            outcome = "diverged"
            break

    arr = {k: np.asarray(v, dtype=float) for k, v in rows.items()}
    arr["obstacle_center"] = arr["obstacle_center"].reshape(len(arr["t"]), len(scenario.obstacles), scenario.dim)
    arr["clearance"] = arr["clearance"].reshape(len(arr["t"]), len(scenario.obstacles))
    record = RunRecord(scenario=scenario.name, controller=controller.name, seed=seed,
                       state_names=tuple(plant.state_names), control_names=tuple(plant.control_names),
                       outcome=outcome, t_com=t_com, **arr)
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
        q1=w.q1, q2=w.q2, R=w.R, t_com=record.t_com)
    metrics["t_background_max"] = float(np.max(record.t_background)) if len(record.t_background) else 0.0
    metrics["outcome"] = record.outcome
    metrics["steps"] = int(len(record.t))
    return metrics
