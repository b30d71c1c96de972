"""Late replans: a replan installed after the robot stopped (or was braked) is re-timed from the
robot's point and speed instead of chasing a reference far ahead of it."""

from __future__ import annotations

import numpy as np
import pytest

from vflpcd.config.scenarios import default_guidance
from vflpcd.core.guidance.planner import GuidancePlanner
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Circle


@pytest.fixture(scope="module")
def planner():
    return GuidancePlanner(ReferencePath.line([0.0, 0.0], [120.0, 0.0]), default_guidance(), 6.0, 3.0, body_radius=1.0,
                           control_period=0.05)


def plan_from(planner, pos, t0, v0, movers=()):
    prepared = planner.prepare(float(pos[0]), [])
    return planner.plan(prepared, np.asarray(pos, float), t0, v0, list(movers), heading=0.0)


def test_a_plan_installed_ten_seconds_late_continues_from_the_stopped_reference(planner):
    # planned at t = 0 from x = 10 at 6 m/s; meanwhile the robot stopped at x = 20 (its old plan ended)
    late = plan_from(planner, [10.0, 0.0], 0.0, 6.0)
    t_now = 10.0
    assert late.trajectory.sample(np.array([t_now]))["pos"][0, 0] > 60.0      # as planned: 40 m ahead
    spliced = planner.splice(late, np.array([20.0, 0.0]), 0.0, t_now)
    now = spliced.trajectory.sample(np.array([t_now, t_now + 1.0]))
    step = planner.params.beta                                                # at most one path step ahead
    assert now["pos"][0] == pytest.approx([20.0, 0.0], abs=step + 1e-6) and now["v"][0] == pytest.approx(0.0, abs=1e-9)
    # it starts off at the speed plan's acceleration limit, not at the planned 6 m/s
    a = planner.params.a_accel
    assert now["pos"][1, 0] - 20.0 == pytest.approx(0.5 * a * 1.0 ** 2, rel=0.15)
    assert spliced.xy[-1] == pytest.approx(late.xy[-1])                       # the same path ahead


def test_a_splice_continues_a_moving_reference_at_its_speed(planner):
    plan = plan_from(planner, [0.0, 0.0], 0.0, 6.0)
    spliced = planner.splice(plan, np.array([30.3, 0.0]), 5.2, 7.0)
    now = spliced.trajectory.sample(np.array([7.0]))
    assert now["pos"][0] == pytest.approx([30.3, 0.0], abs=planner.params.beta + 1e-6)
    assert now["v"][0] == pytest.approx(5.2, abs=0.05)
    n = len(spliced.kappa)                                                    # the plan's own points:
    assert spliced.kappa[2:] == pytest.approx(plan.kappa[-n:][2:], abs=1e-9)  # its curvature (ends aside)


def test_a_splice_that_would_meet_a_moving_obstacle_is_refused(planner):
    # a walker crossing at x = 40 is passed as planned; re-timed 4 s later the car would meet it
    walker = ObstacleState(id="walker", shape=Circle(0.4), center=np.array([40.0, -12.0]), yaw=0.0,
                           velocity=np.array([0.0, 1.5]), stamp=0.0)
    plan = plan_from(planner, [10.0, 0.0], 0.0, 6.0, [walker])
    assert planner.splice(plan, np.array([10.0, 0.0]), 6.0, 0.0) is not None   # on time: it joins
    late = [planner.splice(plan, np.array([10.0, 0.0]), 6.0, dt) for dt in np.arange(0.5, 8.0, 0.5)]
    assert any(p is None for p in late)


def test_after_its_end_a_reference_stands_still():
    from vflpcd.core.guidance.trajectory import timed_trajectory

    xy = np.column_stack([np.linspace(0, 10, 41), np.zeros(41)])
    s = np.linspace(0, 10, 41)
    traj = timed_trajectory(xy, s, np.full(41, 5.0), 0.0, 0.05)
    after = traj.sample(np.array([traj.t[-1] + 1.0]))
    assert after["pos"][0] == pytest.approx([10.0, 0.0]) and after["v"][0] == 0.0 and after["omega"][0] == 0.0
    assert traj.sample(np.array([1.0]))["v"][0] == pytest.approx(5.0)


def test_vflpc_installs_a_late_replan_where_the_robot_stands(tmp_path):
    """The robot stops at the end of its plan while a replan made 8 s earlier is still out; once
    installed, the reference goes on from where the robot waits, not 8 s down the new plan."""
    from line_road import vflpc_on_a_line
    from vflpcd.core.vflpc import plan_job

    sc, ctl, plant = vflpc_on_a_line(tmp_path, 150.0, 6.0)
    dt, job, k = sc.control_period, None, 0
    while job is None:                                  # drive until a replan is due
        ctl.step(plant.state, k * dt)
        plant.step(ctl._u_prev, dt)
        job = ctl.take_replan()
        k += 1
    t_job = k * dt
    end = ctl.current_plan.trajectory.t[-1]
    while k * dt < max(end, t_job) + 8.0:              # the old plan runs out, the robot stops at its end
        plant.step(ctl.step(plant.state, k * dt), dt)
        k += 1
    t = (k - 1) * dt
    robot = plant.state[:2]
    late = plan_job(ctl.planner, job)
    assert np.linalg.norm(late.plan.trajectory.sample(np.array([t]))["pos"][0] - robot) > 20.0
    ctl.install_plan(job, late)
    assert ctl.replans == 2 and ctl.replan_failures == 0
    assert np.linalg.norm(ctl.reference_at(t) - robot) < 0.2                  # one path step and the offset
    assert np.linalg.norm(ctl.reference_at(t + 1.0) - robot) < 0.6 * ctl.planner.params.a_accel + 0.2


def test_vflpc_refuses_a_replan_planned_from_where_the_robot_no_longer_is(tmp_path):
    """A replan made from a point 3 m beside where the robot now drives (it was seconds old) is
    stale: set aside (no planning failure), the old plan stays, and a new one is asked from the
    present state."""
    from line_road import vflpc_on_a_line
    from vflpcd.core.vflpc import ReplanJob, plan_job

    sc, ctl, plant = vflpc_on_a_line(tmp_path, 150.0, 6.0)
    dt = sc.control_period
    for k in range(40):
        x = plant.state.copy()                          # the state the controller saw last
        plant.step(ctl.step(x, k * dt), dt)
    old_plan, t = ctl.current_plan, 39 * dt
    aside = ReplanJob(float(x[0]), np.array([x[0], 3.0]), np.array([6.0, 0.0]), 0.0, t, ())
    ctl.install_plan(aside, plan_job(ctl.planner, aside))
    assert ctl.current_plan is old_plan and ctl.status().stale_replans == 1 and ctl.replan_failures == 0
    fresh = ctl.take_replan()
    assert fresh is not None and abs(fresh.pos[1] - x[1]) < 1e-9 and fresh.t == t
    ctl.install_plan(fresh, plan_job(ctl.planner, fresh))
    assert ctl.current_plan is not old_plan and ctl.status().stale_replans == 1
