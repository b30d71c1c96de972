"""Rate keeping on absolute deadlines, timing statistics, and the failsafe checks."""

import numpy as np
import pytest

from vflpcd.core.ports import StampedState
from vflpcd.daemon.config import FailsafePolicy
from vflpcd.daemon.failsafe import FailsafeMonitor
from vflpcd.daemon.ratekeeper import RateKeeper
from vflpcd.daemon.stats import TimingStats


class FakeClock:
    """A monotonic clock in ns whose sleeps advance it by the requested time plus a wake-up delay."""

    def __init__(self, wake_late_ns=0):
        self.now, self.wake_late_ns = 1_000_000_000, wake_late_ns
        self.work_ns = 0

    def clock(self):
        self.now += 1_000          # each reading costs 1 us
        return self.now

    def sleep(self, seconds):
        self.now += int(seconds * 1e9) + self.wake_late_ns


def test_deadlines_are_absolute_so_lateness_does_not_accumulate():
    fc = FakeClock(wake_late_ns=300_000)          # every sleep wakes 0.3 ms late: the spin absorbs it
    rk = RateKeeper(0.01, spin_s=0.001, clock=fc.clock, sleep=fc.sleep)
    t0 = rk.start()
    for k in range(1000):
        tick = rk.wait()
        assert tick.k == k and tick.deadline_ns == t0 + k * 10_000_000
        assert 0 <= tick.lateness_ns < 20_000
        fc.now += 4_000_000                        # 4 ms of work per tick
    assert rk.skipped == 0


def test_a_tick_late_by_more_than_a_period_skips_the_missed_deadlines():
    fc = FakeClock()
    rk = RateKeeper(0.01, clock=fc.clock, sleep=fc.sleep)
    t0 = rk.start()
    rk.wait()
    fc.now = t0 + 35_000_000                       # a 35 ms stall
    tick = rk.wait()
    assert tick.k == 1 and tick.lateness_ns > 20_000_000
    assert rk.skipped == 2                          # deadlines 2 and 3 are skipped, not run in a burst
    nxt = rk.wait()
    assert nxt.k == 4 and nxt.deadline_ns == t0 + 40_000_000 and nxt.lateness_ns < 10_000


def test_timing_stats_percentiles_against_numpy():
    rng = np.random.default_rng(0)
    x = rng.exponential(0.002, 5000)
    s = TimingStats(bin_s=1e-5, top_s=0.1, window=1000)
    for v in x:
        s.add(v)
    assert s.percentile(99) == pytest.approx(np.percentile(x, 99), abs=2e-5)
    assert s.recent_percentile(50) == pytest.approx(np.percentile(x[-1000:], 50))
    assert s.max_s == x.max() and s.n == 5000
    assert s.over(0.005) == pytest.approx(np.sum(x > 0.005), abs=3)


POLICY = FailsafePolicy(state_max_age=0.1, overrun_streak=3, stall=0.3)


def test_state_checks_name_the_fault():
    m = FailsafeMonitor(POLICY, n_x=3)
    now = 10_000_000_000
    ok = StampedState(np.zeros(3), now - 50_000_000)
    assert m.check_state(ok, now, None) is None
    assert m.check_state(None, now, None).startswith("no_state")
    assert m.check_state(StampedState(np.zeros(3), now - 150_000_000), now, None).startswith("stale_state: 150 ms")
    assert m.check_state(StampedState(np.array([0, np.nan, 0]), now), now, None).startswith("nonfinite_state")
    assert m.check_state(StampedState(np.zeros(2), now), now, None).startswith("nonfinite_state")
    assert m.check_state(ok, now, "no heartbeat for 1.2 s").startswith("link_lost: no heartbeat")
    assert m.check_command(np.array([1.0, np.inf]), 2).startswith("nonfinite_command")
    assert m.check_command(np.zeros(3), 2).startswith("nonfinite_command")
    assert m.check_command(np.zeros(2), 2) is None


def test_overrun_streak_and_stall():
    m = FailsafeMonitor(POLICY, n_x=3)
    assert [m.after_tick(o) for o in (True, True, False, True, True)] == [None] * 5
    assert m.after_tick(True).startswith("overrun_streak: 3")
    assert m.stalled(1_000_000_000, 800_000_000) is None
    assert m.stalled(1_000_000_000, 600_000_000).startswith("stall: no control tick finished for 400 ms")


def test_sched_fifo_refused_is_a_warning_not_an_error(monkeypatch, caplog):
    import os

    from vflpcd.daemon.ratekeeper import set_realtime

    def refuse(*args):
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    with caplog.at_level("WARNING", logger="vflpcd.daemon.ratekeeper"):
        assert set_realtime(50) is False
    assert "event=sched_fifo_denied priority=50" in caplog.text


def test_manual_gc_collects_only_with_slack():
    import gc

    from vflpcd.daemon.ratekeeper import ManualGC

    m = ManualGC(period_ns=10_000_000, mid_every=2, full_every=4)
    m.start()
    try:
        assert not gc.isenabled()
        m.between_ticks(1_000_000)            # 1 ms of 10 left: no collection
        assert m.collections == [0, 0, 0]
        for _ in range(3):
            m.between_ticks(8_000_000)
        assert m.collections == [1, 1, 1]     # ticks 2, 3, 4: young, middle, full
    finally:
        m.stop()
    assert gc.isenabled()
