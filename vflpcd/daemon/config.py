"""The daemon's settings (the mission's [loop], [workers] and [failsafe] tables, validated by
``vflpcd.config.mission``)."""

from __future__ import annotations

from dataclasses import dataclass

EXECUTORS = ("process", "thread")
MAX_RATE_HZ = 200.0


@dataclass(frozen=True)
class LoopConfig:
    """The fixed-rate control task: rate (Hz), SCHED_FIFO request and its priority, and whether the
    garbage collector is kept out of the tick (collected between ticks when there is slack)."""

    rate_hz: float = 50.0
    sched_fifo: bool = False
    priority: int = 10
    manual_gc: bool = True

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


@dataclass(frozen=True)
class WorkerConfig:
    """Guidance and GP workers: executor (a process pool, or threads), a periodic guidance refresh
    (s; 0: replan only when due) and how often the model worker looks for a due GP refit (s)."""

    executor: str = "process"
    replan_period: float = 0.0
    refit_period: float = 1.0


@dataclass(frozen=True)
class FailsafePolicy:
    """When the daemon gives up control and brings the vehicle to its safe state.

    state_max_age: a state older than this (s) at a tick is stale; overrun_streak: consecutive
    ticks whose work ran past the next deadline; stall: seconds without a finished tick (the health
    monitor, outside the tick thread, notices a hung step); connect_timeout: seconds to connect
    and receive the first state; hold: seconds the safe action is held before the daemon exits
    (exit code 3 after a failsafe, 0 after a completed mission).

    Before it exits, the daemon waits until the vehicle is at rest: land_timeout: seconds, from
    the start of the safe action, for a quadrotor to land (the autopilot reports it on the ground
    and disarmed; the safe action's hold comes first); brake_timeout: seconds for a ground
    vehicle to brake to a standstill. Not at rest in time: exit code 4."""

    state_max_age: float = 0.2
    overrun_streak: int = 5
    stall: float = 0.5
    connect_timeout: float = 30.0
    hold: float = 3.0
    land_timeout: float = 60.0
    brake_timeout: float = 10.0

    def rest_timeout(self, aerial: bool) -> tuple[str, float]:
        """The setting that bounds the wait for rest, and its value (s)."""
        return ("land_timeout", self.land_timeout) if aerial else ("brake_timeout", self.brake_timeout)
