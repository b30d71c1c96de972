"""Guidance planning: safety, reachability and the kinodynamic limit over random obstacle fields."""

from dataclasses import replace

import numpy as np
import pytest

from vflpcd.config.scenarios import default_guidance, load_scenario
from vflpcd.core.guidance.grid import FieldGrid, integrate
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.config.params import guidance_params
from vflpcd.core.guidance.planner import FOLLOW_SPEEDS, FOLLOW_SLACK, GuidancePlanner, _crossing_spans
from vflpcd.core.guidance.speed import plan_speed, smooth_path
from vflpcd.core.guidance.tighten import CLEAR_TOLERANCE, Keepout
from vflpcd.core.guidance.trajectory import timed_trajectory
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Box, Circle, Ellipse
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import Table


@pytest.fixture(scope="module")
def params():
    return default_guidance()


def static(oid, shape, x, y, yaw=0.0):
    return ObstacleState(id=oid, shape=shape, center=np.array([x, y]), yaw=yaw, velocity=np.zeros(2), stamp=0.0)


def turn_curvature(xy):
    """Independent curvature estimate: turn angle between consecutive segments over their mean length."""
    d = np.diff(xy, axis=0)
    ang = np.arctan2(d[:, 1], d[:, 0])
    turn = np.abs(np.angle(np.exp(1j * np.diff(ang))))
    ds = 0.5 * (np.linalg.norm(d[1:], axis=1) + np.linalg.norm(d[:-1], axis=1))
    return np.concatenate([[0.0], turn / ds, [0.0]])


def assert_body_clear(planner, plan, obstacles, what):
    """The planned path keeps the body (one disc of body_radius here) the tight path's clearance
    from every obstacle's exact shape (to the tolerance of tighten.py), measured independently of
    the planner's half-planes: the signed distance of the shape at every planned point."""
    for o in obstacles:
        gap = o.signed_distance(plan.xy) - planner.body_radius - planner.tight_clearance(o)
        assert np.min(gap) > -CLEAR_TOLERANCE, f"{what}: the path comes {-np.min(gap):.3f} m inside the clearance of {o.id}"


def random_field(rng, planner_factory):
    """A 60 m straight path with 1-4 obstacles whose reactive regions are disjoint and clear of the ends."""
    L = 60.0
    path = ReferencePath.line([0.0, 0.0], [L, 0.0])
    v_d = rng.uniform(2.0, 7.0)
    planner = planner_factory(path, v_d)
    obstacles, x = [], rng.uniform(14.0, 18.0)
    for k in range(rng.integers(1, 5)):
        kind = rng.integers(3)
        shape = (Circle(rng.uniform(0.4, 1.5)) if kind == 0 else
                 Ellipse(rng.uniform(0.6, 2.0), rng.uniform(0.4, 1.2)) if kind == 1 else
                 Box(rng.uniform(0.8, 3.0), rng.uniform(0.6, 1.5)))
        o = static(f"o{k}", shape, 0.0, rng.uniform(-1.5, 1.5), rng.uniform(-np.pi, np.pi))
        reach = planner.implicit(o).reach
        x = x + (reach if k else 0.0)
        if x + reach + 4.0 > L:
            break
        obstacles.append(replace(o, center=np.array([x, o.center[1]])))
        x += reach + 2.0
    return planner, path, obstacles


@pytest.mark.parametrize("chunk", range(4))
def test_random_fields_reach_the_goal_safely_within_the_lateral_acceleration_limit(params, chunk):
    """200 seeded fields; the first half with the kinodynamic field's virtual obstacles, the rest without."""
    a_max = 3.0
    chosen = replace(params, virtual="auto" if chunk < 2 else "off")

    def factory(path, v_d):
        return GuidancePlanner(path, chosen, v_d, a_max, body_radius=1.0, control_period=0.05)

    for seed in range(chunk * 50, chunk * 50 + 50):
        rng = np.random.default_rng(seed)
        planner, path, obstacles = random_field(rng, factory)
        prepared = planner.prepare(0.0, obstacles)
        plan = planner.plan(prepared, np.array([0.0, 0.0]), 0.0, planner.v_desired)
        assert plan.reached, f"seed {seed}"
        assert np.linalg.norm(plan.xy[-1] - path.point_at(path.length)) < 0.5, f"seed {seed}"
        for term in prepared.field.statics:
            o = term.implicit
            assert np.min(o.value(plan.raw)) > o.c, f"seed {seed}: raw path enters Q of {o.name}"
        assert_body_clear(planner, plan, obstacles, f"seed {seed}")
        kappa = turn_curvature(plan.xy)
        assert np.max(plan.v ** 2 * kappa) <= 1.01 * a_max, f"seed {seed}"
        traj = plan.trajectory
        assert np.all(np.diff(traj.t) > 0) and traj.v[-1] < 0.2 and np.all(traj.v >= 0)


@pytest.mark.parametrize("virtual", ["auto", "off"])
def test_symmetric_head_on_obstacle_does_not_deadlock(params, virtual):
    path = ReferencePath.line([0.0, 0.0], [40.0, 0.0])
    planner = GuidancePlanner(path, replace(params, virtual=virtual), 4.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [static("head_on", Circle(1.5), 20.0, 0.0)])
    plan = planner.plan(prepared, np.array([0.0, 0.0]), 0.0, 4.0)
    assert plan.reached and plan.xy[-1, 0] > 39.0
    assert_body_clear(planner, plan, prepared.statics, virtual)
    assert prepared.field.statics[0].side == 1.0  # a tie passes on the left


