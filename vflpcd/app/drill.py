"""Fault drills: inject one fault into a running mission to see the failsafe act (bench and tests).

``--drill KIND@SECONDS`` (``vflpcd run``) starts fault KIND at mission time SECONDS:
- controller faults: ``stall`` (one step hangs for ``STALL_S``), ``error`` (every step raises),
  ``overrun`` (every step takes 1.5 control periods), ``nan`` (the command becomes NaN), ``veer``
  (the command's last entry is held at ``VEER``: the car steers off its path);
- platform faults (the in-process platform only): ``freeze`` (the state stops updating),
  ``nan_state`` (non-finite states), ``link`` (the driver reports a lost link), ``stuck`` (the
  actuators stick, a throttle open, and ignore the commands).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from vflpcd.base.errors import ConfigError
from vflpcd.core.ports import ControllerBase, ControllerStatus, PlatformBase

CONTROLLER_FAULTS = ("stall", "error", "overrun", "nan", "veer")
PLATFORM_FAULTS = {"freeze": "freeze", "nan_state": "nan", "link": "link", "stuck": "stuck"}
VEER = 0.3          # "veer": the command's last entry (the car's steering angle, rad) is held at this
STALL_S = 1.5


@dataclass(frozen=True)
class Drill:
    kind: str
    at_s: float

    @classmethod
    def parse(cls, spec: str) -> "Drill":
        kind, _, at = spec.partition("@")
        kinds = CONTROLLER_FAULTS + tuple(PLATFORM_FAULTS)
        try:
            at_s = float(at)
        except ValueError:
            at_s = -1.0
        if kind not in kinds or not np.isfinite(at_s) or at_s < 0:
            raise ConfigError("command line", "--drill", f"expected KIND@SECONDS with KIND one of {', '.join(kinds)}, "
                                                         f"got {spec!r}")
        return cls(kind, at_s)


class DrillController(ControllerBase):
    """Wraps a controller; from mission time ``drill.at_s`` on, injects the drill's fault. The
    inner controller's plan, background work, counters and reference are its own."""

    def __init__(self, inner: ControllerBase, drill: Drill, platform: PlatformBase, period_s: float) -> None:
        if drill.kind in PLATFORM_FAULTS and not platform.injects_faults:
            raise ConfigError("command line", "--drill", f"{drill.kind} needs a platform that injects faults (inproc)")
        self.inner, self.drill, self.platform, self.period_s = inner, drill, platform, period_s
        self.name = inner.name
        self.planning, self.jobs = inner.planning, inner.jobs
        self.fired = False
        self.fired_ns: int | None = None       # monotonic time at which the fault started

    def status(self) -> ControllerStatus:
        return self.inner.status()

    def reference_at(self, t: float):
        return self.inner.reference_at(t)

    def prepare(self, state, t: float, obstacles=()) -> None:
        self.inner.prepare(state, t, obstacles)

    def reset(self) -> None:
        self.inner.reset()

    def settle(self) -> None:
        self.inner.settle()

    def step(self, state, t, obstacles=()):
        if t >= self.drill.at_s:
            first, self.fired = not self.fired, True
            if first:
                self.fired_ns = time.monotonic_ns()
            kind = self.drill.kind
            if kind in PLATFORM_FAULTS and first:
                self.platform.inject(PLATFORM_FAULTS[kind])
            elif kind == "stall" and first:
                time.sleep(STALL_S)
            elif kind == "error":
                raise RuntimeError("drill: injected controller error")
            elif kind == "overrun":
                time.sleep(1.5 * self.period_s)
            elif kind == "nan":
                return np.full_like(np.asarray(self.inner.step(state, t, obstacles), dtype=float), np.nan)
            elif kind == "veer":
                u = np.array(self.inner.step(state, t, obstacles), dtype=float)
                u[-1] = VEER
                return u
        return self.inner.step(state, t, obstacles)
