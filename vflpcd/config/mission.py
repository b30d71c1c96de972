"""Mission files: what ``vflpcd run MISSION.toml`` flies or drives, validated before anything runs.

A mission names the vehicle, the platform link, the route (a scenario: reference path, start,
obstacles, desired speed and limits, plant parameters), the controller and its model artifact,
the loop rate, the workers, the telemetry, the failsafe policy and the log directory. The format
is documented in ``config/missions/README.md``; every problem is a ``ConfigError`` naming the file
and the field (the CLI turns it into exit code 2 and one line).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from vflpcd.daemon.config import EXECUTORS, MAX_RATE_HZ, FailsafePolicy, LoopConfig, WorkerConfig
from vflpcd.daemon.telemetry import TelemetryConfig, check_vehicle_id
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.inputfile import read_text
from vflpcd.base.tomlread import Table, parse_toml

PLATFORM_KINDS = {"inproc": ("ground", "aerial"), "mavlink": ("aerial",), "can": ("ground",)}


@dataclass(frozen=True)
class PlatformConfig:
    """The vehicle link: ``kind`` (inproc | mavlink | can) and its options (driver-specific, checked
    by the driver when it is built)."""

    kind: str
    options: dict = field(default_factory=dict)


@dataclass(frozen=True)
class Mission:
    file: Path
    vehicle_id: str
    description: str
    platform: PlatformConfig
    scenario: object            # vflpcd.config.scenarios.Scenario
    controller: str
    model_path: Path | None
    compensation: bool
    loop: LoopConfig
    workers: WorkerConfig
    telemetry: TelemetryConfig
    failsafe: FailsafePolicy
    safety: tuple                # (SupervisorConfig, MonitorConfig) of vflpcd.core.safety
    log_dir: Path
    text: str                   # the mission file as written (kept in the flight log)
    log_flush_period: float = 0.5   # s between the flight log's commits (vflpcd.log.writer)


def load_mission(path: str | Path) -> Mission:
    """Read and validate a mission; raises ConfigError naming the file and the field."""
    file = Path(path)
    text = read_text(file)
    root = Table(parse_toml(text, file), file)
    from vflpcd.config.safety import safety_settings    # with scipy: once there is a mission to check
    from vflpcd.config.scenarios import load_scenario

    root.check_known({"vehicle_id", "description", "platform", "route", "controller", "loop", "workers",
                      "telemetry", "failsafe", "safety", "log"})
    vehicle_id = root.string("vehicle_id")
    try:
        check_vehicle_id(vehicle_id)
    except ValueError as exc:
        raise root.error("vehicle_id", str(exc)) from None

    route = root.table("route")
    route.check_known({"scenario"})
    scenario = load_scenario(_find(route.string("scenario"), file, "scenarios", ".toml", route, "scenario"),
                             stop_at_goal=True)       # a mission ends at rest at its goal

    plat = root.table("platform")
    kind = plat.string("kind", choices=tuple(PLATFORM_KINDS))
    if scenario.platform not in PLATFORM_KINDS[kind]:
        raise plat.error("kind", f"a {kind} platform drives {'/'.join(PLATFORM_KINDS[kind])} robots, "
                                 f"the route is {scenario.platform}")
    platform = PlatformConfig(kind, {k: v for k, v in plat.data.items() if k != "kind"})

    ctl = root.table("controller", {})
    ctl.check_known({"name", "model", "compensation"})
    controller = ctl.string("name", "vflpc")
    model_path = _find(ctl.string("model"), file, "models", ".npz", ctl, "model") if ctl.has("model") else None
    compensation = ctl.boolean("compensation", False)

    lp = root.table("loop", {})
    lp.check_known({"rate_hz", "sched_fifo", "priority", "manual_gc"})
    loop = LoopConfig(rate_hz=lp.number("rate_hz", 50.0, positive=True, max=MAX_RATE_HZ),
                      sched_fifo=lp.boolean("sched_fifo", False), priority=lp.integer("priority", 10, min=1),
                      manual_gc=lp.boolean("manual_gc", True))
    if loop.priority > 99:
        raise lp.error("priority", f"expected a SCHED_FIFO priority in 1..99, got {loop.priority}")

    wk = root.table("workers", {})
    wk.check_known({"executor", "replan_period", "refit_period"})
    workers = WorkerConfig(executor=wk.string("executor", "process", choices=EXECUTORS),
                           replan_period=wk.number("replan_period", 0.0, min=0.0),
                           refit_period=wk.number("refit_period", 1.0, positive=True))

    telemetry = TelemetryConfig.from_table(root.table("telemetry", {}))

    fs = root.table("failsafe", {})
    fs.check_known({"state_max_age", "overrun_streak", "stall", "connect_timeout", "hold", "land_timeout",
                    "brake_timeout"})
    failsafe = FailsafePolicy(state_max_age=fs.number("state_max_age", 0.2, positive=True),
                              overrun_streak=fs.integer("overrun_streak", 5, min=1),
                              stall=fs.number("stall", 0.5, positive=True),
                              connect_timeout=fs.number("connect_timeout", 30.0, positive=True),
                              hold=fs.number("hold", 3.0, min=0.0),
                              land_timeout=fs.number("land_timeout", 60.0, positive=True, max=3600.0),
                              brake_timeout=fs.number("brake_timeout", 10.0, positive=True, max=600.0))
    if failsafe.state_max_age < loop.period_s:
        raise fs.error("state_max_age", f"must be at least one control period ({loop.period_s:g} s)")
    if failsafe.stall < 2.0 * loop.period_s:
        raise fs.error("stall", f"must be at least two control periods ({2 * loop.period_s:g} s)")

    safety = safety_settings(scenario.platform, root.table("safety", {}))

    lg = root.table("log", {})
    lg.check_known({"dir", "flush_period"})
    try:
        log_dir = Path(lg.string("dir", "logs")).expanduser()
    except RuntimeError as exc:             # ~user of an unknown user
        raise lg.error("dir", str(exc)) from None
    flush_period = lg.number("flush_period", 0.5, min=0.05, max=5.0)

    return Mission(file=file, vehicle_id=vehicle_id, description=root.string("description", ""),
                   platform=platform, scenario=scenario, controller=controller, model_path=model_path,
                   compensation=compensation, loop=loop, workers=workers, telemetry=telemetry,
                   failsafe=failsafe, safety=safety, log_dir=log_dir, text=text,
                   log_flush_period=flush_period)


def _find(name: str, mission_file: Path, folder: str, suffix: str, table: Table, key: str) -> Path:
    """A file named in a mission: a path relative to the mission file, else a name in config/FOLDER."""
    candidates = [mission_file.parent / name, config_dir() / folder / name, config_dir() / folder / f"{name}{suffix}"]
    for c in candidates:
        try:
            if c.is_file():
                return c
        except OSError:                     # e.g. a name longer than the file system allows
            continue
    raise table.error(key, f"no such file {name!r} (looked in {mission_file.parent} and {config_dir() / folder})")


def build_controller(mission: Mission):
    """The mission's controller for its route, ticking at the mission's rate."""
    from vflpcd.controllers import make_controller

    options = {}
    if mission.controller in ("vflpc", "vflpc_ml", "koopman_mpc"):
        options = {"model_path": mission.model_path, "period": mission.loop.period_s}
    name = mission.controller
    if mission.compensation:
        if name != "vflpc" or mission.scenario.platform != "ground":
            raise ConfigError(mission.file, "controller.compensation",
                              f"the online GP is VF-LPC's on ground vehicles, not {name}'s on a "
                              f"{mission.scenario.platform} route")
        name = "vflpc_ml"
    try:
        return make_controller(name, mission.scenario, source=(str(mission.file), "controller.name"), **options)
    except ValueError as exc:
        if isinstance(exc, ConfigError):
            raise
        field = "loop.rate_hz" if "period" in str(exc) else "controller.model"
        raise ConfigError(mission.file, field, str(exc)) from None