def test_obstacle_passes_on_the_side_that_leaves_the_path_least(params):
    path = ReferencePath.line([0.0, 0.0], [40.0, 0.0])
    planner = GuidancePlanner(path, params, 4.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [static("above", Circle(1.0), 15.0, 0.8), static("below", Box(3.0, 1.0), 30.0, -0.5)])
    sides = {t.implicit.name: t.side for t in prepared.field.statics}
    assert sides == {"above": -1.0, "below": 1.0}
    plan = planner.plan(prepared, np.array([0.0, 0.0]), 0.0, 4.0)
    near = lambda x: plan.xy[np.argmin(np.abs(plan.xy[:, 0] - x)), 1]  # noqa: E731
    assert near(15.0) < -1.0 and near(30.0) > 1.0


def test_auto_virtual_obstacles_respect_remark_1_and_stop_after_the_actual_region(params):
    path = ReferencePath.line([0.0, 0.0], [60.0, 0.0])
    planner = GuidancePlanner(path, replace(params, virtual="auto"), 6.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [static("car", Box(4.5, 1.9), 30.0, 0.3)])
    assert len(prepared.field.virtuals) == 1
    v = prepared.field.virtuals[0]
    assert v.implicit.axes[0] == pytest.approx(6.0 ** 2 / 3.0 + params.virtual_buffer)
    pts = path.point_at(np.linspace(0, 60, 6001))
    in_q = v.implicit.value(pts) < v.implicit.c
    assert np.all(v.parent.value(pts[in_q]) < 0.0)                       # in-Q_vrtl ∩ P ⊂ in-R_actl ∩ P
    plan = planner.plan(prepared, np.array([0.0, 0.0]), 0.0, 6.0)
    off = plan.virtual_off[0]
    assert off is not None
    p_off = plan.raw[off]
    progress = prepared.field.path.progress(p_off[None, :])[0]
    assert v.parent.value(p_off[None, :])[0] <= 0.0 or progress >= v.x_stop  # stopped at R_actl (remark 2)
    # once past, the virtual obstacle no longer acts in its buffer region: a trajectory started
    # there takes the same first step with and without it
    probe = np.array([v.x_stop + 1.0, v.implicit.center[1] + 0.8 * v.implicit.axes[0] * np.sign(-v.implicit.center[1])])
    probe[1] = v.implicit.center[1] - np.sign(v.implicit.center[1]) * 0.5 * v.implicit.axes[0]
    assert v.implicit.value(probe[None, :])[0] < 0.0 and v.parent.value(probe[None, :])[0] > 0.0
    bare = replace(prepared.field, virtuals=[])
    first = integrate(prepared.field, prepared.grid, probe, prepared.x_end, 0.1, 1e-3, 1).xy[1]
    assert first == pytest.approx(integrate(bare, prepared.grid, probe, prepared.x_end, 0.1, 1e-3, 1).xy[1])
    # and before R_actl it has already turned the robot towards the passing side
    side = prepared.field.statics[0].side
    plain = planner.plan(replace(prepared, field=bare), np.zeros(2), 0.0, 6.0).raw
    at_stop = lambda xy: xy[np.argmin(np.abs(xy[:, 0] - (v.x_stop - 0.5)))]  # noqa: E731
    assert side * at_stop(plan.raw)[1] > side * at_stop(plain)[1] + 0.1


def test_obstacle_on_the_start_or_the_goal_is_named(params):
    path = ReferencePath.line([0.0, 0.0], [40.0, 0.0])
    planner = GuidancePlanner(path, params, 4.0, 3.0, 1.0, 0.05)
    with pytest.raises(GuidanceError, match="'blocker' covers the goal"):
        planner.prepare(0.0, [static("blocker", Circle(1.0), 40.5, 0.0)])
    prepared = planner.prepare(0.0, [static("rock", Circle(1.0), 1.0, 0.5)])
    with pytest.raises(GuidanceError, match="'rock' covers the start"):
        planner.plan(prepared, np.array([0.0, 0.0]), 0.0, 4.0)


@pytest.mark.parametrize("offset", [0.004, -0.0123, 0.03, -0.049, 0.2])
@pytest.mark.parametrize("y0", [0.0, 0.037])
def test_a_trajectory_started_beside_its_route_converges_to_it(params, offset, y0):
    """A robot a few centimetres off its route (its tracking error when it replans) is planned
    back onto the route, wherever the route lies between the grid's nodes: the path's term is
    interpolated between them (at the nearest node, a start within h / 2 = 5 cm ran parallel to
    the route at its offset)."""
    path = ReferencePath.line([0.0, y0], [60.0, y0])
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [])
    raw = integrate(prepared.field, prepared.grid, np.array([0.0, y0 + offset]), prepared.x_end, 0.1, 1e-3, 1000,
                    heading=np.array([1.0, 0.0])).xy
    lateral = raw[:, 1] - y0
    at = lambda x: abs(lateral[np.argmin(np.abs(raw[:, 0] - x))])   # noqa: E731
    assert at(0.0) == pytest.approx(abs(offset))
    # the field's rate k_p = 1 / m: e^-5 of the offset after 5 m of path, nothing after 10
    assert at(5.0) < 0.02 * abs(offset) + 1e-4 and at(10.0) < 1e-4 and np.max(np.abs(lateral[raw[:, 0] > 10.0])) < 1e-4
    plan = planner.plan(prepared, np.array([0.0, y0 + offset]), 0.0, 6.0)
    assert np.max(np.abs(plan.xy[plan.xy[:, 0] > 15.0, 1] - y0)) < 1e-3


