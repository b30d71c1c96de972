"""The plan, tracking and response monitors, and the guard that combines them with the supervisor."""

from dataclasses import dataclass

import numpy as np
import pytest

from vflpcd.core.path import nearest_on_polyline
from vflpcd.core.safety.monitors import (MonitorConfig, PlanLimits, PlanWatch, ResponseWatch, TrackingWatch,
                                         check_plan)

LIMITS = PlanLimits(kappa_max=0.174, a_lat_max=3.0)
CFG = MonitorConfig()


@dataclass
class Plan:
    xy: np.ndarray
    s: np.ndarray
    kappa: np.ndarray
    v: np.ndarray


def straight(length=60.0, kappa=0.0, v=5.0, bad_at=None, bad_kappa=0.5):
    s = np.linspace(0.0, length, int(length / 0.25) + 1)
    k = np.full_like(s, kappa)
    if bad_at is not None:
        k[(s > bad_at) & (s < bad_at + 1.0)] = bad_kappa
    return Plan(np.column_stack([s, np.zeros_like(s)]), s, k, np.full_like(s, v))


def test_check_plan_names_the_limit_that_is_exceeded():
    assert check_plan(np.full(5, 0.17), np.full(5, 4.0), LIMITS, 0.05) is None
    assert "steering limit" in check_plan(np.array([0.0, 0.19, 0.0]), np.full(3, 1.0), LIMITS, 0.05)
    assert check_plan(np.array([0.0, 0.18, 0.0]), np.full(3, 1.0), LIMITS, 0.05) is None    # inside 5 %
    assert "lateral acceleration" in check_plan(np.full(3, 0.1), np.full(3, 6.0), LIMITS, 0.05)
    assert "non-finite" in check_plan(np.array([0.0, np.nan]), np.ones(2), LIMITS, 0.05)


def test_an_undrivable_stretch_ahead_stops_the_mission_after_the_timeout_only():
    w = PlanWatch(CFG, LIMITS)
    plan = straight(bad_at=10.0)
    for t in np.arange(0.0, CFG.plan_timeout + 0.01, 0.05):
        reason, distance = w.update(t, plan, 1, 0, np.array([0.0, 0.4]))
        assert reason is None and distance == pytest.approx(0.4)
    reason, _ = w.update(CFG.plan_timeout + 0.1, plan, 1, 0, np.array([0.0, 0.4]))
    assert reason.startswith("undrivable_plan:") and "steering limit" in reason


def test_an_undrivable_stretch_beyond_the_lookahead_or_behind_the_body_is_not_a_fault():
    w = PlanWatch(CFG, LIMITS)
    far = straight(length=100.0, bad_at=CFG.plan_lookahead_m + 5.0)
    behind = straight(length=60.0, bad_at=2.0)
    for t in np.arange(0.0, 3 * CFG.plan_timeout, 0.05):
        assert w.update(t, far, 1, 0, np.array([0.0, 0.0]))[0] is None
    for t in np.arange(3 * CFG.plan_timeout, 6 * CFG.plan_timeout, 0.05):
        assert w.update(t, behind, 2, 0, np.array([10.0, 0.0]))[0] is None


def test_a_drivable_replan_in_time_clears_the_fault_and_admit_refuses_undrivable_replans():
    w = PlanWatch(CFG, LIMITS)
    w.update(0.0, straight(bad_at=5.0), 1, 0, np.zeros(2))
    assert w.update(CFG.plan_timeout * 0.9, straight(), 2, 0, np.zeros(2))[0] is None
    assert w.update(CFG.plan_timeout * 2, straight(), 2, 0, np.zeros(2))[0] is None
    assert "steering limit" in w.admit(straight(bad_at=5.0))
    assert w.admit(straight()) is None
    assert w.admit(straight(length=100.0, bad_at=CFG.plan_lookahead_m + 5.0)) is None


def test_failing_replans_without_a_new_plan_end_in_no_plan():
    w = PlanWatch(CFG, LIMITS)
    plan = straight()
    assert w.update(0.0, plan, 1, 0, np.zeros(2))[0] is None
    t, failures = 0.0, 0
    while t <= CFG.plan_timeout:
        t, failures = t + 0.05, failures + 1
        assert w.update(t, plan, 1, failures, np.zeros(2))[0] is None
    reason, _ = w.update(t + 0.1, plan, 1, failures + 1, np.zeros(2))
    assert reason.startswith("no_plan:") and f"{failures + 1} failed replans" in reason
    # a success resets it
    assert w.update(t + 0.2, plan, 2, failures + 1, np.zeros(2))[0] is None


def test_no_plan_at_all_ends_in_no_plan():
    w = PlanWatch(CFG, LIMITS)
    assert w.update(0.0, None, 0, 0, np.zeros(2))[0] is None
    assert w.update(CFG.plan_timeout + 0.1, None, 0, 0, np.zeros(2))[0].startswith("no_plan: ")


def test_tracking_error_needs_to_persist():
    w = TrackingWatch(CFG)
    assert w.update(0.0, 5.0, 3.0) is None
    assert w.update(CFG.tracking_persist - 0.1, 5.0, 3.0) is None
    assert w.update(CFG.tracking_persist - 0.05, 1.0, 3.0) is None            # back on track: starts again
    assert w.update(CFG.tracking_persist + 0.1, 5.0, 3.0) is None
    assert w.update(2 * CFG.tracking_persist + 0.2, 5.0, 3.0).startswith("tracking_error: 5.00 m")
    assert w.update(10.0, np.nan, 3.0) is None


def drive(watch, accel_cmd, accel_real, yaw_cmd=0.0, yaw_real=0.0, v0=5.0, seconds=2.0, dt=0.05):
    v, reason = v0, None
    for k in range(int(seconds / dt)):
        reason = reason or watch.update(k * dt, v, np.array([v]), np.array([accel_cmd]), yaw_real, yaw_cmd)
        v += accel_real * dt
    return reason


def test_a_vehicle_that_follows_its_commands_is_responsive_also_when_it_understeers():
    assert drive(ResponseWatch(CFG, 0.05), 1.0, 1.0, 0.2, 0.25) is None
    assert drive(ResponseWatch(CFG, 0.05), 1.0, 1.0, 0.5, 0.3) is None       # 60 % of the kinematic yaw rate


def test_a_vehicle_that_ignores_its_acceleration_commands_is_unresponsive():
    assert drive(ResponseWatch(CFG, 0.05), 2.0, 0.0).startswith("unresponsive: measured acceleration")
    assert drive(ResponseWatch(CFG, 0.05), -3.0, 0.5).startswith("unresponsive: measured acceleration")


def test_a_yaw_rate_that_does_not_follow_the_steering_is_unresponsive_and_slow_windows_are_not_judged():
    assert drive(ResponseWatch(CFG, 0.05), 0.0, 0.0, 0.4, 0.0).startswith("unresponsive: yaw rate 0.00 times")
    assert drive(ResponseWatch(CFG, 0.05), 0.0, 0.0, 0.4, -0.3).startswith("unresponsive: yaw rate -0.75 times")
    assert drive(ResponseWatch(CFG, 0.05), 0.0, 0.0, 0.05, 0.0) is None      # too little steering to judge
    assert drive(ResponseWatch(CFG, 0.05), 2.0, 0.0, v0=0.5) is None


def test_the_nearest_point_of_a_polyline():
    xy = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    assert nearest_on_polyline(np.array([5.0, 2.0]), xy) == (pytest.approx(2.0), 0)
    assert nearest_on_polyline(np.array([12.0, 6.0]), xy) == (pytest.approx(2.0), 1)
