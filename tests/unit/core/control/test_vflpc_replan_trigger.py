"""The VF-LPC replan trigger under a changing obstacle picture: one replan asked per change (not
one per tick while the worker plans it), the newest picture when it changes faster than the
worker plans, and a failed replan asked again."""

import dataclasses

import numpy as np
import pytest

from vflpcd.controllers.vflpc import make_vflpc
from sim.plants import make_plant
from vflpcd.config.scenarios import load_scenario
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Circle
from vflpcd.core.vflpc import plan_job

DT = 0.05


@pytest.fixture(scope="module")
def straight():
    sc = load_scenario("carsim_avoidance")
    return dataclasses.replace(sc, obstacles=())


@pytest.fixture
def ctrl(straight):
    ctrl = make_vflpc(straight)
    ctrl.state0 = make_plant(straight, 0).state
    ctrl.step(ctrl.state0, 0.0)                         # the first plan, made at once
    assert ctrl.status().replans == 1 and ctrl.take_replan() is None
    return ctrl


def walker(vx: float) -> ObstacleState:
    """A walker 30 m ahead beside the road, walking along it at vx."""
    return ObstacleState("walker", Circle(0.4), np.array([30.0, 8.0]), 0.0, np.array([vx, 0.0]), 0.0)


def test_one_replan_per_change_while_the_worker_plans(ctrl):
    jitter = ctrl.params.velocity_change / 4
    ctrl.step(ctrl.state0, DT, [walker(1.0)])            # the walker appears
    job = ctrl.take_replan()
    assert job is not None and [o.id for o in job.obstacles] == ["walker"]
    for k in range(2, 12):                              # the same picture, jitter below the threshold
        ctrl.step(ctrl.state0, k * DT, [walker(1.0 + jitter * (-1) ** k)])
        assert ctrl.take_replan() is None, k            # being planned already: not asked again
    ctrl.install_plan(job, plan_job(ctrl.planner, job))
    ctrl.step(ctrl.state0, 12 * DT, [walker(1.0 - jitter)])
    assert ctrl.status().replans == 2 and ctrl.take_replan() is None


def test_the_newest_picture_is_planned_next(ctrl):
    ctrl.step(ctrl.state0, DT, [walker(1.0)])
    job = ctrl.take_replan()                            # being planned ...
    for k, vx in enumerate((2.0, 3.0, 4.0), start=2):   # ... while the walker speeds up
        ctrl.step(ctrl.state0, k * DT, [walker(vx)])
    ctrl.install_plan(job, plan_job(ctrl.planner, job))
    newest = ctrl.take_replan()
    assert newest is not None and newest.t == pytest.approx(4 * DT)
    np.testing.assert_allclose(newest.obstacles[0].velocity, [4.0, 0.0])
    assert ctrl.take_replan() is None                   # handed out once
    ctrl.step(ctrl.state0, 5 * DT, [walker(4.0)])
    assert ctrl.take_replan() is None                   # that picture is being planned


def test_a_failed_replan_is_asked_again(ctrl):
    ctrl.step(ctrl.state0, DT, [walker(1.0)])
    job = ctrl.take_replan()
    ctrl.replan_failed(job, "no plan from here")
    ctrl.step(ctrl.state0, 2 * DT, [walker(1.0)])       # the same picture, still without a plan for it
    again = ctrl.take_replan()
    assert again is not None and again.t == pytest.approx(2 * DT)
    ctrl.install_plan(again, plan_job(ctrl.planner, again))
    ctrl.step(ctrl.state0, 3 * DT, [walker(1.0)])
    assert ctrl.take_replan() is None and ctrl.replan_failures == 1


def test_an_obstacle_that_goes_asks_a_replan(ctrl):
    ctrl.step(ctrl.state0, DT, [walker(1.0)])
    job = ctrl.take_replan()
    ctrl.install_plan(job, plan_job(ctrl.planner, job))
    ctrl.step(ctrl.state0, 2 * DT, [])
    gone = ctrl.take_replan()
    assert gone is not None and gone.obstacles == ()


def test_a_plan_with_a_stretch_beyond_the_limits_is_planned_again_until_one_keeps_them(ctrl):
    """The safety gate admits a plan whose look-ahead is drivable; one that breaks the steering
    limit further on is planned again every UNDRIVABLE_RETRY s (nothing else would ask before the
    car reaches that stretch), and a drivable replan ends the retries."""
    from vflpcd.core.vflpc import UNDRIVABLE_RETRY, PlanResult

    job = ctrl._fresh_job(0.0)                              # from the state of the fixture's first tick
    good = plan_job(ctrl.planner, job)
    kappa = good.plan.kappa.copy()
    kappa[-5:] = 3.0 * ctrl.planner.kappa_limit                # far beyond the gate's look-ahead
    ctrl.install_plan(job, PlanResult(dataclasses.replace(good.plan, kappa=kappa), good.ends_path))
    steps = int(round(UNDRIVABLE_RETRY / DT))
    for k in range(1, steps):
        ctrl.step(ctrl.state0, k * DT)
        assert ctrl.take_replan() is None, k
    ctrl.step(ctrl.state0, steps * DT)
    retry = ctrl.take_replan()
    assert retry is not None and retry.t == pytest.approx(steps * DT)
    ctrl.install_plan(retry, plan_job(ctrl.planner, retry))
    for k in range(steps + 1, 3 * steps):
        ctrl.step(ctrl.state0, k * DT)
        assert ctrl.take_replan() is None, k


def test_the_replan_check_comes_after_the_command(ctrl):
    """The step that sees the walker appear commands without checking for a replan; its settle
    (or a replan taken before it) asks for the one replan."""
    ctrl.step(ctrl.state0, DT, [walker(1.0)])
    assert ctrl._pending is None and ctrl._unguided is not None       # not checked before the command
    ctrl.settle()
    job = ctrl.take_replan()
    assert job is not None and job.t == pytest.approx(DT) and ctrl.take_replan() is None
    ctrl.step(ctrl.state0, 2 * DT, [walker(3.0)])                     # the walker speeds up
    newer = ctrl.take_replan()                                         # taken before the settle
    assert newer is not None and newer.t == pytest.approx(2 * DT)
    ctrl.settle()
    assert ctrl.take_replan() is None                                  # checked once