def test_a_plan_that_leaves_the_field_s_grid_is_an_error_naming_how_far_and_where(params, monkeypatch):
    """The steps after the integration (here a fairing that swings the path out at 45 degrees from
    10 m on) are checked to keep within the grid the field and the obstacles are known in."""
    import vflpcd.core.guidance.planner as planner_module

    path = ReferencePath.line([0.0, 0.0], [60.0, 0.0])
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [])
    assert np.max(np.abs(planner.plan(prepared, np.zeros(2), 0.0, 6.0).xy[:, 1])) < 1e-6
    assert prepared.grid.bounds[3] == pytest.approx(params.corridor, abs=params.grid_resolution)

    def swung(xy, *args, **kwargs):
        out = np.array(xy, float)
        out[:, 1] += np.clip(out[:, 0] - 10.0, 0.0, None)
        return out

    monkeypatch.setattr(planner_module, "fair_path", swung)
    with pytest.raises(GuidanceError, match=r"the plan leaves the field's grid: 4\d\.\d m beyond it at "
                                            r"\[5\d\.\d, 4\d\.\d\] \(grid x -8\.0\.\.\d+\.\d, y -8\.0\.\.8\.0\)"):
        planner.plan(prepared, np.zeros(2), 0.0, 6.0)


def test_leaving_the_grid_is_an_error(params):
    path = ReferencePath.line([0.0, 0.0], [40.0, 0.0])
    planner = GuidancePlanner(path, params, 4.0, 3.0, 1.0, 0.05)
    prepared = planner.prepare(0.0, [])
    tiny = FieldGrid.build(prepared.field, (-1.0, 5.0, -1.0, 1.0), 0.1)
    with pytest.raises(GuidanceError, match="left the grid"):
        integrate(prepared.field, tiny, np.zeros(2), prepared.x_end, 0.1, 1e-3, 1000)


def test_bad_guidance_parameters_are_named(tmp_path):
    text = (config_dir() / "guidance.toml").read_text()
    for old, new, field in (("k_p = 1.0", "k_p = nan", "k_p"), ("beta = 0.1", "beta = -0.1", "beta"),
                            ('virtual = "off"', 'virtual = "sometimes"', "virtual")):
        t = Table(__import__("tomllib").loads(text.replace(old, new)), "g.toml")
        with pytest.raises(ConfigError, match=f"g.toml: {field}:"):
            guidance_params(t)
    base = guidance_params(Table(__import__("tomllib").loads(text), "g.toml"))
    t = Table({"virtual_obstacles": [{"center": [1.0, 2.0], "radius": 3.0, "c": 0.2, "parent": "x"}]}, "s.toml",
              "guidance")
    with pytest.raises(ConfigError, match=r"guidance.virtual_obstacles\[0\].c: .*c_i < 0"):
        guidance_params(t, base)


def test_dense_static_plan_is_safe_and_timed(params):
    s = load_scenario("dense_static")
    planner = GuidancePlanner(s.path, params, s.v_desired, s.a_lat_max, s.footprint.radius, s.control_period)
    obstacles = [static(o.id, o.shape, *o.center, o.yaw) for o in s.obstacles]
    prepared = planner.prepare(0.0, obstacles)
    plan = planner.plan(prepared, s.start[:2], 0.0, s.start[3])
    assert plan.reached
    traj = plan.trajectory
    assert traj.t[1] - traj.t[0] == pytest.approx(s.control_period)
    assert np.max(np.abs(traj.v ** 2 * traj.kappa)) <= 1.01 * s.a_lat_max
    ref = traj.vehicle_states()
    assert ref.shape == (len(traj.t), 6) and np.all(np.isfinite(ref))


@pytest.mark.parametrize("kappa_limit, heading", [(np.inf, None), (0.17, 0.4)])
def test_replanning_from_mid_path_around_a_crossing_obstacle(params, kappa_limit, heading):
    """Moving obstacles: the plan starts where the robot is and avoids where the obstacle will be,
    also when fairing resamples the path (a car's curvature limit and a start heading off the field)."""
    path = ReferencePath.line([0.0, 0.0], [80.0, 0.0])
    planner = GuidancePlanner(path, replace(params, horizon=40.0), 4.0, 3.0, 1.0, 0.05, kappa_limit=kappa_limit)
    prepared = planner.prepare(20.0, [])
    assert prepared.s_end == pytest.approx(60.0)
    crossing = ObstacleState(id="walker", shape=Circle(0.5), center=np.array([35.0, -6.0]), yaw=0.0,
                             velocity=np.array([0.0, 1.5]), stamp=10.0)
    start = np.array([20.0, 1.5])
    plan = planner.plan(prepared, start, 10.0, 4.0, movers=[crossing], heading=heading)
    assert plan.reached and plan.xy[0] == pytest.approx(start, abs=0.05)
    traj = plan.trajectory
    o = plan.field.movers[0].implicit
    at_time = np.array([o.value(p[None, :], t)[0] for p, t in zip(traj.pos, traj.t)])
    assert np.min(at_time) > o.c                       # never inside the walker's repulsive boundary
    straight = np.column_stack([20.0 + 4.0 * (traj.t - 10.0), np.zeros_like(traj.t)])
    assert np.min([o.value(p[None, :], t)[0] for p, t in zip(straight, traj.t)]) < o.c  # the straight line would be


