"""The control loop on a fake clock: absolute deadlines, every command to the platform, and each
way a tick gives up control (stale state, a lost link, a controller that raises or returns
non-finite numbers, an overrun streak), mission completion, and the worker-job flow."""

from __future__ import annotations

import numpy as np
import pytest

from daemon_fakes import Cart, EventLoopThread, FakeClock, Scripted
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.path import ReferencePath
from vflpcd.daemon.config import FailsafePolicy, LoopConfig, WorkerConfig
from vflpcd.daemon.control_loop import COMPLETE, FAILSAFE, RUNNING, ControlLoop, Sinks
from vflpcd.daemon.progress import Progress
from vflpcd.daemon.workers import Finished

RATE_HZ, PERIOD = 50.0, 0.02


@pytest.fixture
def aio():
    thread = EventLoopThread()
    yield thread
    thread.close()


def make_loop(aio, clock, platform, controller, *, policy=FailsafePolicy(), workers_cfg=WorkerConfig(), **kw):
    events = []
    loop = ControlLoop(platform, controller, LoopConfig(rate_hz=RATE_HZ, manual_gc=False), workers_cfg,
                       policy, aio.loop, sinks=Sinks(on_event=events.append), clock=clock, sleep=clock.sleep, **kw)
    loop.t0_ns = loop.rate.start()
    return loop, events


def run(loop, aio, n):
    for _ in range(n):
        loop.tick_once()
    aio.flush()


def test_ticks_fall_on_absolute_deadlines_and_every_command_reaches_the_platform(aio):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock, command=(0.7,), compute_s=0.004)
    loop, events = make_loop(aio, clock, cart, ctl)
    run(loop, aio, 25)
    assert ctl.times == pytest.approx([k * PERIOD for k in range(25)])
    assert [float(u[0]) for u in cart.sent] == [0.7] * 25
    c = loop.counters
    assert (c.ticks, c.commands, c.overruns, loop.rate.skipped) == (25, 25, 0, 0)
    assert loop.mode == RUNNING and events == [] and cart.failsafes == []
    assert c.lateness.percentile(100) < 1e-4             # woken within a few clock reads of the deadline


@pytest.mark.parametrize("fault, reason", [
    ("frozen", "stale_state"), ("link", "link_lost"), ("raises", "controller_error"),
    ("nan", "nonfinite_command"), ("inf_state", "nonfinite_state"), ("wrong_size", "nonfinite_command"),
])
def test_a_fault_trips_the_failsafe_once_and_no_command_follows(aio, fault, reason):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock)
    loop, events = make_loop(aio, clock, cart, ctl, policy=FailsafePolicy(state_max_age=0.1))
    run(loop, aio, 5)
    if fault == "frozen":
        cart.frozen_at_ns = clock()
    elif fault == "link":
        cart.link_fault = "no heartbeat for 0.5 s"
    elif fault == "raises":
        ctl.fail = RuntimeError("solver diverged")
    elif fault == "nan":
        ctl.command = (float("nan"),)
    elif fault == "inf_state":
        cart.x[1] = float("inf")
    elif fault == "wrong_size":
        ctl.command = (0.1, 0.2)
    run(loop, aio, 20)
    assert loop.mode == FAILSAFE and loop.reason.startswith(reason + ":")
    assert len(cart.failsafes) == 1 and cart.failsafes[0] == loop.reason
    sent_before = 5 + (5 if fault == "frozen" else 0)      # a frozen state is stale after 0.1 s (5 ticks)
    assert len(cart.sent) == sent_before
    assert [e.kind for e in events] == ["failsafe"] and events[0].detail["action"] == "brake_to_stop"
    assert loop.counters.ticks == 25                       # it keeps ticking (recording), not commanding


