"""``vflpcd run``: a mission wired into the daemon (the composition root of a run).

Builds, from a validated ``Mission``: the platform driver, the controller (VF-LPC by default) at
the mission's rate, the safety guard between the two (``vflpcd.config.safety``), the mission's obstacles (``vflpcd.core.obstacle_world``: static ones, and moving ones
with their triggers), progress along the route, the workers, the flight recorder, the Zenoh
telemetry and perception input, and the daemon; runs it and returns the outcome and the log.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vflpcd.daemon.control_loop import ControlLoop, Sinks
from vflpcd.daemon.progress import Progress
from vflpcd.log.records import MissionHeader
from vflpcd.daemon.service import Daemon, Outcome
from vflpcd.app.drill import Drill, DrillController
from vflpcd.base.errors import ConfigError
from vflpcd.config.mission import Mission, build_controller
from vflpcd.config.safety import guard_for

log = logging.getLogger("vflpcd.app.run")


@dataclass
class RunResult:
    """outcome; log_path: the flight log; log_stop: why the log stopped before the run ended
    (``FlightRecorder.stop_reason``), None when it did not."""

    outcome: Outcome
    log_path: Path | None
    mission: Mission
    log_stop: str | None = None


def build_platform(mission: Mission, flight_log: Path | None = None):
    """The mission's platform driver (ConfigError for bad options). ``flight_log``: the run's MCAP
    path; drivers that record their link (the CAN bus log) write beside it."""
    from drivers import make_platform

    return make_platform(mission.platform.kind, mission.scenario, mission.platform.options, mission.file, flight_log)


def position_index(state_names) -> list[int]:
    names = [n for n in ("X", "Y", "Z") if n in state_names]
    return [state_names.index(n) for n in names]


def mission_obstacles(scenario, state_names):
    """obstacles(t, state): the mission's obstacles at mission time t (triggers fire from the state)."""
    from vflpcd.core.obstacle_world import ObstacleWorld

    world = ObstacleWorld(scenario.obstacles)
    index = position_index(state_names)

    def obstacles(t: float, state: np.ndarray):
        world.update(t, np.asarray(state)[index])
        return world.snapshot(t)
    return obstacles


def mission_header(mission: Mission, platform, controller) -> MissionHeader:
    from vflpcd.core.shapes import top_view

    sc = mission.scenario
    s = np.linspace(0.0, sc.path.length, max(2, int(sc.path.length / 0.5)))
    path = sc.path.point_at(s)
    obstacles = tuple({"id": o.id, "center": o.center.tolist(), "velocity": o.velocity.tolist(),
                       "radius": float(o.shape.bounding_radius()), "trigger": o.trigger,
                       "outline": top_view(o.shape).outline(o.center[:2], o.yaw, 48).tolist()}
                      for o in sc.obstacles)
    return MissionHeader(vehicle_id=mission.vehicle_id, platform=mission.platform.kind, controller=controller.name,
                         dim=sc.dim, rate_hz=mission.loop.rate_hz, state_names=tuple(platform.state_names),
                         control_names=tuple(platform.control_names),
                         path=tuple(tuple(map(float, p)) for p in np.asarray(path)), obstacles=obstacles,
                         mission_file=str(mission.file), model_file=str(mission.model_path or ""))


def run_mission(mission: Mission, *, drill: Drill | None = None, rate_hz: float | None = None,
                log_dir: Path | None = None, stop_after_s: float | None = None) -> RunResult:
    """Run the mission to its end (complete, failsafe, a signal, or ``stop_after_s`` seconds of
    control). ``rate_hz`` and ``log_dir`` override the mission's. Process workers are started by
    ``spawn``, which imports the main module again: a script that calls this needs the
    ``if __name__ == "__main__":`` guard (the ``vflpcd`` command has it)."""
    from vflpcd.log.writer import FlightRecorder, log_path
    from vflpcd.daemon.workers import Workers

    if rate_hz is not None:
        mission = replace(mission, loop=replace(mission.loop, rate_hz=rate_hz))
    loop_cfg = mission.loop
    flight_log = log_path(log_dir or mission.log_dir, mission.vehicle_id)
    platform = build_platform(mission, flight_log)
    controller = build_controller(mission)
    if drill is not None:
        controller = DrillController(controller, drill, platform, loop_cfg.period_s)
    header = mission_header(mission, platform, controller)
    closers: list = []
    telemetry = perception = None
    if mission.telemetry.enabled:         # first: a port in use must not leave an empty log behind
        telemetry, perception = _open_telemetry(mission, platform, header, closers)
    try:
        recorder = FlightRecorder(flight_log, header, mission.log_flush_period)
    except ConfigError:
        for close in closers:
            close()
        raise
    closers.append(recorder.close)
    workers = Workers(mission.workers.executor, controller.jobs.planner) if controller.jobs is not None else None
    if workers is not None:
        closers.insert(0, workers.close)
    sc = mission.scenario
    progress = Progress(sc.path, sc.goal_progress, position_index(platform.state_names))
    obstacles = mission_obstacles(sc, platform.state_names)
    sinks = Sinks(recorder=recorder, telemetry=telemetry)

    guard = guard_for(sc, loop_cfg.period_s, platform.state_names, mission.safety)

    def make_loop(aio) -> ControlLoop:
        return ControlLoop(platform, controller, loop_cfg, mission.workers, mission.failsafe, aio,
                           obstacles=obstacles, perception=perception, progress=progress, workers=workers,
                           sinks=sinks, guard=guard)

    def first_plan(state):
        controller.prepare(state, 0.0, obstacles(0.0, state))

    daemon = Daemon(platform, make_loop, first_plan=first_plan, workers=workers, closers=closers,
                    telemetry=telemetry, stop_after_s=stop_after_s)
    if perception is not None:      # drops and rejections, aggregated at most once a second per kind
        def perception_event(kind: str, detail: dict) -> None:
            if daemon.loop is not None:
                daemon.loop.event(kind, **detail)
            else:                   # before the control loop exists: the log only
                log.info("event=%s %s", kind, " ".join(f"{k}={v}" for k, v in detail.items()))
        perception.on_event = perception_event
    outcome = asyncio.run(daemon.run())
    return RunResult(outcome, recorder.path, mission, recorder.stop_reason)


def _open_telemetry(mission: Mission, platform, header: MissionHeader, closers: list):
    from vflpcd.daemon.telemetry import TelemetryPublisher, open_session

    try:
        session = open_session(mission.telemetry, vehicle_id=mission.vehicle_id)
    except ConfigError as exc:
        raise ConfigError(mission.file, exc.field, exc.message) from None
    closers.append(session.close)
    telemetry = TelemetryPublisher(session, mission.vehicle_id, mission.telemetry,
                                   state_names=platform.state_names, control_names=platform.control_names)
    closers.insert(len(closers) - 1, telemetry.close)
    telemetry.offer_header(header)
    perception = None
    if mission.telemetry.perception:
        from vflpcd.daemon.perception import PerceptionInput, PerceptionLimits

        tc = mission.telemetry
        limits = PerceptionLimits.around(mission.scenario.path, tc.perception_area_margin_m,
                                         tc.perception_max_speed, tc.perception_max_radius)
        perception = PerceptionInput(session, mission.vehicle_id, mission.scenario.dim, tc.perception_max_age_s,
                                     limits, tc.perception_rate_hz)
        closers.insert(closers.index(telemetry.close), perception.close)   # its last report goes out too
    return telemetry, perception
