"""The two ports of the system: every controller and every platform driver implements one.

``Controller`` is implemented by VF-LPC and every baseline, so the offline runner, the
benchmarks and the daemon take any of them. ``Platform`` is implemented by every driver
(in-process plant, MAVLink quadrotor, CAN vehicle); the daemon knows no protocol details.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, Sequence, runtime_checkable

import numpy as np

from vflpcd.core.obstacles import ObstacleState


@runtime_checkable
class Controller(Protocol):
    """A steppable feedback law.

    ``step`` maps the platform state (its ``state_names`` order, shape (n_x,)), the time t
    in seconds and the obstacles perceived at t to a command (n_u,) in the platform's
    ``control_names`` order. It must not block on I/O and must not read a clock: time is
    the argument.
    """

    name: str

    def reset(self) -> None: ...

    def step(self, state: np.ndarray, t: float,
             obstacles: Sequence[ObstacleState] = ()) -> np.ndarray: ...


@runtime_checkable
class PlanningController(Protocol):
    """A controller that follows a plan of its own (VF-LPC), which the safety monitors check:
    ``current_plan`` (with ``kappa`` (K,) and ``v`` (K,): the path's curvature and speed plan; None
    before the first), ``reference_at(t)`` (the reference position (d,) or None), and the counts of
    installed (``replans``) and failed (``replan_failures``) replans. ``plan_gate``: None, or a
    callable plan -> reason that the controller asks before it installs a replan; a reason refuses
    it (the previous plan stays, the refusal counts as a failed replan)."""

    replans: int
    replan_failures: int
    plan_gate: object

    @property
    def current_plan(self): ...

    def reference_at(self, t: float) -> np.ndarray | None: ...


@dataclass(frozen=True)
class StampedState:
    """A platform state with the monotonic time (ns) at which it was measured."""

    state: np.ndarray
    stamp_ns: int


class Platform(Protocol):
    """A vehicle link: connect, enable (arm), read the latest state, send commands, fail safe.

    Optional members the daemon uses when a driver has them: ``async prepare()`` (after the first
    state, bring the vehicle to the route's start: the quadrotor arms and takes off), ``fault()``
    (a link fault as a string, or None), ``at_rest`` (stands still / landed), ``link_stats()``
    (the link's counters for the log), ``inject(kind)`` (drills).
    """

    state_names: tuple[str, ...]
    control_names: tuple[str, ...]

    async def connect(self) -> None: ...

    async def enable(self) -> None: ...

    def latest_state(self) -> StampedState | None:
        """Newest state received, without waiting; None before the first one."""
        ...

    async def send(self, command: np.ndarray) -> None: ...

    async def failsafe(self, reason: str) -> None:
        """Bring the vehicle to its safe state (vehicle: brake to stop; quadrotor: hold, then land)."""
        ...

    async def close(self) -> None: ...
