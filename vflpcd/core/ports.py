"""The two ports of the system: every controller and every platform driver implements one.

``Controller`` is implemented by VF-LPC and every baseline, so the offline runner, the
benchmarks and the daemon take any of them. ``Platform`` is implemented by every driver
(in-process plant, MAVLink quadrotor, CAN vehicle); the daemon knows no protocol details.
Everything the runner and the daemon call is declared here: the optional members have safe
defaults in ``ControllerBase`` and ``PlatformBase``, which every controller and driver derive
from; a controller's background work follows ``WorkerJobs`` (``vflpcd.core.jobs`` runs it
inline); its counters are one ``ControllerStatus``. Nothing is probed with getattr.
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

    The optional members (``prepare``, ``fault``, ``at_rest``, ``link_stats``, ``link_warnings``,
    ``inject``) and the ``safe_action`` are declared, with safe defaults, by ``PlatformBase``.
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


@dataclass(frozen=True)
class ControllerStatus:
    """A controller's counters, one record (``Controller.status()``): guidance plans installed
    (``replans``) and failed, GP refits installed, solver fallbacks, the obstacles whose barrier is
    on (``threats``, ids), and finished replans set aside as stale (``stale_replans``: planned from
    where the robot no longer is)."""

    replans: int = 0
    replan_failures: int = 0
    refits: int = 0
    fallbacks: int = 0
    threats: tuple[str, ...] = ()
    stale_replans: int = 0


class WorkerJobs(Protocol):
    """The background work of a controller, in three steps: ``take_*`` hands out a job (or None),
    someone runs it (``vflpcd.core.jobs``: inline in the offline runner, on the daemon's worker
    processes), and ``install_*`` / ``replan_failed`` hand the outcome back between two ticks.
    ``planner`` is the object a replan runs on (given to each guidance worker once)."""

    planner: object

    def take_replan(self, force_at: float | None = None): ...

    def install_plan(self, job, result) -> None: ...

    def replan_failed(self, job, reason: str) -> None: ...

    def take_refit(self): ...

    def install_model(self, job, model) -> None: ...


class ControllerBase:
    """The ``Controller`` port with safe defaults for its optional members (as python-can's
    ``BusABC``): no plan of its own (``planning`` None), no background work (``jobs`` None), zero
    counters, no reference, nothing to prepare. Every controller derives from it."""

    name: str = ""
    planning: PlanningController | None = None
    jobs: WorkerJobs | None = None

    def reset(self) -> None:
        raise NotImplementedError

    def step(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> np.ndarray:
        raise NotImplementedError

    def status(self) -> ControllerStatus:
        return ControllerStatus()

    def reference_at(self, t: float) -> np.ndarray | None:
        """The reference position (d,) at time t, None without one."""
        return None

    def prepare(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> None:
        """Before the first tick, from the first state (VF-LPC plans its first reference)."""

    def settle(self) -> None:
        """After a step's command is sent: the step's work that the command does not wait for (a
        learning controller's sample of the transition it saw). A controller whose ``settle`` is not
        called does it at its next step; nothing to do by default."""


class PlatformBase:
    """The ``Platform`` port with safe defaults for its optional members: ``prepare`` does nothing
    (``prepares`` False; the quadrotor arms and takes off), no link ``fault``, ``at_rest`` unknown
    (None), no ``link_stats`` and no ``link_warnings``, no fault injection (``injects_faults`` False). ``safe_action`` names
    what ``failsafe`` does: "brake_to_stop" (ground) or "hold_then_land" (aerial)."""

    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    safe_action: str = "brake_to_stop"
    prepares: bool = False
    injects_faults: bool = False

    async def connect(self) -> None:
        raise NotImplementedError

    async def enable(self) -> None:
        raise NotImplementedError

    def latest_state(self) -> StampedState | None:
        raise NotImplementedError

    async def send(self, command: np.ndarray) -> None:
        raise NotImplementedError

    async def failsafe(self, reason: str) -> None:
        raise NotImplementedError

    async def close(self) -> None:
        raise NotImplementedError

    async def prepare(self) -> None:
        """After the first state, bring the vehicle to the route's start (default: nothing to do)."""

    def fault(self) -> str | None:
        """A link fault as a string, None while the link is sound."""
        return None

    @property
    def at_rest(self) -> bool | None:
        """Standing still / landed and disarmed; None: the platform cannot tell."""
        return None

    def link_stats(self) -> dict:
        """The link's counters for the log ({} without any)."""
        return {}

    def link_warnings(self) -> tuple[str, ...]:
        """Weaknesses of the link as configured, one line each, for ``vflpcd check`` (default: none)."""
        return ()

    def inject(self, fault: str | None) -> None:
        """Start (or with None end) an injected fault (drills); only where ``injects_faults``."""
        raise NotImplementedError(f"{type(self).__name__} does not inject faults")
