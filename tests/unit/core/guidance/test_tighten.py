"""The tight path (vflpcd/core/guidance/tighten.py): as close to the reference path as the body's
clearance lets it, never closer, and the field's own path where no tight path exists."""

from dataclasses import replace
from functools import partial

import numpy as np

from vflpcd.base.paths import config_dir
from vflpcd.config.scenarios import default_guidance
from vflpcd.core.guidance.planner import GuidancePlanner
from vflpcd.core.guidance.tighten import CLEAR_TOLERANCE, Body, Keepout, disc_gaps, tighten_path
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath, feet_on_polyline, unit_differences
from vflpcd.core.shapes import Box, Circle

CAR = Body(offsets=np.array([-1.2, 0.0, 1.2]), radius=1.1)


def obstacle(oid, shape, x, y, velocity=(0.0, 0.0)):
    return ObstacleState(id=oid, shape=shape, center=np.array([x, y]), yaw=0.0, velocity=np.array(velocity, float),
                         stamp=0.0)


def planner(params, body=CAR, **changes):
    path = ReferencePath.line([0.0, 0.0], [80.0, 0.0])
    return GuidancePlanner(path, replace(params, **changes), 6.0, 3.0, body.radius, 0.05, kappa_limit=0.2, body=body)


def test_a_parked_car_is_passed_as_close_as_the_clearance_lets_the_body():
    """A box on the road's right edge: the field's path passes 0.8-1.2 m wider than the body needs
    (its repulsive region is a conservative fit of the grown box, plus the reactive band); the tight
    path keeps exactly the clearance from the box with every covering disc, and swings out less."""
    params = default_guidance()
    box = obstacle("parked", Box(4.6, 1.9), 40.0, -0.6)
    wide = planner(params, tight_length=0.0)
    tight = planner(params)
    plans = [p.plan(p.prepare(0.0, [box]), np.zeros(2), 0.0, 6.0, heading=0.0) for p in (wide, tight)]
    peak = [np.max(np.abs(p.xy[:, 1])) for p in plans]
    assert peak[1] < peak[0] - 0.4, peak
    gaps = disc_gaps(plans[1].xy, CAR, [Keepout(box, tight.tight_clearance(box))])
    assert np.min(gaps) > -CLEAR_TOLERANCE
    assert np.min(gaps) < 0.05      # it does touch the clearance: no wider than needed
    assert np.max(plans[1].kappa) <= tight.kappa_max


def test_no_tight_path_exists_within_a_curvature_limit_no_detour_can_keep():
    """With a curvature limit no detour can keep there is no tight path (None: the planner then keeps
    the field's path); with the car's limit there is one."""
    params = default_guidance()
    box = obstacle("parked", Box(4.6, 1.9), 40.0, -0.6)
    p = planner(params)
    prepared = p.prepare(0.0, [box])
    field_plan = planner(params, tight_length=0.0).plan(prepared, np.zeros(2), 0.0, 6.0, heading=0.0)
    times = np.linspace(0.0, 10.0, len(field_plan.xy))
    road = partial(feet_on_polyline, xy=p.path.point_at(np.arange(0.0, 80.0, 0.5)))
    keep = [Keepout(box, 0.4)]
    assert tighten_path(field_plan.xy, times, road, 1e-4, CAR, keep, 6.0, np.array([1.0, 0.0])) is None
    assert tighten_path(field_plan.xy, times, road, 0.2, CAR, keep, 6.0, np.array([1.0, 0.0])) is not None


def test_a_slow_car_is_passed_with_the_clearance_over_the_time_window():
    """A slow car ahead in the lane: the tight path passes it closer than the field's path, and the
    timed tight plan keeps every disc the clearance from the car where it is at each time and
    ``tight_mover_window`` s before and after, or, where the field's own timed path comes closer
    than that, no closer than it (measured on the plans' trajectories, apart from the half-planes)."""
    params = default_guidance()
    slow = obstacle("slow", Box(4.5, 1.9), 25.0, 0.0, velocity=(2.0, 0.0))
    plans, planners = [], []
    for length in (0.0, 6.0):
        p = planner(params, tight_length=length)
        planners.append(p)
        plans.append(p.plan(p.prepare(0.0, []), np.zeros(2), 0.0, 6.0, [slow], heading=0.0))
    wide, tight = (np.max(np.abs(q.xy[:, 1])) for q in plans)
    assert tight < wide - 0.3, (wide, tight)
    w = params.tight_mover_window
    assert w > 0.0
    keep = [Keepout(slow, planners[1].tight_clearance(slow), dt) for dt in (-w, 0.0, w)]

    def least_gap(plan):
        traj = plan.trajectory
        passing = traj.pos[:, 0] < 50.0     # before the plan's end, where it stops (the car catches up there)
        return np.min(disc_gaps(traj.pos[passing], CAR, keep, traj.t[passing]))
    assert least_gap(plans[1]) > min(0.0, least_gap(plans[0])) - CLEAR_TOLERANCE


