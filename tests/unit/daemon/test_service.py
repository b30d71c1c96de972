"""The daemon service on a fake clock (every hold, time-out and stall judged on it, the control
thread ticking on it): how a run ends and with which exit code, in milliseconds of real time."""

from __future__ import annotations

import asyncio
import threading

import numpy as np

from daemon_fakes import Cart, FakeClock, Scripted
from vflpcd.core.path import ReferencePath
from vflpcd.daemon.config import FailsafePolicy, LoopConfig, WorkerConfig
from vflpcd.daemon.control_loop import ControlLoop, Sinks
from vflpcd.daemon.progress import Progress
from vflpcd.daemon.service import (EXIT_COLLISION, EXIT_ERROR, EXIT_FAILSAFE, EXIT_NOT_AT_REST, EXIT_OK,
                                   Daemon)


class Notifier:
    """Records what the daemon tells systemd."""

    watchdog_period_s = None

    def __init__(self):
        self.said = []

    def status(self, text):
        self.said.append(("STATUS", text))

    def ready(self):
        self.said.append(("READY", ""))

    def stopping(self):
        self.said.append(("STOPPING", ""))

    def watchdog(self):
        self.said.append(("WATCHDOG", ""))


def daemon(clock, cart, ctl, *, policy, progress=None, stop_after_s=None):
    events = []

    def make_loop(aio):
        return ControlLoop(cart, ctl, LoopConfig(rate_hz=50.0, manual_gc=False), WorkerConfig(), policy, aio,
                           progress=progress, sinks=Sinks(on_event=events.append), clock=clock, sleep=clock.sleep)
    d = Daemon(cart, make_loop, notifier=Notifier(), monitor_s=0.001, stop_after_s=stop_after_s, clock=clock)
    return d, events


def run(d):
    return asyncio.run(asyncio.wait_for(d.run(), 20.0))


def test_a_latched_failsafe_holds_for_failsafe_hold_on_the_clock_then_exits_3():
    clock = FakeClock()
    cart, ctl = Cart(clock, at_rest=True), Scripted(clock)
    ctl.fail = RuntimeError("diverged")
    d, events = daemon(clock, cart, ctl, policy=FailsafePolicy(hold=2.0))
    out = run(d)
    assert out.code == EXIT_FAILSAFE and out.reason.startswith("controller_error: RuntimeError: diverged")
    assert cart.enabled and cart.closed and cart.failsafes[0] == out.reason
    kinds = [e.kind for e in events]
    assert {"started", "ready", "failsafe"} <= set(kinds) and kinds[-1] == "stopping"
    (trip,) = [e for e in events if e.kind == "failsafe"]
    (stop,) = [e for e in events if e.kind == "stopping"]
    assert stop.t - trip.t >= 2.0                       # held on the (fake) clock, not cut short


def test_a_collision_failsafe_exits_5():
    clock = FakeClock()
    cart, ctl = Cart(clock, at_rest=True), Scripted(clock)
    d, _ = daemon(clock, cart, ctl, policy=FailsafePolicy(hold=0.5))
    threading.Timer(0.05, lambda: d.loop.trip("collision: body touched wall")).start()
    assert run(d).code == EXIT_COLLISION


def test_a_control_thread_that_stops_ticking_is_tripped_as_a_stall_by_the_monitor():
    clock = FakeClock(step_ns=1_000_000)              # each read 1 ms: the monitor's polls move time on
    cart, ctl = Cart(clock, at_rest=True), Scripted(clock)
    hang = threading.Event()
    cart.on_failsafe = lambda reason: hang.set()     # the safe action releases the hung step
    ctl.hang = threading.Event()
    threading.Timer(0.02, lambda: setattr(ctl, "hang", hang)).start()
    ctl.hang.set()
    d, events = daemon(clock, cart, ctl, policy=FailsafePolicy(stall=0.5, hold=0.2))
    out = run(d)
    assert out.code == EXIT_FAILSAFE and out.reason.startswith("stall: no control tick finished for")
    assert cart.failsafes[0] == out.reason


def test_mission_complete_exits_0_once_the_vehicle_is_at_rest():
    clock = FakeClock()
    cart, ctl = Cart(clock, at_rest=False), Scripted(clock)
    progress = Progress(ReferencePath(np.array([[0.0, 0.0], [100.0, 0.0]])), goal=5.0, position_index=[0, 1])
    cart.on_failsafe = lambda reason: setattr(cart, "rest", True)      # it stops when told to

    orig = cart.latest_state

    def moving():
        cart.x[0] += 0.05
        return orig()
    cart.latest_state = moving
    d, events = daemon(clock, cart, ctl, policy=FailsafePolicy(hold=3.0), progress=progress)
    out = run(d)
    assert out == out.__class__(EXIT_OK, "mission_complete", d.loop)
    assert cart.failsafes == ["mission_complete"]
    kinds = [e.kind for e in events]
    assert "mission_complete" in kinds and "at_rest" in kinds and kinds[-1] == "stopping"


def test_a_vehicle_that_does_not_stop_within_brake_timeout_turns_the_exit_into_4():
    clock = FakeClock(step_ns=1_000_000)
    cart, ctl = Cart(clock, at_rest=False), Scripted(clock)
    d, events = daemon(clock, cart, ctl, policy=FailsafePolicy(brake_timeout=1.5), stop_after_s=0.05)
    out = run(d)
    assert out.code == EXIT_NOT_AT_REST
    assert "the vehicle was not at a standstill within failsafe.brake_timeout = 1.5 s" in out.reason
    (timeout,) = [e for e in events if e.kind == "rest_timeout"]
    assert timeout.detail["setting"] == "brake_timeout"
    assert cart.failsafes == ["shutdown: ran 0.05 s"]


def test_a_stop_request_after_a_failsafe_keeps_the_failsafe_as_the_outcome():
    clock = FakeClock()
    cart, ctl = Cart(clock, at_rest=True), Scripted(clock)
    d, _ = daemon(clock, cart, ctl, policy=FailsafePolicy(hold=1e6))        # would hold for ever

    def trip_then_stop():
        d.loop.trip("stale_state: 300 ms old")
        threading.Timer(0.05, lambda: d.loop.aio.call_soon_threadsafe(d.request_stop, "SIGTERM")).start()
    threading.Timer(0.05, trip_then_stop).start()
    out = run(d)
    assert out.code == EXIT_FAILSAFE and out.reason == "stale_state: 300 ms old (then SIGTERM)"


def test_a_platform_that_never_delivers_a_state_ends_with_exit_1_and_nothing_enabled():
    clock = FakeClock(step_ns=20_000_000)
    cart, ctl = Cart(clock), Scripted(clock)
    cart.latest_state = lambda: None
    d, _ = daemon(clock, cart, ctl, policy=FailsafePolicy(connect_timeout=0.5))
    out = run(d)
    assert out.code == EXIT_ERROR and "did not connect within 0.5 s" in out.reason
    assert not cart.enabled and cart.failsafes == [] and cart.closed