def test_a_streak_of_overruns_trips_the_failsafe_and_missed_deadlines_are_skipped(aio):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock, compute_s=2.5 * PERIOD)
    loop, events = make_loop(aio, clock, cart, ctl, policy=FailsafePolicy(overrun_streak=5))
    run(loop, aio, 8)
    assert loop.mode == FAILSAFE and loop.reason.startswith("overrun_streak: 5 consecutive")
    assert loop.counters.overruns == 6 and loop.rate.skipped == 7
    # the missed deadlines were skipped, not run as a burst
    assert np.all(np.diff(ctl.times) >= PERIOD - 1e-9) and loop.rate.k == loop.counters.ticks + loop.rate.skipped


def test_one_overrun_does_not_trip(aio):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock)
    loop, _ = make_loop(aio, clock, cart, ctl, policy=FailsafePolicy(overrun_streak=3))
    for k in range(30):
        ctl.compute_s = 2.5 * PERIOD if k % 3 == 0 else 0.0
        loop.tick_once()
    aio.flush()
    # a slow tick and the late tick after it both end past their next deadline: 2 of every 3
    assert loop.mode == RUNNING and loop.counters.overruns == 20


def test_at_the_goal_the_mission_completes_and_the_vehicle_is_brought_to_rest(aio):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock)
    path = ReferencePath(np.array([[0.0, 0.0], [100.0, 0.0]]))
    progress = Progress(path, goal=10.0, position_index=[0, 1])   # [X, vx]: vx = 0 is on the line
    loop, events = make_loop(aio, clock, cart, ctl, progress=progress)
    for _ in range(20):
        cart.x[0] += 1.0
        loop.tick_once()
    aio.flush()
    assert loop.mode == COMPLETE and cart.failsafes == ["mission_complete"]
    assert [e.kind for e in events] == ["mission_complete"] and len(cart.sent) == 11     # the first state starts the count


class Jobs:
    """A controller's worker jobs: a replan whenever asked, a refit every time it is due."""

    planner = None

    def __init__(self):
        self.installed, self.failed, self.asked = [], [], []

    def take_replan(self, force_at=None):
        self.asked.append(force_at)
        return ("plan", force_at) if force_at is not None else None

    def install_plan(self, job, result):
        self.installed.append(("plan", job, result))

    def replan_failed(self, job, reason):
        self.failed.append(reason)

    def take_refit(self):
        return ("refit",)

    def install_model(self, job, model):
        self.installed.append(("model", job, model))


class FakeWorkers:
    def __init__(self):
        self.submitted, self.done, self.in_flight = [], [], set()

    def busy(self, which):
        return which in self.in_flight

    def submit(self, which, job):
        self.submitted.append((which, job))
        self.in_flight.add(which)
        return True

    def collect(self):
        out, self.done = self.done, []
        for f in out:
            self.in_flight.discard(f.kind)
        return out


def test_worker_jobs_are_submitted_when_due_and_their_results_installed_between_ticks(aio):
    clock = FakeClock()
    cart, ctl = Cart(clock), Scripted(clock)
    ctl.jobs = jobs = Jobs()
    workers = FakeWorkers()
    loop, events = make_loop(aio, clock, cart, ctl, workers=workers,
                             workers_cfg=WorkerConfig(replan_period=0.1, refit_period=0.2))
    run(loop, aio, 6)                                     # t = 0 .. 0.1: one forced replan at 0.1
    assert workers.submitted == [("replan", ("plan", pytest.approx(0.1)))]
    workers.done.append(Finished("replan", ("plan", 0.1), "the plan", None, 0.05))
    run(loop, aio, 6)                                     # installed at the next tick, refit due at 0.2
    assert jobs.installed[0] == ("plan", ("plan", 0.1), "the plan")
    assert ("refit", ("refit",)) in workers.submitted
    workers.done += [Finished("replan", ("plan", 0.2), None, GuidanceError("no route around the wall"), 0.05),
                     Finished("refit", ("refit",), None, MemoryError("GP"), 0.05)]
    run(loop, aio, 1)
    assert jobs.failed == ["no route around the wall"] and loop.counters.worker_errors == 1
    assert [e.kind for e in events] == ["replan_failed", "worker_error"]
    assert loop.mode == RUNNING                           # a failed background job does not stop control
