"""A fake monotonic clock, a one-dimensional cart platform and a scripted controller for the
control loop's and the daemon service's unit tests: every time judgement (deadlines, state ages,
overruns, stalls, holds, time-outs) runs on the fake clock, so the tests take milliseconds."""

from __future__ import annotations

import asyncio
import threading

import numpy as np

from vflpcd.core.ports import ControllerBase, PlatformBase, StampedState


class FakeClock:
    """Monotonic ns; every read advances it by ``step_ns`` (so a spin on it ends), ``sleep`` and
    ``advance`` jump ahead. Thread-safe."""

    def __init__(self, step_ns: int = 10_000) -> None:
        self.ns, self.step_ns = 1_000_000_000, step_ns
        self._lock = threading.Lock()

    def __call__(self) -> int:
        with self._lock:
            self.ns += self.step_ns
            return self.ns

    def sleep(self, seconds: float) -> None:
        self.advance(seconds)

    def advance(self, seconds: float) -> None:
        with self._lock:
            self.ns += int(round(seconds * 1e9))


class Cart(PlatformBase):
    """A cart on a line, state [X, vx], command [a]; its state is stamped when read (fresh) unless
    ``frozen_at_ns`` holds a stamp (a link that stopped delivering)."""

    state_names = ("X", "vx")
    control_names = ("a",)

    def __init__(self, clock: FakeClock, *, at_rest: bool | None = None) -> None:
        self.clock = clock
        self.x = np.zeros(2)
        self.sent: list[np.ndarray] = []
        self.failsafes: list[str] = []
        self.frozen_at_ns: int | None = None
        self.link_fault: str | None = None
        self.rest = at_rest
        self.on_failsafe = None          # called with the reason (e.g. to release a hung controller)
        self.connected = self.enabled = self.closed = False

    async def connect(self) -> None:
        self.connected = True

    async def enable(self) -> None:
        self.enabled = True

    def latest_state(self) -> StampedState:
        stamp = self.frozen_at_ns if self.frozen_at_ns is not None else self.clock()
        return StampedState(self.x.copy(), stamp)

    async def send(self, command: np.ndarray) -> None:
        self.sent.append(np.array(command))

    async def failsafe(self, reason: str) -> None:
        self.failsafes.append(reason)
        if self.on_failsafe is not None:
            self.on_failsafe(reason)

    async def close(self) -> None:
        self.closed = True

    def fault(self) -> str | None:
        return self.link_fault

    @property
    def at_rest(self) -> bool | None:
        return self.rest


class Scripted(ControllerBase):
    """Returns ``command`` each step after ``compute_s`` on the fake clock; ``fail``: an exception
    to raise; ``hang``: an Event the step waits on (a controller that stops returning)."""

    name = "scripted"

    def __init__(self, clock: FakeClock, command=(0.5,), compute_s: float = 0.0) -> None:
        self.clock, self.command, self.compute_s = clock, command, compute_s
        self.fail: Exception | None = None
        self.hang: threading.Event | None = None
        self.times: list[float] = []

    def reset(self) -> None:
        self.times.clear()

    def step(self, state, t, obstacles=()):
        self.times.append(t)
        self.clock.advance(self.compute_s)
        if self.hang is not None:
            self.hang.wait(5.0)
        if self.fail is not None:
            raise self.fail
        return np.array(self.command, dtype=float)


class EventLoopThread:
    """An asyncio loop on its own thread, as the daemon's is beside the control thread."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()

    def flush(self) -> None:
        """Wait until everything scheduled on the loop so far has run."""
        asyncio.run_coroutine_threadsafe(asyncio.sleep(0), self.loop).result(2.0)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(2.0)
        self.loop.close()