def test_manual_virtual_obstacle_from_a_scenario_overrides_the_automatic_one(params, tmp_path):
    text = (config_dir() / "scenarios" / "dense_static.toml").read_text() + """
[guidance]
virtual = "auto"

[[guidance.virtual_obstacles]]
center = [5.0, -6.0]
radius = 5.0
c = -0.2
parent = "c1"
gamma = 1
"""
    f = tmp_path / "manual.toml"
    f.write_text(text)
    s = load_scenario(f)
    assert s.guidance.virtual == "auto" and len(s.guidance.virtual_obstacles) == 1
    planner = GuidancePlanner(s.path, s.guidance, s.v_desired, s.a_lat_max, s.footprint.radius, s.control_period)
    prepared = planner.prepare(0.0, [static(o.id, o.shape, *o.center, o.yaw) for o in s.obstacles])
    (v,) = prepared.field.virtuals
    assert v.implicit.center == pytest.approx([5.0, -6.0]) and v.implicit.c == -0.2 and v.gamma == 1.0
    assert v.parent.name == "c1"
    bad = guidance_params(Table({"virtual_obstacles": [
        {"center": [5.0, -6.0], "radius": 5.0, "c": -0.2, "parent": "nobody"}]}, "s.toml", "guidance"), s.guidance)
    with pytest.raises(GuidanceError, match="parent 'nobody'"):
        GuidancePlanner(s.path, bad, 3.0, 2.0, 1.25, 0.05).prepare(0.0, [static("c1", Circle(1.0), 8.0, 1.2)])


@pytest.mark.parametrize("v_start, v_end", [(7.0, None), (7.0, 0.0), (2.0, None), (0.0, None)])
def test_a_cap_below_the_start_speed_is_reached_by_braking_not_by_a_step(params, v_start, v_end):
    """A cap of 3 m/s from the start of a straight 60 m path, the robot at ``v_start``: the profile
    starts at the robot's speed (before, at the cap: a step the tracking braked hard for), brakes
    no harder than a_decel, meets the cap where braking at a_decel from v_start does, and
    keeps the acceleration limit and the stop; a robot slower than the cap accelerates as before."""
    xy = np.column_stack([np.linspace(0.0, 60.0, 241), np.zeros(241)])
    cap = np.where(xy[:, 0] < 40.0, 3.0, 7.0)
    s, _, v = plan_speed(xy, cap, 3.0, params.a_accel, params.a_decel, v_start, v_end)
    assert v[0] == v_start
    rate = np.diff(v ** 2) / (2.0 * np.diff(s))
    assert rate.min() >= -params.a_decel - 1e-9 and rate.max() <= params.a_accel + 1e-9
    capped = s < 40.0
    if v_start > 3.0:       # braking at a_decel down to the cap
        expected = np.maximum(np.sqrt(np.maximum(v_start ** 2 - 2.0 * params.a_decel * s, 0.0)), 3.0)
    else:                   # accelerating at a_accel up to it
        expected = np.minimum(np.sqrt(v_start ** 2 + 2.0 * params.a_accel * s), 3.0)
    assert np.allclose(v[capped], expected[capped], rtol=0.0, atol=1e-9)
    if v_end is not None:
        assert v[-1] == 0.0


def test_the_speed_plan_keeps_the_steering_rate_in_a_quick_swerve_and_leaves_steady_bends_alone(params):
    """A 3.5 m lane change over 8 m, planned at up to 9 m/s within the lateral-acceleration limit,
    asks the SUV's steering (0.6 rad/s, wheelbase 3.14 m) for twice its rate: with kappa_rate_max
    the speed there keeps v |d kappa / ds| within it; a
    straight road and a circle of constant curvature keep their speeds (the centripetal limit
    alone)."""
    from vflpcd.core.guidance.speed import curvature_rate

    rate_max = 0.6 / 3.14
    x = np.linspace(0.0, 80.0, 321)
    ramp = np.clip((x - 30.0) / 8.0, 0.0, 1.0)
    swerve = np.column_stack([x, 3.5 * ramp ** 3 * (10.0 - 15.0 * ramp + 6.0 * ramp ** 2)])
    s, _, free = plan_speed(swerve, 9.0, 3.0, params.a_accel, params.a_decel, 9.0)
    s, _, v = plan_speed(swerve, 9.0, 3.0, params.a_accel, params.a_decel, 9.0, kappa_rate_max=rate_max)
    need = curvature_rate(swerve, s)
    assert np.max(free * need) > 2.0 * rate_max                          # unaware, beyond the steering
    assert np.all(v * need <= rate_max * (1.0 + 1e-9)) and v.min() < 0.7 * free.min()
    assert np.all(v <= free + 1e-12)
    for path in (np.column_stack([x, np.zeros_like(x)]),
                 20.0 * np.column_stack([np.cos(x / 20.0), np.sin(x / 20.0)])):
        _, _, plain = plan_speed(path, 9.0, 3.0, params.a_accel, params.a_decel, 4.0)
        _, _, capped = plan_speed(path, 9.0, 3.0, params.a_accel, params.a_decel, 4.0, kappa_rate_max=rate_max)
        np.testing.assert_allclose(capped, plain, rtol=0.0, atol=1e-9)


@pytest.mark.parametrize("start_y", [-40.0, -37.0])     # at 6 m/s both reach the crossing at about 6.7 s
def test_a_car_crossing_the_route_is_yielded_to_not_swerved_round(params, start_y):
    """A car crossing the route at 6 m/s ahead: the plan keeps to the route (no swerve), slows before
    the crossing so that its timed trajectory stays out of the car's repulsive region (at full speed
    on the same path it would enter it), and is back at the desired speed beyond it."""
    path = ReferencePath.line([0.0, 0.0], [100.0, 0.0])
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.25, 0.05)
    car = ObstacleState(id="crossing", shape=Box(4.5, 1.9), center=np.array([40.0, start_y]), yaw=np.pi / 2,
                        velocity=np.array([0.0, 6.0]), stamp=0.0)
    prepared = planner.prepare(0.0, [])
    plan = planner.plan(prepared, np.zeros(2), 0.0, 6.0, [car], heading=0.0)
    term = plan.field.movers[0]
    assert term.crosses
    assert np.max(np.abs(plan.xy[:, 1])) < 0.05                                # on the route
    assert not planner.meets_mover(plan.field.movers, plan.trajectory)        # clear of the car as timed
    assert np.min(plan.v) < 0.95 * planner.v_desired                           # it slowed for it
    assert plan.v[0] == 6.0                                                    # from the car's speed, braking
    assert np.min(np.diff(plan.v ** 2) / (2.0 * np.diff(plan.s))) >= -params.a_decel - 1e-9
    assert plan.v[-1] == pytest.approx(planner.v_desired)                      # and went on at speed
    s_, _, v_ = plan_speed(plan.xy, planner.v_desired, 3.0, params.a_accel, params.a_decel, 6.0)
    full_speed = timed_trajectory(plan.xy, s_, v_, 0.0, 0.05)
    assert planner.meets_mover(plan.field.movers, full_speed)                  # at full speed it would meet the car


