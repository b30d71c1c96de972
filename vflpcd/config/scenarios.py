"""Scenarios: TOML data in ``config/scenarios/`` turned into validated objects.

A scenario names the plant and its parameter set, the reference path (analytic or a
waypoint file), the start state, the desired speed and lateral-acceleration limit, the
obstacles (static, constant-velocity, triggered), the metric weights and the run limits.
The file format is documented in ``config/scenarios/README.md``. Every problem is a
``ConfigError`` naming the file and the field.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from vflpcd.core.footprint import Footprint
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.config.params import guidance_params
from vflpcd.core.guidance.params import GuidanceParams
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import SHAPES_2D, SHAPES_3D, shape_from_table
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.inputfile import read_text
from vflpcd.base.tomlread import Table, load_table

PLATFORMS = {"ground": ("dynamic_bicycle", 2, 2), "aerial": ("quadrotor", 3, 3)}  # plant, dim, n_u
TRIGGERS = ("always", "move", "appear")
RUN_ON_TIME = 3.0   # s at the desired speed beyond the braking distance that a goal passed at speed runs on


@dataclass(frozen=True)
class ObstacleSpec:
    """One scenario obstacle: physical shape, initial centre (d,), yaw, velocity (d,), trigger."""

    id: str
    shape: object
    center: np.ndarray
    yaw: float
    velocity: np.ndarray
    trigger: str
    trigger_distance: float


@dataclass(frozen=True)
class MetricWeights:
    """q1, q2 of J_Lat and J_Heading, R (n_u, n_u) of J_Con."""

    q1: float
    q2: float
    R: np.ndarray


@dataclass(frozen=True)
class Scenario:
    name: str
    file: Path
    description: str
    platform: str               # "ground" | "aerial"
    plant: str                  # "dynamic_bicycle" | "quadrotor"
    params: str                 # parameter set of the plant file
    process_noise: bool
    dim: int
    path: ReferencePath
    start: np.ndarray           # plant initial state: ground [X, Y, psi, vx], aerial [X, Y, Z, vx, vy, vz, yaw]
    v_desired: float
    a_lat_max: float
    control_period: float
    t_max: float
    goal_tolerance: float
    goal_at: float              # arc length of the goal along ``path``: its given end, before any run-on
    stop_at_goal: bool
    laps: int
    obstacles: tuple[ObstacleSpec, ...]
    weights: MetricWeights
    footprint: Footprint
    guidance: GuidanceParams    # config/guidance.toml with the scenario's [guidance] overrides

    @property
    def goal_progress(self) -> float:
        """Arc length the robot must cover to complete the run (m)."""
        if self.path.closed:
            return self.laps * self.path.length
        return self.goal_at - self.goal_tolerance


def scenario_file(name_or_path: str | Path) -> Path:
    """A scenario name (``config/scenarios/<name>.toml``) or a path to a TOML file."""
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        return p
    return config_dir() / "scenarios" / f"{name_or_path}.toml"


def available_scenarios() -> list[str]:
    return sorted(p.stem for p in (config_dir() / "scenarios").glob("*.toml"))


def run_on_length(v_desired: float, a_decel: float) -> float:
    """The straight (m) an open path runs on past a goal that is passed at speed: the braking
    distance v_d^2 / (2 a_decel) of the speed plan's stop at the end of the road, plus
    ``RUN_ON_TIME`` s at v_d (a horizon controller's 1 s horizon, the replan margin of 1 s before
    a plan runs out, and the lead with which the throttle eases into a planned stop), so that
    nothing brakes for the end of the road before the goal."""
    return v_desired * v_desired / (2.0 * a_decel) + RUN_ON_TIME * v_desired


def load_scenario(name_or_path: str | Path, stop_at_goal: bool | None = None) -> Scenario:
    """Load and validate a scenario; raises ConfigError naming the file and field. ``stop_at_goal``
    overrides the file's ``[goal] stop`` (a mission ends at rest at its goal)."""
    file = scenario_file(name_or_path)
    if not file.exists():
        raise ConfigError(file, "<file>", f"no such scenario (available: {', '.join(available_scenarios())})")
    root = load_table(file)
    root.check_known({"name", "description", "platform", "control_period", "t_max",
                      "vehicle", "path", "start", "speed", "goal", "metrics", "obstacles", "guidance"})
    platform = root.string("platform", choices=tuple(PLATFORMS))
    plant_name, dim, n_u = PLATFORMS[platform]

    veh = root.table("vehicle")
    veh.check_known({"plant", "params", "process_noise", "body_radius"})
    plant = veh.string("plant", choices=(plant_name,))
    params = veh.string("params", "nominal")
    if platform == "ground":
        bike = _bicycle_config(params, veh)
        footprint = Footprint.rectangle(bike.body.length, bike.body.width,
                                        bike.body.rear_overhang + bike.params.lr)
    else:
        footprint = Footprint.sphere(veh.number("body_radius", positive=True))

    path = _load_path(root.table("path"), dim, file)

    start_t = root.table("start")
    start_t.check_known({"position", "yaw", "speed"})
    pos = start_t.vector("position", dim)
    yaw = start_t.number("yaw", 0.0)
    speed = start_t.number("speed", 0.0, min=0.0)
    if platform == "ground":
        start = np.array([pos[0], pos[1], yaw, speed])
    else:
        v = speed * np.array([np.cos(yaw), np.sin(yaw), 0.0])
        start = np.concatenate([pos, v, [yaw]])

    spd = root.table("speed")
    spd.check_known({"desired", "a_lat_max"})
    goal = root.table("goal", {})
    goal.check_known({"tolerance", "laps", "stop"})
    stop = goal.boolean("stop", False) if stop_at_goal is None else bool(stop_at_goal)
    if path.closed and goal.has("stop"):
        raise goal.error("stop", "a closed path has no end to stop at or run on from (laps counts its rounds)")
    metrics = root.table("metrics")
    metrics.check_known({"q1", "q2", "R"})
    R = metrics.matrix("R", n_u)
    if R.shape != (n_u, n_u) or not np.allclose(R, R.T) or np.min(np.linalg.eigvalsh(R)) <= 0:
        raise metrics.error("R", f"expected a symmetric positive definite {n_u}x{n_u} matrix")

    obstacles = tuple(_load_obstacle(t, dim) for t in root.tables("obstacles", []))
    ids = [o.id for o in obstacles]
    for i, oid in enumerate(ids):
        if ids.index(oid) != i:
            raise ConfigError(file, f"obstacles[{i}].id", f"duplicate id {oid!r}")

    guidance = guidance_params(root.table("guidance", {}), default_guidance())
    v_desired = spd.number("desired", positive=True)
    goal_at = path.length
    if not (stop or path.closed):
        path = path.run_on(run_on_length(v_desired, guidance.a_decel))

    scenario = Scenario(
        name=root.string("name"), file=file, description=root.string("description", ""),
        platform=platform, plant=plant, params=params,
        process_noise=veh.boolean("process_noise", False), dim=dim, path=path, start=start,
        v_desired=v_desired, a_lat_max=spd.number("a_lat_max", positive=True),
        control_period=root.number("control_period", positive=True, max=1.0),
        t_max=root.number("t_max", positive=True),
        goal_tolerance=goal.number("tolerance", 1.0, positive=True), goal_at=goal_at, stop_at_goal=stop,
        laps=goal.integer("laps", 1, min=1), obstacles=obstacles,
        weights=MetricWeights(q1=metrics.number("q1", min=0.0), q2=metrics.number("q2", min=0.0), R=R),
        footprint=footprint, guidance=guidance)
    _check_start_is_free(scenario)
    return scenario


