"""Absolute-deadline rate keeping for the control thread, and the real-time set-up of that thread.

Tick k is due at t0 + k T (``time.monotonic_ns``), never at "last wake-up + T", so lateness does
not accumulate into drift. ``wait()`` sleeps with ``time.sleep`` until ``spin_s`` before the
deadline and then spins on the clock (epoll and ``asyncio.sleep`` wake about 1 ms late; a thread
with sleep plus a short spin wakes within tens of microseconds). A tick that starts more than one
period late skips the deadlines it missed (counted in ``skipped``) instead of running a burst of
late ticks. Lateness is returned for every tick and counted, not hidden.
"""

from __future__ import annotations

import gc
import logging
import os
import time
from dataclasses import dataclass

log = logging.getLogger("vflpcd.daemon.ratekeeper")


@dataclass(frozen=True)
class Tick:
    """k: tick index; deadline_ns / start_ns: monotonic ns; lateness_ns = start_ns - deadline_ns."""

    k: int
    deadline_ns: int
    start_ns: int

    @property
    def lateness_ns(self) -> int:
        return self.start_ns - self.deadline_ns


class RateKeeper:
    """Ticks every ``period_s`` from ``start()`` on."""

    def __init__(self, period_s: float, spin_s: float = 0.0008, clock=time.monotonic_ns, sleep=time.sleep) -> None:
        if period_s <= 0:
            raise ValueError(f"period must be positive, got {period_s}")
        self.period_ns = int(round(period_s * 1e9))
        self.spin_ns = int(spin_s * 1e9)
        self.clock, self.sleep = clock, sleep
        self.t0_ns: int | None = None
        self.k = 0
        self.skipped = 0

    def start(self, t0_ns: int | None = None) -> int:
        """Set tick 0's deadline (default: now); returns it."""
        self.t0_ns = self.clock() if t0_ns is None else t0_ns
        self.k = 0
        return self.t0_ns

    def deadline(self, k: int) -> int:
        return self.t0_ns + k * self.period_ns

    def wait(self) -> Tick:
        """Block until the next tick's deadline and return that tick."""
        deadline = self.deadline(self.k)
        remaining = deadline - self.clock()
        if remaining > self.spin_ns:
            self.sleep((remaining - self.spin_ns) * 1e-9)
        while self.clock() < deadline:
            pass
        start = self.clock()
        tick = Tick(self.k, deadline, start)
        behind = (start - deadline) // self.period_ns      # whole periods missed
        if behind >= 1:
            self.skipped += int(behind)
        self.k += 1 + max(0, int(behind))
        return tick


def set_realtime(priority: int) -> bool:
    """Make the calling thread SCHED_FIFO at ``priority``; False (and a warning) when not permitted."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (PermissionError, OSError, AttributeError) as exc:
        log.warning("event=sched_fifo_denied priority=%d reason=%s hint=LimitRTPRIO in the unit or CAP_SYS_NICE",
                    priority, exc)
        return False
    log.info("event=sched_fifo priority=%d", priority)
    return True


class ManualGC:
    """Garbage collection kept out of the tick (as real-time Python loops do): automatic collection
    is off, the objects of start-up are frozen out of the collector, and the control thread calls
    ``between_ticks(slack_ns)`` after its work: a young-generation collection when at least a
    third of the period is left, the middle one every ``mid_every`` and a full one every
    ``full_every`` ticks when more than half is."""

    def __init__(self, period_ns: int, mid_every: int = 100, full_every: int = 2000) -> None:
        self.period_ns, self.mid_every, self.full_every = period_ns, mid_every, full_every
        self.count = 0
        self.collections = [0, 0, 0]

    def start(self) -> None:
        gc.disable()
        gc.freeze()

    def between_ticks(self, slack_ns: int) -> None:
        self.count += 1
        generation = 0
        if slack_ns > self.period_ns // 2:
            generation = 2 if self.count % self.full_every == 0 else 1 if self.count % self.mid_every == 0 else 0
        elif slack_ns <= self.period_ns // 3:
            return
        gc.collect(generation)
        self.collections[generation] += 1

    def stop(self) -> None:
        gc.unfreeze()
        gc.enable()
