"""The supervisor's clearance tests compiled (``clearance_kernel``) give the numbers, obstacles and
decisions of its numpy paths, for the car and the quadrotor, static and moving, round and box
shapes, ahead of and behind the body; a shape without a closed form keeps the numpy path."""

import numpy as np
import pytest

from vflpcd.config.vehicles import BicycleConfig
from vflpcd.controllers.loops import supervisor_loops
from vflpcd.core.footprint import Footprint
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.safety.arc_kernel import arcs_loop
from vflpcd.core.safety.clearance_kernel import clearances_loop, within_reach_loop
from vflpcd.core.safety.obstacle_arrays import ObstacleArrays
from vflpcd.core.safety.supervisor import (AerialSupervisor, CarLimits, GroundSupervisor, QuadLimits,
                                           SupervisorConfig, SupervisorLoops)
from vflpcd.core.shapes import Box, Box3, Circle, Ellipse, Sphere

COMPILED = supervisor_loops()
LOOPS = [pytest.param(SupervisorLoops(clearances_loop, within_reach_loop, arcs_loop), id="python")] + (
    [pytest.param(COMPILED, id="compiled")] if COMPILED is not None else [])


def car_supervisor(loops):
    cfg = BicycleConfig.load("nominal")
    lim = cfg.limits
    limits = CarLimits(cfg.params.wheelbase, lim.a_min, lim.a_max, lim.delta_max, lim.delta_rate_max)
    body = Footprint.rectangle(cfg.body.length, cfg.body.width, cfg.body.rear_overhang + cfg.params.lr)
    return GroundSupervisor(SupervisorConfig(), body, limits, 0.05, loops=loops)


def quad_supervisor(loops):
    return AerialSupervisor(SupervisorConfig(), 0.4, QuadLimits(8.0), 0.05, ("X", "Y", "Z", "vx", "vy", "vz"),
                            loops=loops)


def supervisors(loops, d: int):
    """The car's (d = 2) or the quadrotor's supervisor on its numpy paths, and with ``loops``."""
    make = car_supervisor if d == 2 else quad_supervisor
    return make(None), make(loops)


def scene(rng, d: int, n: int) -> list[ObstacleState]:
    """n obstacles within 8 m (a quadrotor's 4 m) of the origin, half of them moving, round and box shapes."""
    out = []
    for i in range(n):
        if d == 2:
            shape = Circle(rng.uniform(0.2, 1.5)) if i % 2 else Box(rng.uniform(0.3, 4.0), rng.uniform(0.3, 2.0))
        else:
            shape = Sphere(rng.uniform(0.2, 1.5)) if i % 2 else Box3(*rng.uniform(0.3, 3.0, 3))
        velocity = rng.normal(0.0, 2.0, d) if i % 4 < 2 else np.zeros(d)
        out.append(ObstacleState(f"o{i}", shape, rng.uniform(-8.0, 8.0, d) / (d - 1), rng.uniform(-np.pi, np.pi),
                                 velocity, rng.uniform(-0.5, 0.5)))
    return out


def poses(rng, d: int, K: int):
    """A wandering path of K poses from near the origin, its yaws and times."""
    step = rng.normal(0.0, 0.3, (K, d))
    step[:, 0] += 0.25
    pos = np.cumsum(step, axis=0) + rng.uniform(-2.0, 2.0, d)
    yaw = np.cumsum(rng.normal(0.0, 0.1, K)) if d == 2 else np.zeros(K)
    return pos, yaw, np.linspace(0.0, rng.uniform(0.5, 4.0), K)


@pytest.mark.parametrize("loops", LOOPS)
@pytest.mark.parametrize("d", [2, 3])
def test_the_compiled_clearances_are_the_numpy_ones(loops, d):
    rng = np.random.default_rng(7 + d)
    plain, fast = supervisors(loops, d)
    checked = np.zeros(2, int)              # finite static and mover clearances compared
    for trial in range(120):
        obstacles = scene(rng, d, int(rng.integers(1, 7)))
        arrays = ObstacleArrays.of(obstacles, d)
        pos, yaw, times = poses(rng, d, int(rng.integers(2, 41)))
        for movers_only in (False, True):
            for behind in (False, True):
                want = plain._clearances(pos, yaw, times, arrays, movers_only, behind)
                got = fast._clearances(pos, yaw, times, arrays, movers_only, behind)
                for kind, ((w, who_w), (g, who_g)) in enumerate(zip(want, got)):
                    assert who_g == who_w
                    assert g == pytest.approx(w, abs=1e-12) or (np.isinf(w) and np.isinf(g))
                    checked[kind] += np.isfinite(w)
    assert (checked > 50).all(), checked    # statics and movers within reach in many trials