@pytest.mark.parametrize("speed, side", [(4.0, -1.0), (-4.0, 1.0), (1.2, -1.0), (-1.2, 1.0), (0.9, -1.0), (-0.9, 1.0),
                                         (0.6, 1.0)])
def test_a_crosser_is_passed_behind_and_a_dawdler_where_it_leaves_the_path_least(params, speed, side):
    """A cyclist at 4 m/s or a walker at 1.2 m/s, or a slow one at 0.9 m/s, crossing from either side
    is passed on the side it comes from; one that crosses at 0.6 m/s, 1 m right of the path, is
    passed on the left (the side its region reaches less far)."""
    path = ReferencePath.line([0.0, 0.0], [80.0, 0.0])
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.0, 0.05)
    y = -1.0 if speed > 0 else 1.0
    mover = ObstacleState(id="m", shape=Circle(0.5), center=np.array([30.0, y]), yaw=0.0,
                          velocity=np.array([0.0, speed]), stamp=0.0)
    term = planner.actual_term(planner.implicit(mover), 0.0)
    assert term.side == side


def test_a_plan_into_a_slow_car_it_cannot_pass_is_slowed_to_follow_it(params):
    """followed(): the lane's own points, speed-planned slower until the trajectory stays out of the
    slow car's repulsive region; none for a car coming the other way on them. Where an oncoming
    car near the centre line reaches into the lane with its region at every speed, the lane behind
    the slow car is taken on the cars' shapes (given their states), not the swerve; a swerve that
    keeps out of the regions comes first, unless it breaks the steering limit."""
    path = ReferencePath.line([0.0, 0.0], [120.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)
    xy = np.column_stack([np.linspace(0.0, 100.0, 401), np.zeros(401)])

    def state(x, vx, y=0.0):
        return ObstacleState(id=f"car{x:g}", shape=Box(4.5, 1.9), center=np.array([x, y]),
                             yaw=0.0 if vx >= 0 else np.pi, velocity=np.array([vx, 0.0]), stamp=0.0)

    def mover(x, vx, y=0.0):
        return planner.actual_term(planner.implicit(state(x, vx, y)), 0.0)

    lead = [mover(20.0, 3.0)]
    s, kappa, v = plan_speed(xy, 7.0, 3.0, params.a_accel, params.a_decel, 7.0)
    assert planner.meets_mover(lead, timed_trajectory(xy, s, v, 0.0, 0.05), FOLLOW_SLACK)
    path_xy, s, kappa, v, trajectory = planner.followed(lead, [(xy, False)], 0.0, 7.0)
    assert path_xy is xy
    assert not planner.meets_mover(lead, trajectory) and v.max() <= 7.0 and v[-1] < 3.5
    assert planner.followed([mover(60.0, -7.0)], [(xy, False)], 0.0, 7.0) is None
    assert planner.followed([mover(60.0, -7.0)], [(xy, False)], 0.0, 7.0, [state(60.0, -7.0)]) is None
    oncoming = (60.0, -7.0, 2.4)        # its side 0.5 m from the side of a car in the lane
    movers, states = [mover(20.0, 3.0), mover(*oncoming)], [state(20.0, 3.0), state(*oncoming)]
    slowed = [planner.timed(xy, f * 7.0, 7.0, 0.0, False)[3] for f in FOLLOW_SPEEDS]
    assert all(planner.meets_mover(movers, trajectory) for trajectory in slowed)
    assert planner.followed(movers, [(xy, False)], 0.0, 7.0) is None
    path_xy, s, kappa, v, trajectory = planner.followed(movers, [(xy, False)], 0.0, 7.0, states)
    assert path_xy is xy and not planner.touches_mover(states, trajectory) and v[-1] < 3.5
    # a swerve clear of both regions is taken before the lane on the shapes; with a stretch beyond
    # the steering limit (a weave of the field between movers) it is not taken at any speed
    ease = np.clip(xy[:, 0] / 30.0, 0.0, 1.0)
    swerve = np.column_stack([xy[:, 0], -5.0 * ease ** 2 * (3.0 - 2.0 * ease)])
    assert planner.followed(movers, [(xy, False), (swerve, False)], 0.0, 7.0, states)[0] is swerve
    kinked = swerve.copy()
    kinked[300:, 1] += 1.0                      # a 1 m step sideways at x = 75 m
    assert planner.followed(movers, [(xy, False), (kinked, False)], 0.0, 7.0, states)[0] is kinked
    car = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05, kappa_limit=0.174)     # the SUV's steering
    assert car.followed(movers, [(xy, False), (kinked, False)], 0.0, 7.0, states)[0] is xy