def test_the_tight_path_is_never_closer_than_a_field_path_that_comes_close():
    """Where the field's path comes closer than the clearance (it starts at a robot that drifted
    close to a post), the tight path comes no closer than it does, and keeps the clearance elsewhere."""
    body = Body(np.zeros(1), 1.0)
    post = obstacle("post", Circle(0.3), 10.0, -1.2)
    keep = [Keepout(post, 0.4)]
    xy = np.column_stack([np.linspace(0.0, 30.0, 121), np.zeros(121)])      # the field's path: on the road
    road = partial(feet_on_polyline, xy=np.array([[0.0, 0.0], [40.0, 0.0]]))
    field_gap = disc_gaps(xy, body, keep)
    assert np.min(field_gap) < -0.4
    out = tighten_path(xy, np.linspace(0.0, 10.0, 121), road, 0.2, body, keep, 6.0, np.array([1.0, 0.0]))
    assert out is not None
    tight_gap = disc_gaps(out[0], body, keep)
    assert np.min(tight_gap) > np.min(field_gap) - CLEAR_TOLERANCE
    far = np.abs(out[0][:, 0] - 10.0) > 4.0
    assert np.all(tight_gap[far] > -CLEAR_TOLERANCE)


def test_the_body_is_yawed_out_of_a_bend_by_the_plants_steady_slip():
    """The dynamic bicycle (the SUV) held on a constant steering angle settles on a circle with its
    body yawed out of it by the slip angle atan(vy / vx) at the CoG: ``Body.axes`` with the car's
    lr and slip gain (``planner_body``) turns the tangent by that angle within 10 % at 3, 5 and
    8 m/s, on left and right bends; without a bend the axes are the tangents."""
    from sim.plants.dynamic_bicycle import DynamicBicycle
    from vflpcd.config.scenarios import load_scenario
    from vflpcd.config.vehicles import BicycleConfig
    from vflpcd.controllers.vflpc import planner_body

    body = planner_body(load_scenario(config_dir() / "scenarios" / "suite" / "roundabout.toml"))
    assert body.rear_axle > 1.0 and body.slip_gain > 0.0
    cfg = BicycleConfig.load("nominal")
    for v in (3.0, 5.0, 8.0):
        for delta in (0.15, -0.15):
            plant = DynamicBicycle(cfg, np.array([0.0, 0.0, 0.0, v, 0.0, 0.0]))
            for _ in range(400):                                  # 20 s: steady
                plant.step(np.array([0.0, delta]), 0.05)
                plant.reset(np.concatenate([plant.state[:3], [v], plant.state[4:]]))   # hold the speed
            _, _, _, vx, vy, omega = plant.state
            slip = np.arctan2(vy, vx)                            # velocity left of the body axis
            kappa = omega / np.hypot(vx, vy)
            a = np.linspace(0.0, 0.5, 21)                        # a circle of that curvature
            r = 1.0 / abs(kappa)
            x = np.column_stack([r * np.sin(a), np.sign(kappa) * r * (1.0 - np.cos(a))])
            axes = body.axes(x, np.full(len(x), kappa), np.full(len(x), v))
            tangents = body.axes(x)
            assert np.array_equal(tangents, unit_differences(x))
            assert np.array_equal(body.axes(x, np.zeros(len(x)), np.full(len(x), v)), tangents)
            turn = np.arctan2(tangents[:, 0] * axes[:, 1] - tangents[:, 1] * axes[:, 0],
                              np.einsum("ij,ij->i", tangents, axes))
            assert np.allclose(turn, -slip, rtol=0.1), (v, delta, turn[10], slip)


def test_on_a_ring_the_tight_path_keeps_the_clearance_with_the_yawed_body():
    """Debris on the outer edge of a 15 m ring at 5 m/s: with the body yawed by its slip the tight
    path keeps the clearance from the debris with the yawed discs, which the body along the tangent
    would not see: its front discs swing out towards the debris."""
    from vflpcd.controllers.vflpc import planner_body
    from vflpcd.config.scenarios import load_scenario

    sc = load_scenario(config_dir() / "scenarios" / "suite" / "roundabout.toml")
    body = planner_body(sc)
    flat = Body(body.offsets, body.radius)
    params = default_guidance()
    debris = obstacle("debris", Circle(0.4), 15.9, 15.0)
    p = GuidancePlanner(sc.path, params, 5.0, 3.0, body.radius, 0.05, kappa_limit=0.17, body=body)
    plan = p.plan(p.prepare(0.0, [debris]), np.array([0.0, 0.0]), 0.0, 5.0, heading=0.0)
    keep = [Keepout(debris, p.tight_clearance(debris))]
    near = np.hypot(plan.xy[:, 0] - 15.9, plan.xy[:, 1] - 15.0) < 6.0
    bend = np.full(len(plan.xy), 1.0 / 15.0)
    speed = np.full(len(plan.xy), 5.0)
    yawed = disc_gaps(plan.xy, body, keep, None, bend, speed)[near]
    along = disc_gaps(plan.xy, flat, keep)[near]
    assert np.min(yawed) > -CLEAR_TOLERANCE - 0.03
    assert np.min(along) > np.min(yawed) + 0.05