def default_guidance() -> GuidanceParams:
    """The guidance parameters of ``config/guidance.toml``."""
    path = config_dir() / "guidance.toml"
    return guidance_params(load_table(path))


def _bicycle_config(params: str, veh: Table) -> BicycleConfig:
    try:
        return BicycleConfig.load(params)
    except ConfigError as exc:
        if exc.field.startswith("params."):
            raise veh.error("params", exc.message) from None
        raise


def _load_path(t: Table, dim: int, file: Path) -> ReferencePath:
    kind = t.string("kind", choices=("line", "arc", "waypoints"))
    if kind == "line":
        t.check_known({"kind", "start", "end"})
        start, end = t.vector("start", dim), t.vector("end", dim)
        if np.linalg.norm(end - start) <= 0:
            raise t.error("end", "expected an end point different from the start")
        return ReferencePath.line(start, end)
    if kind == "arc":
        t.check_known({"kind", "center", "radius", "start_angle", "end_angle"})
        if dim != 2:
            raise t.error("kind", "an arc path is planar; use waypoints for a 3-D path")
        a0, a1 = t.number("start_angle"), t.number("end_angle")
        if a0 == a1:
            raise t.error("end_angle", "expected an angle different from start_angle")
        return ReferencePath.arc(t.vector("center", 2), t.number("radius", positive=True), a0, a1)
    t.check_known({"kind", "points", "file", "closed"})
    closed = t.boolean("closed", False)
    if t.has("points") == t.has("file"):
        raise t.error("points", "expected exactly one of `points` (inline) or `file` (CSV)")
    if t.has("points"):
        wp = t.matrix("points", dim, min_rows=2)
    else:
        wp_file = (file.parent / t.string("file")).resolve()
        try:
            lines = read_text(wp_file).splitlines()
        except ConfigError as exc:
            raise t.error("file", f"waypoint file {wp_file}: {exc.message}") from None
        try:
            with warnings.catch_warnings():             # "no data": the shape check below says so
                warnings.simplefilter("ignore", UserWarning)
                wp = np.loadtxt(lines, delimiter=",", comments="#", ndmin=2)
        except ValueError as exc:
            raise t.error("file", f"{wp_file} is not a CSV of numbers ({exc})") from None
        if wp.shape[1] != dim or wp.shape[0] < 2 or not np.all(np.isfinite(wp)):
            raise t.error("file", f"{wp_file}: expected at least 2 rows of {dim} finite numbers, got shape {wp.shape}")
    try:
        return ReferencePath.from_waypoints(wp, closed=closed)
    except ValueError as exc:
        raise t.error("points" if t.has("points") else "file", str(exc)) from None