def test_a_graze_of_a_movers_region_is_not_a_conflict_to_follow(params):
    path = ReferencePath.line([0.0, 0.0], [120.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)
    o = ObstacleState(id="car", shape=Box(4.5, 1.9), center=np.array([40.0, 0.0]), yaw=0.0,
                      velocity=np.array([2.0, 0.0]), stamp=0.0)
    term = planner.actual_term(planner.implicit(o), 0.0)
    imp = term.implicit
    # a straight line beside the car, just inside its repulsive boundary at the closest point
    for y in np.linspace(4.0, 1.0, 61):
        xy = np.column_stack([np.linspace(0.0, 100.0, 401), np.full(401, y)])
        s, kappa, v = plan_speed(xy, 7.0, 3.0, params.a_accel, params.a_decel, 7.0)
        traj = timed_trajectory(xy, s, v, 0.0, 0.05)
        if planner.meets_mover([term], traj):
            break
    assert planner.meets_mover([term], traj) and not planner.meets_mover([term], traj, FOLLOW_SLACK)


def test_smoothing_keeps_a_bend_of_the_path_and_a_plan_that_starts_on_it_stays_on_it(params):
    """The smoothing acts on the offset from the path: on an 18 m arc with no obstacle the plan lies
    on the path (plain Gaussian smoothing of the points cuts the bend by sigma^2 kappa / 2, 2.8 cm
    here), also at its start, where the smoothing fades out."""
    radius = 18.0
    path = ReferencePath.arc([0.0, radius], radius, -np.pi / 2, np.pi / 2)
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.0, 0.05)
    s0 = 10.0
    prepared = planner.prepare(s0, [])
    plan = planner.plan(prepared, path.point_at(s0), 0.0, 6.0, heading=float(path.heading_at(s0)))
    def offsets(xy):
        return np.array([path.project(p, None).lateral for p in xy[::5]])

    off = offsets(plan.xy)
    assert abs(np.mean(off)) < 0.005 and np.max(np.abs(off)) < 0.02 and abs(off[0]) < 1e-9
    cut = offsets(smooth_path(plan.raw, params.smoothing / params.beta))   # the points smoothed themselves
    assert abs(np.mean(cut[10:-10])) > 0.8 * params.smoothing ** 2 / (2.0 * radius)
    kappa = turn_curvature(plan.xy[5:-5])
    assert np.all(np.abs(kappa[1:-1] - 1.0 / radius) < 0.5 / radius)


@pytest.mark.parametrize("offset, limit", [(0.0, 0.01), (0.05, 0.02), (0.3, 0.1)])
def test_a_plan_that_starts_beside_its_path_has_no_yaw_rate_spike_where_the_smoothing_fades(params, offset, limit):
    """A plan from ``offset`` m beside an 18 m arc: the start offset that the smoothing keeps fades
    out along a C2 smoothstep, so the timed reference's yaw rate has no one-sample spike (with a
    linear fade the points had a kink there: spikes of 0.05, 0.045 and 0.79 rad/s for these
    offsets; the limits here are a fifth to a half of them)."""
    radius = 18.0
    path = ReferencePath.arc([0.0, radius], radius, -np.pi / 2, np.pi / 2)
    planner = GuidancePlanner(path, params, 6.0, 3.0, 1.0, 0.05)
    s0 = 10.0
    h = float(path.heading_at(s0))
    start = path.point_at(s0) + offset * np.array([-np.sin(h), np.cos(h)])
    plan = planner.plan(planner.prepare(s0, []), start, 0.0, 6.0, heading=h)
    omega = plan.trajectory.omega[:60]
    spike = np.abs(omega[1:-1] - 0.5 * (omega[:-2] + omega[2:]))
    assert np.max(spike) < limit, np.round(omega, 3)


