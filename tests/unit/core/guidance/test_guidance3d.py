"""3-D guidance for the quadrotor: the two-surface path field, obstacles in detour planes, planning."""

import numpy as np
import pytest

from vflpcd.core.obstacle_world import ObstacleWorld
from vflpcd.config.scenarios import load_scenario
from vflpcd.core.guidance.field3d import GraphPath3D
from vflpcd.core.guidance.grid import BACKWARDS
from vflpcd.core.guidance.integrate_kernel import step_time
from vflpcd.core.guidance.planner import GuidanceLoops
from vflpcd.core.guidance.planner3d import GuidancePlanner3D
from vflpcd.core.guidance.primitives import bump
from vflpcd.core.guidance.speed import menger_curvature
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Box3, Cylinder, Ellipsoid, Sphere

GRAPH = GraphPath3D(np.array([1.0, -1.0, 2.0]), 0.3, np.array([0.0, 5.0, 10.0, 20.0]),
                    np.array([0.0, 1.0, -1.0, 0.5]), np.array([0.0, 0.5, 1.0, 1.0]))


def test_path_surfaces_gradients_match_finite_differences():
    rng = np.random.default_rng(0)
    p = rng.uniform(-5, 25, (40, 3))
    _, _, g1, g2 = GRAPH.value_grad(p)
    h = 1e-6
    for j in range(3):
        dp = np.zeros(3)
        dp[j] = h
        a, b = GRAPH.value_grad(p + dp), GRAPH.value_grad(p - dp)
        assert (a[0] - b[0]) / (2 * h) == pytest.approx(g1[:, j], abs=1e-6)
        assert (a[1] - b[1]) / (2 * h) == pytest.approx(g2[:, j], abs=1e-6)


@pytest.fixture(scope="module")
def uav():
    return load_scenario("uav_3d", stop_at_goal=True)      # the route as drawn, ending at its goal


def test_on_the_path_the_field_is_the_unit_forward_tangent(uav):
    planner = GuidancePlanner3D(uav.path, uav.guidance, 1.0, 2.0, 0.3, 0.02)
    field = planner.prepare(0.0, []).field
    s = np.linspace(2.0, 30.0, 50)
    pts = field.path.origin + np.column_stack([s, field.path.f(s), field.path.g(s)]) @ field.path.R.T
    chi = field.composite(pts)
    tangents = np.array([field.path.tangent(p) for p in pts])
    assert np.linalg.norm(chi, axis=1) == pytest.approx(1.0)
    assert chi == pytest.approx(tangents, abs=1e-9)


def test_inside_a_repulsive_region_the_field_circulates_in_the_detour_plane_and_pushes_out(uav):
    planner = GuidancePlanner3D(uav.path, uav.guidance, 1.0, 2.0, 0.3, 0.02)
    ob = ObstacleState("ball", Sphere(1.0), uav.path.point_at(15.0), 0.0, np.zeros(3), 0.0)
    field = planner.prepare(0.0, [ob]).field
    o = field.statics[0]
    rng = np.random.default_rng(1)
    d = rng.normal(size=(300, 3))
    pts = o.implicit.center + 1.5 * d / np.linalg.norm(d, axis=1, keepdims=True)
    assert np.all(o.implicit.value(pts) < o.implicit.c)
    _, chi_r = field.repulsive_unit(o, o.gamma, pts)
    assert field.composite(pts) == pytest.approx(chi_r, abs=1e-12)
    _, g = o.implicit.value_grad(pts)
    assert np.all(np.einsum("ij,ij->i", chi_r, g) > 0)                       # outwards
    side_pt = o.implicit.center + o.side * 0.999 * o.implicit.axes[0]  # on R: pure circulation
    _, chi_side = field.repulsive_unit(o, o.gamma, side_pt[None, :])
    tangent = uav.path.project(o.implicit.center).tangent
    assert chi_side[0] @ tangent > 0.9                                        # along the path on the passing side


def random_field_3d(rng, params):
    path = ReferencePath.line([0.0, 0.0, 2.0], [40.0, 0.0, 3.0])
    planner = GuidancePlanner3D(path, params, rng.uniform(0.8, 3.0), 2.0, 0.3, 0.02)
    obstacles, x = [], rng.uniform(10.0, 13.0)
    for k in range(rng.integers(1, 4)):
        kind = rng.integers(4)
        shape = (Sphere(rng.uniform(0.3, 1.2)) if kind == 0 else
                 Ellipsoid(rng.uniform(0.4, 1.5), rng.uniform(0.4, 1.0), rng.uniform(0.4, 1.0)) if kind == 1 else
                 Cylinder(rng.uniform(0.2, 0.8), rng.uniform(2.0, 8.0)) if kind == 2 else
                 Box3(rng.uniform(0.5, 2.0), rng.uniform(0.5, 2.0), rng.uniform(0.5, 3.0)))
        o = ObstacleState(f"o{k}", shape, np.zeros(3), rng.uniform(-np.pi, np.pi), np.zeros(3), 0.0)
        reach = planner.implicit(o).reach
        x = x + (reach if k else 0.0)
        if x + reach + 4.0 > 40.0:
            break
        center = path.point_at(x) + [0.0, rng.uniform(-0.8, 0.8), rng.uniform(-0.5, 0.5)]
        obstacles.append(ObstacleState(o.id, shape, center, o.yaw, np.zeros(3), 0.0))
        x += reach + 2.0
    return planner, path, obstacles


