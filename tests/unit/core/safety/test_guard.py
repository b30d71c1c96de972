"""The safety guard: supervisor, monitors and the failsafe reasons they give, on a car."""

from dataclasses import replace

import numpy as np

from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.ports import ControllerBase, PlanningController
from vflpcd.core.safety.guard import SafetyGuard
from vflpcd.core.shapes import Box, Circle
from vflpcd.config.safety import guard_for, safety_settings

STATE_NAMES = ("X", "Y", "psi", "vx", "vy", "omega")


def guard(line_scenario, **monitor_overrides) -> SafetyGuard:
    sc = line_scenario("g", length=60.0, speed=7.0)
    sup, mon = safety_settings("ground")
    return guard_for(sc, 0.05, STATE_NAMES, (sup, replace(mon, **monitor_overrides)))


def ob(oid, shape, center, velocity=(0.0, 0.0), stamp=0.0):
    return ObstacleState(oid, shape, np.array(center, float), 0.0, np.array(velocity, float), stamp)


def car(x=0.0, v=0.0):
    return np.array([x, 0.0, 0.0, v, 0.0, 0.0])


def test_touching_a_known_obstacle_is_a_collision_failsafe(line_scenario):
    g = guard(line_scenario)
    step = g.step(0.0, car(), np.zeros(2), [ob("on_top", Circle(1.0), [0.5, 0.0])])
    assert step.trip.startswith("collision: the body overlaps on_top by ")
    assert step.verdict.override and step.command[0] == -6.0


def test_held_at_rest_in_front_of_a_wall_for_blocked_s_gives_up(line_scenario):
    g = guard(line_scenario, blocked_s=1.0)
    wall = [ob("wall", Box(1.0, 10.0), [3.2, 0.0])]                      # 0.56 m from the bumper
    trips = [g.step(k * 0.05, car(), np.array([3.0, 0.0]), wall).trip for k in range(25)]
    assert trips[:20] == [None] * 20
    assert trips[22].startswith("blocked: held at rest by the safety supervisor for 1.") and "(wall in the way)" in trips[22]


def test_the_route_bound_is_the_tracking_limit_of_a_controller_without_a_plan(line_scenario):
    g = guard(line_scenario, tracking_persist=0.0)
    assert g.step(0.0, car(v=5.0), np.zeros(2), [], route_error=7.9).trip is None
    assert g.step(0.05, car(v=5.0), np.zeros(2), [], route_error=8.1).trip.startswith("tracking_error: 8.10 m")


class Planner(ControllerBase):
    """A stand-in controller that follows a plan of its own (a ``PlanningController``): straight along x."""

    name = "planner"

    def __init__(self, kappa=0.0):
        s = np.linspace(0.0, 60.0, 241)

        class P:
            pass

        self.plan = P()
        self.plan.s, self.plan.xy = s, np.column_stack([s, np.zeros_like(s)])
        self.plan.kappa, self.plan.v = np.full_like(s, kappa), np.full_like(s, 5.0)
        self.replans, self.replan_failures, self.plan_gate = 1, 0, None
        self.planning = self

    @property
    def current_plan(self):
        return self.plan

    def reference_at(self, t):
        return np.array([5.0 * t, 0.0])

    def reset(self):
        pass

    def step(self, state, t, obstacles=()):
        return np.zeros(2)


def test_a_planning_controller_gets_the_plan_gate_and_its_undrivable_plan_stops_it(line_scenario):
    g = guard(line_scenario)
    ctl = Planner(kappa=0.5)
    assert isinstance(ctl, PlanningController)
    trips = [g.step(k * 0.05, car(v=5.0), np.zeros(2), [], controller=ctl).trip for k in range(45)]
    assert ctl.plan_gate is not None and ctl.plan_gate(ctl.plan).startswith("undrivable_plan: peak curvature")
    assert trips[40] is None and trips[42].startswith("undrivable_plan: no valid plan for 2.1 s")


def test_the_planning_controllers_tracking_error_is_across_its_path_not_behind_its_timed_reference(line_scenario):
    g = guard(line_scenario, tracking_persist=0.0)
    ctl = Planner()
    # 20 m behind the timed reference (held back) but on the path: fine; 3.5 m beside it: not
    assert g.step(5.0, car(x=5.0, v=5.0), np.zeros(2), [], controller=ctl).trip is None
    off = np.array([10.0, 3.5, 0.0, 5.0, 0.0, 0.0])
    assert g.step(5.05, off, np.zeros(2), [], controller=ctl).trip.startswith("tracking_error: 3.50 m")


def test_a_failsafe_waits_while_stopping_would_leave_the_car_in_a_movers_way(line_scenario):
    # at 7 m/s a full stop leaves the rear of the car where the pedestrian crosses; going on clears it
    g = guard(line_scenario, tracking_persist=0.0, defer_max_s=1.0)
    ped = ob("ped", Circle(0.4), [4.0, -3.5], velocity=(0.0, 1.5))
    first = g.step(0.0, car(v=7.0), np.zeros(2), [ped], route_error=20.0)
    assert first.trip is None and not first.verdict.override
    later = ob("ped", Circle(0.4), [4.0, -3.5], velocity=(0.0, 1.5), stamp=0.0)
    assert g.step(1.05, car(v=7.0), np.zeros(2), [later], route_error=20.0).trip.startswith("tracking_error")
    # without the mover the failsafe comes at once
    g = guard(line_scenario, tracking_persist=0.0)
    assert g.step(0.0, car(v=7.0), np.zeros(2), [], route_error=20.0).trip.startswith("tracking_error")