def _one_keepout_at_a_time(x, times, body, keepouts, slack, beyond, normals):
    """The discs' distances keepout by keepout, each shape placed where it is ``shift`` s after the
    time each point is reached, through ``Shape.signed_distance`` and ``distance_and_normal`` (the
    reference of the batched evaluation)."""
    axes = body.axes(x)
    discs = (x[None] + body.offsets[:, None, None] * axes[None]).reshape(-1, x.shape[1])
    tiled = np.tile(times, len(body.offsets))
    near, out = [], []
    for k in keepouts:
        o = k.obstacle
        far = float(np.max(np.abs(body.offsets))) + body.radius + k.clearance + beyond + o.shape.bounding_radius()
        near.append(np.linalg.norm(x - (o.center + (times + k.shift - o.stamp)[:, None] * o.velocity), axis=1) <= far)
        pts = discs - (tiled + k.shift - o.stamp)[:, None] * o.velocity
        if normals:
            sd, g = o.shape.distance_and_normal(pts, o.center, o.yaw)
            out.append((sd.reshape(len(body.offsets), -1), g.reshape(len(body.offsets), len(x), -1)))
        else:
            out.append(o.shape.signed_distance(pts, o.center, o.yaw).reshape(len(body.offsets), -1))
    return near, out


def test_the_batched_disc_distances_are_those_of_one_keepout_at_a_time():
    """disc_gaps and body_half_planes evaluate the keepouts of one shape together; their numbers
    are those of the keepouts taken one by one (the most binding disc and keepout the first of
    equals), for circles, boxes and ellipses, static and moving, in time shifts."""
    from vflpcd.core.guidance.tighten import REACH, body_half_planes
    from vflpcd.core.shapes import Ellipse
    rng = np.random.default_rng(11)
    x = np.column_stack([np.linspace(0.0, 40.0, 161), 0.8 * np.sin(np.linspace(0.0, 3.0, 161))])
    times = np.linspace(0.0, 6.0, len(x))
    body = Body(np.array([-1.2, 0.0, 1.2]), 1.0)
    shapes = [Circle(0.3), Circle(0.3), Box(4.5, 1.9), Ellipse(1.2, 0.6), Circle(0.4), Box(4.5, 1.9)]
    keepouts = []
    for i, shape in enumerate(shapes):
        moving = i % 2 == 1
        o = ObstacleState(f"o{i}", shape, np.array([rng.uniform(3.0, 38.0), rng.uniform(-3.0, 3.0)]),
                          float(rng.uniform(-1.0, 1.0)), rng.normal(size=2) if moving else np.zeros(2), 0.5)
        for shift in ((-0.5, 0.0, 0.8) if moving else (0.0,)):
            keepouts.append(Keepout(o, 0.3 + 0.1 * i, shift))
    slack = np.maximum(rng.normal(0.0, 0.1, len(x)), 0.0)

    near, sds = _one_keepout_at_a_time(x, times, body, keepouts, slack, 0.0, normals=False)
    gaps = np.min([np.where(m, sd.min(axis=0) - body.radius - k.clearance, np.inf)
                   for m, sd, k in zip(near, sds, keepouts)], axis=0)
    assert np.isfinite(gaps).sum() > 40 and np.any(gaps < 0.0)
    np.testing.assert_allclose(disc_gaps(x, body, keepouts, times), gaps, rtol=0.0, atol=1e-12)

    near, pairs = _one_keepout_at_a_time(x, times, body, keepouts, slack, REACH, normals=True)
    n_ref, b_ref, need = np.zeros_like(x), np.full(len(x), -np.inf), np.full(len(x), -np.inf)
    for m, (sd, g), k in zip(near, pairs, keepouts):
        want = body.radius + k.clearance - slack - sd
        disc = np.argmax(want, axis=0)
        w = want[disc, np.arange(len(x))]
        take = m & (w > -REACH) & (w > need)
        need[take] = w[take]
        n_ref[take] = g[disc[take], np.flatnonzero(take)]
        b_ref[take] = np.einsum("ij,ij->i", n_ref[take], x[take]) + w[take]
    n, b = body_half_planes(x, times, body, keepouts, slack)
    assert np.isfinite(b_ref).sum() > 40
    np.testing.assert_array_equal(np.isfinite(b), np.isfinite(b_ref))
    np.testing.assert_allclose(n, n_ref, rtol=0.0, atol=1e-12)
    np.testing.assert_allclose(b[np.isfinite(b)], b_ref[np.isfinite(b_ref)], rtol=0.0, atol=1e-12)
    assert disc_gaps(x, body, [], times).tolist() == [np.inf] * len(x)