def test_random_3d_fields_reach_the_goal_safely_within_the_lateral_acceleration_limit(uav):
    for seed in range(40):
        rng = np.random.default_rng(seed)
        planner, path, obstacles = random_field_3d(rng, uav.guidance)
        prepared = planner.prepare(0.0, obstacles)
        plan = planner.plan(prepared, path.point_at(0.0), 0.0, planner.v_desired)
        assert plan.reached and np.linalg.norm(plan.xy[-1] - path.point_at(path.length)) < 0.5, f"seed {seed}"
        for ob in prepared.field.statics:
            assert np.min(ob.implicit.value(plan.raw)) > ob.implicit.c, f"seed {seed}: enters Q of {ob.implicit.name}"
        assert np.max(plan.v ** 2 * menger_curvature(plan.xy)) <= 1.01 * planner.a_lat_max, f"seed {seed}"


def test_uav_3d_scenario_plan_keeps_clear_of_every_obstacle(uav):
    planner = GuidancePlanner3D(uav.path, uav.guidance, uav.v_desired, uav.a_lat_max, uav.footprint.radius,
                                uav.control_period)
    world = ObstacleWorld(uav.obstacles)
    world.t_trigger = [0.0] * len(uav.obstacles)  # every obstacle known from the start
    obstacles = world.snapshot(0.0)
    prepared = planner.prepare(0.0, [o for o in obstacles if not o.moving])
    plan = planner.plan(prepared, uav.start[:3], 0.0, 0.0, [o for o in obstacles if o.moving])
    assert plan.reached
    traj = plan.trajectory
    for o in obstacles:
        centers = o.center[None, :] + o.velocity[None, :] * (traj.t - o.stamp)[:, None]
        gaps = [o.shape.signed_distance(p[None, :], c, o.yaw)[0] for p, c in zip(traj.pos, centers)]
        assert min(gaps) - uav.footprint.radius > 0.3, o.id


def _reference_steps(field, obstacles, start, x_end, beta, epsilon, max_steps, t0, speed, times):
    """Eq. (xi_r) in 3-D step by step on the vectorised field (path_unit, repulsive_unit, bump),
    with the integration's rules: the reach test, gamma_i decided at first entry against the
    path's tangent, the near-zero rule."""
    gammas, x, pts, prev = [None] * len(obstacles), np.asarray(start, float), [np.asarray(start, float)], None
    for k in range(max_steps):
        t = step_time(k, t0, beta, speed, times)
        P, V = 1.0, np.zeros(3)
        for n, ob in enumerate(obstacles):
            o = ob.implicit
            if np.sum((x - (o.center + o.velocity * (t - o.stamp))) ** 2) > o.reach ** 2:
                continue
            if gammas[n] is None:
                phi0, chi0 = field.repulsive_unit(ob, ob.gamma, x[None], t)
                if phi0[0] >= 0.0:
                    continue
                gammas[n] = -ob.gamma if chi0[0] @ field.path.tangent(x) < BACKWARDS else ob.gamma
            phi, chi = field.repulsive_unit(ob, gammas[n], x[None], t)
            cup = bump(phi, o.c, field.l1, field.l2)[0][0]
            P, V = P * cup, V + (1.0 - cup) * chi[0]
        c = P * field.path_unit(x[None])[0] + V
        if np.linalg.norm(c) < epsilon:
            u = prev
        else:
            u = prev = c / np.linalg.norm(c)
        x = x + beta * u
        pts.append(x)
        if (x - field.path.origin) @ field.path.R[:, 0] >= x_end:
            return np.array(pts), gammas
    return np.array(pts), gammas


def test_the_3d_steps_are_the_vectorised_field_stepped(uav):
    """The 3-D steps of eq. (xi_r) (``integrate3d_kernel``), compiled and run as Python, give the
    same points as the vectorised field stepped point by point, past a static box, a moving
    cylinder and a moving ellipsoid (each gamma_i decided at first entry), with and without step
    times, and the gammas decided."""
    from vflpcd.controllers.loops import integrate3d_loop
    from vflpcd.core.guidance.integrate3d_kernel import steps3d_loop

    planner = GuidancePlanner3D(uav.path, uav.guidance, 1.0, 2.0, 0.3, 0.02)
    shapes = (Box3(1.0, 2.0, 1.5), Cylinder(0.8, 2.0), Ellipsoid(1.0, 0.6, 0.8))
    obstacles = [ObstacleState(f"o{k}", sh, uav.path.point_at(8.0 + 7.0 * k) + np.array([0.3, -0.2, 0.1]), 0.4 * k,
                               np.array([0.3, -0.2, 0.1]) * (k > 0), 0.5) for k, sh in enumerate(shapes)]
    prepared = planner.prepare(0.0, obstacles[:1])
    field = prepared.field
    field.movers = [planner.obstacle(planner.implicit(o), 0.0) for o in obstacles[1:]]
    terms = field.statics + field.movers
    start = uav.path.point_at(0.0) + np.array([0.0, 0.4, -0.2])
    compiled = integrate3d_loop()
    assert compiled is not None
    entered = 0
    for times in (None, 0.2 + 0.1 * np.arange(150)):
        ref, gammas = _reference_steps(field, terms, start, prepared.x_end, planner.params.beta,
                                       planner.params.epsilon, 400, 0.2, 1.0, times)
        out = {}
        for name, loop in (("compiled", compiled), ("python", steps3d_loop)):
            planner._loops = lambda loop=loop: GuidanceLoops(steps3d=loop)
            out[name] = planner._integrate(field, start, prepared.x_end, 0.2, 1.0, 400, times)
        np.testing.assert_array_equal(out["compiled"][0], out["python"][0])
        xyz, reached, _, decided = out["compiled"]
        assert reached and decided == out["python"][3] == tuple(gammas)
        np.testing.assert_allclose(xyz, ref, rtol=0.0, atol=1e-9)
        entered += sum(g is not None for g in decided)
    assert entered >= 4