def _load_obstacle(t: Table, dim: int) -> ObstacleSpec:
    shapes = SHAPES_2D if dim == 2 else SHAPES_3D
    kind = t.string("shape", choices=tuple(shapes))
    size_keys = {f.name for f in fields(shapes[kind])}
    t.check_known({"id", "shape", "center", "yaw", "velocity", "trigger", "trigger_distance"} | size_keys)
    sizes = {k: t.number(k, positive=True) for k in sorted(size_keys)}
    try:
        shape = shape_from_table(kind, sizes)
    except ValueError as exc:
        raise t.error("shape", str(exc)) from None
    trigger = t.string("trigger", "always", choices=TRIGGERS)
    if trigger == "always":
        if t.has("trigger_distance"):
            raise t.error("trigger_distance", "only meaningful with trigger = \"move\" or \"appear\"")
        trigger_distance = 0.0
    else:
        trigger_distance = t.number("trigger_distance", positive=True)
    return ObstacleSpec(id=t.string("id"), shape=shape, center=t.vector("center", dim),
                        yaw=t.number("yaw", 0.0), velocity=t.vector("velocity", dim, np.zeros(dim).tolist()),
                        trigger=trigger, trigger_distance=trigger_distance)


def _check_start_is_free(s: Scenario) -> None:
    position, yaw = s.start[:s.dim], (s.start[2] if s.platform == "ground" else s.start[-1])
    for i, o in enumerate(s.obstacles):
        if o.trigger == "appear":
            continue
        gap = s.footprint.clearance(o.shape, o.center, o.yaw, position, yaw)
        if gap < 0.0:
            raise ConfigError(s.file, f"obstacles[{i}]",
                              f"obstacle {o.id!r} covers the start position (clearance {gap:.2f} m)")


LINE_TOML = """name = "{name}"
platform = "ground"
control_period = 0.05
t_max = {t_max}
[vehicle]
plant = "dynamic_bicycle"
[path]
kind = "line"
start = [0.0, 0.0]
end = [{length}, 0.0]
[start]
position = [0.0, {y0}]
speed = {speed}
[speed]
desired = {speed}
a_lat_max = {a_lat_max}
[goal]
tolerance = 1.0
stop = {stop}
[metrics]
q1 = 1.0
q2 = 1.0
R = [[0.1, 0.0], [0.0, 1.0]]
{obstacles}
"""


def line_scenario_toml(name: str, *, length: float = 60.0, y0: float = 0.0, speed: float = 5.0,
                       a_lat_max: float = 3.0, t_max: float = 20.0, obstacles: str = "", stop: bool = False) -> str:
    """TOML of a ground scenario on the straight road (0, 0) -> (length, 0) with the car starting
    y0 beside it, its goal at the road's end (``stop``: at rest there, else passed at speed);
    ``obstacles`` is TOML text of [[obstacles]] tables (tests and `bench variants`)."""
    return LINE_TOML.format(name=name, length=length, y0=y0, speed=speed, a_lat_max=a_lat_max, t_max=t_max,
                            obstacles=obstacles, stop=str(bool(stop)).lower())