def test_a_slow_car_that_cannot_be_passed_is_followed_in_the_lane(params):
    """A car 30 m ahead at 3 m/s and a stream of oncoming cars in the other lane: the field's path
    round the slow car meets the stream, so the plan follows, and it follows on the lane (the plan
    without the movers), not crawling along the swerve it could not take."""
    path = ReferencePath.line([0.0, 0.0], [150.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)

    def car(oid, x, y, vx):
        return ObstacleState(id=oid, shape=Box(4.5, 1.9), center=np.array([x, y]), yaw=0.0,
                             velocity=np.array([vx, 0.0]), stamp=0.0)

    movers = [car("slow", 30.0, 0.0, 3.0)] + [car(f"on{k}", 40.0 + 30.0 * k, 3.5, -7.0) for k in range(5)]
    plan = planner.plan(planner.prepare(0.0, []), np.array([0.0, 0.0]), 0.0, 7.0, movers, heading=0.0)
    assert np.max(np.abs(plan.xy[:, 1])) < 0.05
    assert plan.v[0] == 7.0 and plan.v[1:].max() < 7.0      # it joins the car's speed and brakes from it
    assert not planner.meets_mover(plan.field.movers, plan.trajectory)


def test_a_crossing_walker_is_yielded_to_while_a_slow_car_ahead_is_passed_tightly(params):
    """A slow car ahead that the plan passes (by the tight path, closer than the car's repulsive
    region) and a walker crossing farther on: the yielding plan exists (it used to be refused
    because the tight pass enters the car's region by design), meets no crossing mover and keeps
    the tight clearance from the car."""
    path = ReferencePath.line([0.0, 0.0], [140.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05, kappa_limit=0.17)
    slow = ObstacleState(id="slow", shape=Box(4.5, 1.9), center=np.array([20.0, 0.0]), yaw=0.0,
                         velocity=np.array([2.0, 0.0]), stamp=0.0)
    walker = ObstacleState(id="walker", shape=Circle(0.4), center=np.array([70.0, -7.0]), yaw=0.0,
                           velocity=np.array([0.0, 1.4]), stamp=0.0)
    prepared = planner.prepare(0.0, [])
    field = replace(prepared.field, movers=[planner.actual_term(planner.implicit(o), 0.0) for o in (slow, walker)])
    plan = planner.yielding(prepared, field, np.zeros(2), 0.0, 7.0, np.array([1.0, 0.0]), [slow, walker], [walker])
    assert plan is not None
    assert np.max(np.abs(plan.xy[:, 1])) > 1.0                     # it passes the slow car
    assert not planner.meets_mover([field.movers[1]], plan.trajectory)
    assert planner.least_gap(plan.trajectory, [Keepout(slow, planner.tight_clearance(slow))]) > -CLEAR_TOLERANCE


def test_the_body_touching_a_mover_is_found_where_the_region_test_lets_it_pass(params):
    """touches_mover: the body's discs in a mover's shape along the timed trajectory, from no closer
    than they start."""
    path = ReferencePath.line([0.0, 0.0], [120.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)

    def car(x, y, vx):
        return ObstacleState(id="car", shape=Box(4.5, 1.9), center=np.array([x, y]), yaw=0.0,
                             velocity=np.array([vx, 0.0]), stamp=0.0)

    def lane(y0=0.0, y1=0.0):
        xy = np.column_stack([np.linspace(0.0, 100.0, 401), np.linspace(y0, y1, 401)])
        s, kappa, v = plan_speed(xy, 7.0, 3.0, params.a_accel, params.a_decel, 7.0)
        return timed_trajectory(xy, s, v, 0.0, 0.05)

    assert planner.touches_mover([car(20.0, 0.0, 2.0)], lane())           # into the slow car's rear
    assert not planner.touches_mover([car(20.0, 4.0, 2.0)], lane())       # beside it, a lane over
    assert not planner.touches_mover([static("post", Circle(0.3), 20.0, 0.0)], lane())   # statics: not its job
    beside = car(0.0, 1.6, 7.0)                   # alongside at the same speed, discs already in it
    assert not planner.touches_mover([beside], lane())
    assert planner.touches_mover([beside], lane(0.0, 1.0))                # and drifting closer


def test_a_late_pass_of_a_slow_car_keeps_the_body_out_of_it(params):
    """`bench variants` seed 22: the slow car starts moving (2.1 m/s) 26 m ahead of the car; the
    replan asked then passed it by a tight path re-timed so that the body's discs entered its shape
    by 0.46 m (the field's regions said it passed), and the car came within 0.10 m of its corner."""
    from sim.bench.variants import variant_toml
    from vflpcd.controllers.vflpc import make_vflpc
    from vflpcd.core.vflpc import ReplanJob, plan_job

    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory() as d:
        f = Path(d) / "variant22.toml"
        f.write_text(variant_toml(22))
        scenario = load_scenario(f)
    planner = make_vflpc(scenario).planner
    t = 8.95        # what the car knew then (the walker and the slow car moving)
    slow = ObstacleState("slow_car", Box(4.5, 1.9), np.array([87.554, -0.449]), 0.0, np.array([2.111, 0.0]), t)
    obstacles = (ObstacleState("pedestrian", Circle(0.431), np.array([42.430, -2.002]), 0.0,
                               np.array([-0.244, -0.969]), t), slow,
                 ObstacleState("barrel", Circle(0.6), np.array([63.819, -0.341]), 0.0, np.zeros(2), t))
    job = ReplanJob(61.652, np.array([61.652, 1.518]), np.array([6.822, 1.092]), 0.1588, t, obstacles)
    plan = plan_job(planner, job).plan
    assert planner.least_gap(plan.trajectory, [Keepout(slow, 0.0)]) > 0.3
    assert not planner.touches_mover([slow], plan.trajectory)



def test_crossing_spans_skip_a_mover_whose_line_is_passed_and_are_nearest_first(params):
    """_crossing_spans: a walker whose line of motion lies behind the path's start has none; the
    others' entries (within reach of their line) and ends (past the line) are ordered by entry."""
    path = ReferencePath.line([0.0, 0.0], [100.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)
    xy = np.column_stack([np.linspace(20.0, 100.0, 321), np.zeros(321)])
    s = np.linspace(0.0, 80.0, 321)

    def walker(oid, x, y):
        o = ObstacleState(id=oid, shape=Circle(0.4), center=np.array([x, y]), yaw=0.0,
                          velocity=np.array([0.0, 1.4]), stamp=0.0)
        return planner.actual_term(planner.implicit(o), 0.0).implicit

    movers = [walker("far", 60.0, -8.0), walker("behind", 10.0, -3.0), walker("near", 24.0, -3.0)]
    spans = _crossing_spans(xy, s, movers, 0.0)
    assert [i for _, _, i in spans] == [2, 0]
    for (entry, across, i), line in zip(spans, (24.0, 60.0)):
        assert entry == pytest.approx(max(line - movers[i].reach - 20.0, 0.0), abs=0.26)
        assert across == pytest.approx(line - 20.0, abs=0.26) and across >= line - 20.0


def test_a_walker_the_car_passes_ahead_of_and_one_farther_are_yielded_to_by_a_plan_that_brakes_from_its_speed(params):
    """A car at 7 m/s with a walker 4 m ahead that it passes in front of, and another crossing 34 m
    ahead that it would meet: the plan yields to the farther one (the slowing lasts until the path
    has crossed that walker's line). It starts at the car's speed, brakes no harder than a_yield,
    meets neither walker, and slows before the farther walker's line. Before, the slowing ended
    where the nearer walker's reach begins, 0.4 m ahead, and no plan yielded."""
    path = ReferencePath.line([0.0, 0.0], [120.0, 0.0])
    planner = GuidancePlanner(path, params, 7.0, 3.0, 1.25, 0.05)
    walkers = [ObstacleState(id=oid, shape=Circle(0.4), center=np.array([x, y]), yaw=0.0,
                             velocity=np.array([0.0, 1.4]), stamp=0.0) for oid, x, y in (("near", 4.0, -4.5), ("far", 34.0, -7.0))]
    prepared = planner.prepare(0.0, [])
    field = replace(prepared.field, movers=[planner.actual_term(planner.implicit(o), 0.0) for o in walkers])
    assert planner.meets_mover(field.movers[1:], planner.plan(prepared, np.zeros(2), 0.0, 7.0, heading=0.0).trajectory)
    plan = planner.yielding(prepared, field, np.zeros(2), 0.0, 7.0, np.array([1.0, 0.0]), walkers, walkers)
    assert plan is not None
    assert plan.v[0] == 7.0
    assert np.min(np.diff(plan.v ** 2) / (2.0 * np.diff(plan.s))) >= -params.a_yield - 1e-9
    assert not planner.meets_mover(field.movers, plan.trajectory)
    assert np.min(plan.v[plan.xy[:, 0] < 34.0]) < 0.8 * 7.0


@pytest.mark.parametrize("beside", [1.5, 3.0])
def test_a_route_that_turns_back_in_ahead_of_a_slower_car_beside_is_joined_past_it_at_speed(beside):
    """The safety bench's cut_in: at 8 m/s the route turns back into the lane 1 m ahead of a 6 m/s
    car whose front is ``beside`` m behind the car's rear axle line. Braking beside it keeps it
    beside, and the lane cuts in ahead of it: the plan keeps its speed along its line and joins the
    route only once the slower car, a tight_mover_window either side, leaves the body its tight
    clearance (before, the plan braked to 6.3 m/s and swerved into it)."""
    from vflpcd.controllers.vflpc import make_vflpc

    scenario = load_scenario(config_dir() / "scenarios" / "safety" / "cut_in.toml")
    planner = make_vflpc(scenario).planner
    slow = ObstacleState("slow_car", Box(4.5, 1.9), np.array([-1.6 - beside, 0.0]), 0.0, np.array([6.0, 0.0]), 0.0)
    plan = planner.plan(planner.prepare(0.0, []), np.array([0.0, 3.5]), 0.0, 8.0, [slow], heading=0.0)
    assert np.min(plan.v) >= 8.0 - 1e-9
    window = [Keepout(slow, planner.tight_clearance(slow), dt) for dt in (-1.0, 0.0, 1.0)]
    assert planner.least_gap(plan.trajectory, window) > -CLEAR_TOLERANCE
    assert not planner.touches_mover([slow], plan.trajectory)
    assert abs(plan.xy[-1, 1]) < 0.05        # on the route again at the plan's end


def test_a_join_along_a_line_that_leaves_the_field_s_grid_is_not_taken(tmp_path):
    """cut_in with the route turning hard right after the merge: the start's line runs off the
    field's grid before any join keeps clear of the slower car. Such a join is not taken (the
    replan would fail on ``within_grid``, where the field's plan stood before); the plan comes back
    and lies on the grid."""
    from vflpcd.controllers.vflpc import make_vflpc

    text = (config_dir() / "scenarios" / "safety" / "cut_in.toml").read_text()
    turn = ("points = [[0.0, 3.5], [3.0, 3.5], [6.0, 3.0], [9.0, 1.5], [12.0, 0.3], [15.0, 0.0], [20.0, -1.0], "
            "[24.0, -4.0], [27.0, -9.0], [29.0, -20.0], [30.0, -60.0]]\n")
    start = text.index("points = [[")
    end = text.index("]]", start) + 3
    (tmp_path / "turn.toml").write_text(text[:start] + turn + text[end:])
    planner = make_vflpc(load_scenario(tmp_path / "turn.toml")).planner
    slow = ObstacleState("slow_car", Box(4.5, 1.9), np.array([-3.1, 0.0]), 0.0, np.array([6.0, 0.0]), 0.0)
    prepared = planner.prepare(0.0, [])
    plan = planner.plan(prepared, np.array([0.0, 3.5]), 0.0, 8.0, [slow], heading=0.0)
    xmin, xmax, ymin, ymax = prepared.grid.bounds
    assert np.all((plan.xy >= [xmin, ymin]) & (plan.xy <= [xmax, ymax]))


@pytest.mark.parametrize("parked_x", [22.0, 30.0])
def test_a_parked_car_on_the_start_s_line_beside_a_slower_car_makes_the_plan_stop_before_it(parked_x):
    """cut_in with a car parked in the passing lane ahead: no join past the slower car keeps clear
    before it, and the field's plan turned in and was hit (the whole loop: a collision at 0 supervisor
    interventions). The plan holds its line and brakes to rest before the parked car, clear of both."""
    from vflpcd.controllers.vflpc import make_vflpc

    planner = make_vflpc(load_scenario(config_dir() / "scenarios" / "safety" / "cut_in.toml")).planner
    slow = ObstacleState("slow_car", Box(4.5, 1.9), np.array([-3.1, 0.0]), 0.0, np.array([6.0, 0.0]), 0.0)
    parked = static("parked", Box(4.6, 1.9), parked_x, 3.5)
    plan = planner.plan(planner.prepare(0.0, [parked]), np.array([0.0, 3.5]), 0.0, 8.0, [slow], heading=0.0)
    assert plan.v[-1] == 0.0 and np.max(plan.xy[:, 0]) < parked_x
    assert planner.least_gap(plan.trajectory, [Keepout(parked, planner.tight_clearance(parked))]) > -CLEAR_TOLERANCE
    assert not planner.touches_mover([slow], plan.trajectory)
