"""The CPU time a virtual machine's host takes from it ("steal", ``/proc/stat``), sampled over a run.

A guest's vCPU that the host runs something else on stops dead: a SCHED_FIFO thread on it starts
its tick late by however long that lasts, and nothing inside the guest can prevent it. A bench of
the loop's timing samples the machine's steal counter beside the run (``StealSampler``), so that
each late tick can be told apart: one that began while the host was taking CPU time, or one the
daemon made late itself.

The counter is the sum over the CPUs of the ``steal`` column of ``/proc/stat``'s ``cpu`` line, in
USER_HZ ticks (10 ms of one CPU on Linux): a window in which it grew held at least one stolen tick
of some CPU. Without ``/proc/stat`` (not Linux) nothing is sampled and every answer is None.
"""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

import numpy as np

PROC_STAT = Path("/proc/stat")
STEAL_COLUMN = 8            # cpu user nice system idle iowait irq softirq steal ...
PERIOD_S = 0.1              # sampling period
USER_HZ = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100


def read_steal(path: Path = PROC_STAT) -> int | None:
    """The machine's steal counter (USER_HZ ticks, summed over the CPUs), None where it cannot be read."""
    try:
        with open(path, "rb") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if len(fields) <= STEAL_COLUMN or fields[0] != b"cpu":
        return None
    return int(fields[STEAL_COLUMN])


class StealSampler:
    """Samples ``read_steal`` every ``period_s`` on ``time.monotonic_ns`` (the daemon's clock) in a
    thread of its own between ``start()`` and ``stop()``."""

    def __init__(self, period_s: float = PERIOD_S, read=read_steal) -> None:
        self.period_s, self._read = period_s, read
        self.stamps: list[int] = []
        self.counts: list[int] = []
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    @property
    def available(self) -> bool:
        return len(self.counts) >= 2

    def _sample(self) -> None:
        value = self._read()
        if value is not None:
            self.stamps.append(time.monotonic_ns())
            self.counts.append(value)

    def start(self) -> "StealSampler":
        self._sample()
        if self.counts:          # nothing to sample where there is no counter
            self._thread = threading.Thread(target=self._run, name="steal-sampler", daemon=True)
            self._thread.start()
        return self

    def _run(self) -> None:
        while not self._stop.wait(self.period_s):
            self._sample()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._sample()

    def share(self, cpus: int | None = None) -> float | None:
        """Steal as a fraction of the CPU time of the sampled span (all ``cpus``, default this
        machine's), None without two samples."""
        if not self.available:
            return None
        span_s = (self.stamps[-1] - self.stamps[0]) * 1e-9
        cpus = cpus or os.cpu_count() or 1
        return (self.counts[-1] - self.counts[0]) / USER_HZ / max(span_s * cpus, 1e-9)

    def stolen_near(self, stamps_ns: np.ndarray) -> np.ndarray | None:
        """Per stamp (monotonic ns), whether the counter grew between the last sample a sampling
        period or more before it and the first a period or more after it (a window of two to three
        periods: the host's hold comes before a late tick's start, and the kernel books steal at
        its next timer tick); None without two samples. A stamp whose window leaves the sampled
        span counts as not stolen."""
        if not self.available:
            return None
        stamps = np.asarray(self.stamps, dtype=np.int64)
        counts = np.asarray(self.counts)
        s = np.asarray(stamps_ns, dtype=np.int64)
        p = int(self.period_s * 1e9)
        before = np.searchsorted(stamps, s - p, side="right") - 1
        after = np.searchsorted(stamps, s + p, side="left")
        inside = (before >= 0) & (after < len(stamps))
        grew = counts[np.clip(after, 0, len(stamps) - 1)] > counts[np.clip(before, 0, None)]
        return inside & grew