@pytest.mark.parametrize("loops", LOOPS)
@pytest.mark.parametrize("d", [2, 3])
def test_the_compiled_pre_filter_keeps_the_obstacles_that_the_numpy_one_keeps(loops, d):
    rng = np.random.default_rng(3 + d)
    plain, fast = supervisors(loops, d)
    kept = dropped = 0
    for trial in range(300):
        obstacles = scene(rng, d, int(rng.integers(1, 9)))
        obstacles[0] = ObstacleState("wall", Ellipse(3.0, 0.5) if d == 2 else Box3(0.5, 6.0, 3.0),
                                     obstacles[0].center, 0.4, obstacles[0].velocity, obstacles[0].stamp)
        arrays = ObstacleArrays.of(obstacles, d)
        state = np.zeros(6)
        state[:d] = rng.uniform(-6.0, 6.0, d)
        if d == 2:
            state[2], state[3], state[4] = rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 12.0), rng.normal(0.0, 0.3)
            u = np.array([rng.uniform(-6.0, 3.0), rng.uniform(-0.5, 0.5)])
        else:
            state[3:] = rng.normal(0.0, 3.0, 3)
            u = rng.uniform(-8.0, 8.0, 3)
        t = rng.uniform(0.0, 2.0)
        want = plain._within_reach(state, u, arrays, t)
        got = fast._within_reach(state, u, arrays, t)
        assert got.dtype == bool and np.array_equal(got, want)
        kept += want.sum()
        dropped += (~want).sum()
    assert kept > 100 and dropped > 100         # both decisions are compared


def test_a_shape_without_a_closed_form_keeps_the_numpy_path():
    """An ellipse's distance is its own method's: the compiled test is not asked, and the result is
    the numpy path's."""
    def refuse(*args):
        raise AssertionError("the compiled clearance test was asked about an ellipse")

    refusing = SupervisorLoops(clearances=refuse, within_reach=within_reach_loop, arcs=arcs_loop)

    wedge = ObstacleState("wedge", Ellipse(2.0, 1.0), np.array([4.0, 0.5]), 0.3, np.zeros(2), 0.0)
    post = ObstacleState("post", Circle(0.3), np.array([9.0, 3.0]), 0.0, np.zeros(2), 0.0)
    arrays = ObstacleArrays.of([post, wedge], 2)
    assert not arrays.closed
    pos = np.column_stack([np.linspace(0.0, 6.0, 25), np.zeros(25)])
    yaw, times = np.zeros(25), np.linspace(0.0, 2.0, 25)
    want = car_supervisor(None)._clearances(pos, yaw, times, arrays)
    assert car_supervisor(refusing)._clearances(pos, yaw, times, arrays) == want
    assert want[0][1] == "wedge" and want[0][0] < 0.0


@pytest.mark.parametrize("loops", LOOPS)
def test_the_compiled_manoeuvre_is_the_numpy_one(loops):
    """The car's predicted poses, yaws and times along "u for the reaction time, then the stop" (and
    "u held", the stop that straightens, the steering moving on through it), from rest to 20 m/s,
    straight and turning, braking and accelerating."""
    rng = np.random.default_rng(11)
    plain, fast = car_supervisor(None), car_supervisor(loops)
    shapes = set()
    for trial in range(300):
        state = np.array([*rng.uniform(-5.0, 5.0, 2), rng.uniform(-np.pi, np.pi), rng.uniform(0.0, 20.0),
                          rng.normal(0.0, 0.5), rng.normal(0.0, 0.3)])
        if trial % 5 == 0:
            state[3] = rng.uniform(0.0, 0.3)           # nearly at rest: the two-pose branch
        u = np.array([rng.uniform(-8.0, 3.0), rng.uniform(-0.6, 0.6) if trial % 3 else 0.0])
        delta = float(rng.uniform(-0.3, 0.3)) if trial % 3 else 0.0
        for kwargs in ({"brake": True}, {"brake": False}, {"brake": True, "ramp": True},
                       {"brake": True, "settle": 0.0}, {"brake": False, "hold": 2.0}):
            plain.delta = fast.delta = delta
            want, got = plain._poses(state, u, **kwargs), fast._poses(state, u, **kwargs)
            for w, g in zip(want, got):
                assert g.shape == w.shape
                np.testing.assert_allclose(g, w, rtol=0.0, atol=1e-12)
            shapes.add(len(want[0]))
    assert {2, SupervisorConfig().samples} <= shapes      # both branches, the longest stops
