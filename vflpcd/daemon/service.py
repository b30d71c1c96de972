"""The daemon: asyncio orchestration around the control thread.

``Daemon.run()``:
1. connects the platform and waits for its first state (``failsafe.connect_timeout``); a platform
   with ``prepare()`` is then brought to the route's start (the quadrotor arms and takes off);
2. plans the first reference and starts the workers (off the event loop);
3. enables the platform (arm / engage), starts the control thread, sends READY=1;
4. monitors health every ``monitor_s``: a stalled control thread trips the failsafe; WATCHDOG=1 is
   sent only while ticks finish on time; STATUS= and health telemetry once a second;
5. ends when the mission is complete or a failsafe has held for ``failsafe.hold`` seconds, or on
   SIGTERM/SIGINT (safe stop, flush the log, exit 0 within 2 s).
Exit codes: 0 stopped or mission complete, 3 failsafe latched (systemd does not restart it),
2 no first plan from where the vehicle is (the route does not fit), 1 the platform never
connected or start-up failed.
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from dataclasses import dataclass

from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.daemon.control import COMPLETE, FAILSAFE, RUNNING, STOPPING, ControlLoop
from vflpcd.daemon.sdnotify import SystemdNotifier

log = logging.getLogger("vflpcd.daemon")

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT, EXIT_FAILSAFE = 0, 1, 2, 3


@dataclass
class Outcome:
    """How the run ended: exit code, why, and the control loop (its counters and timings)."""

    code: int
    reason: str
    loop: ControlLoop | None


class Daemon:
    """``make_loop(aio)`` builds the ControlLoop once the event loop exists; ``first_plan(state)``
    plans the first reference (may take a second); ``closers``: callables run at shutdown, in order
    (workers, telemetry, recorder), each bounded in time by its own implementation."""

    def __init__(self, platform, make_loop, *, first_plan=None, workers=None, closers=(),
                 notifier: SystemdNotifier | None = None, telemetry=None, monitor_s: float = 0.05,
                 stop_after_s: float | None = None) -> None:
        self.platform, self.make_loop, self.first_plan = platform, make_loop, first_plan
        self.workers, self.closers = workers, list(closers)
        self.notifier = notifier or SystemdNotifier.from_env()
        self.telemetry, self.monitor_s, self.stop_after_s = telemetry, monitor_s, stop_after_s
        self.loop: ControlLoop | None = None
        self._signal: str | None = None
        self._wake: asyncio.Event | None = None

    async def run(self) -> Outcome:
        aio = asyncio.get_running_loop()
        self._wake = asyncio.Event()
        for sig in (signal.SIGTERM, signal.SIGINT):
            aio.add_signal_handler(sig, self._on_signal, sig.name)
        try:
            return await self._run(aio)
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                aio.remove_signal_handler(sig)

    def _on_signal(self, name: str) -> None:
        self.request_stop(name)

    def request_stop(self, reason: str) -> None:
        """Stop as on SIGTERM (event loop thread)."""
        self._signal = reason
        self._wake.set()

    async def _run(self, aio) -> Outcome:
        self.loop = loop = self.make_loop(aio)
        policy = loop.policy
        self.notifier.status("connecting to the platform")
        try:
            await asyncio.wait_for(self.platform.connect(), policy.connect_timeout)
            first = await self._first_state(policy.connect_timeout)
        except (asyncio.TimeoutError, OSError) as exc:
            reason = f"platform did not connect within {policy.connect_timeout:g} s ({type(exc).__name__}: {exc})"
            log.error("event=connect_failed reason=%s", reason)
            await self._shutdown(loop, started=False)
            return Outcome(EXIT_ERROR, reason, loop)
        if self._signal:
            await self._shutdown(loop, started=False)
            return Outcome(EXIT_OK, self._signal, loop)
        prepare = getattr(self.platform, "prepare", None)
        if prepare is not None:             # e.g. the quadrotor arms and takes off to the route's start
            self.notifier.status("preparing the platform")
            try:
                await prepare()
                first = await self._first_state(policy.connect_timeout, after_ns=time.monotonic_ns())
            except Exception as exc:
                reason = f"platform preparation failed: {type(exc).__name__}: {exc}"
                log.error("event=prepare_failed reason=%s", reason)
                await self._shutdown(loop, started=False, reason=reason, prepared=True)
                return Outcome(EXIT_ERROR, reason, loop)
            if self._signal:
                await self._shutdown(loop, started=False, reason=self._signal, prepared=True)
                return Outcome(EXIT_OK, self._signal, loop)
        self.notifier.status("planning the first reference")
        try:
            if self.first_plan is not None:
                await aio.run_in_executor(None, self.first_plan, first.state)
        except (GuidanceError, ValueError) as exc:     # e.g. the vehicle starts inside an obstacle
            reason = f"no first plan from the vehicle's state: {exc}"
            log.error("event=first_plan_failed reason=%s", reason)
            await self._shutdown(loop, started=False, reason=reason, prepared=prepare is not None)
            return Outcome(EXIT_BAD_INPUT, reason, loop)
        try:
            if self.workers is not None:
                await aio.run_in_executor(None, self.workers.start)
            await self.platform.enable()
        except Exception as exc:
            reason = f"start-up failed: {type(exc).__name__}: {exc}"
            log.exception("event=startup_failed")
            await self._shutdown(loop, started=False, reason=reason, prepared=prepare is not None)
            return Outcome(EXIT_ERROR, reason, loop)
        loop.start()
        if self.stop_after_s is not None:
            aio.call_later(self.stop_after_s, self.request_stop, f"ran {self.stop_after_s:g} s")
        loop.event("started", rate_hz=loop.cfg.rate_hz, controller=getattr(loop.controller, "name", "?"),
                   realtime=loop.cfg.sched_fifo)
        self.notifier.ready()
        loop.event("ready")
        outcome = await self._monitor(loop)
        await self._shutdown(loop, started=True, reason=outcome.reason)
        return outcome

    async def _first_state(self, timeout_s: float, after_ns: int = 0):
        """The platform's first state (stamped at or after ``after_ns``)."""
        deadline = time.monotonic() + timeout_s
        while True:
            s = self.platform.latest_state()
            if s is not None and s.stamp_ns >= after_ns:
                return s
            if self._signal:
                return None
            if time.monotonic() > deadline:
                raise asyncio.TimeoutError("no state received")
            await asyncio.sleep(0.01)

    async def _monitor(self, loop: ControlLoop) -> Outcome:
        period_ns = loop.rate.period_ns
        pet_s = self.notifier.watchdog_period_s
        next_pet = next_status = time.monotonic()
        while True:
            try:
                await asyncio.wait_for(self._wake.wait(), self.monitor_s)
            except asyncio.TimeoutError:
                pass
            if self._signal:
                return Outcome(EXIT_OK, self._signal, loop)
            now_ns = time.monotonic_ns()
            stall = loop.monitor.stalled(now_ns, loop.last_tick_ns)
            if stall is not None and loop.mode == RUNNING:
                loop.trip(stall)
            on_time = now_ns - loop.last_tick_ns <= max(3 * period_ns, int(0.05e9))
            now = time.monotonic()
            if pet_s is not None and on_time and now >= next_pet:
                self.notifier.watchdog()
                next_pet = now + pet_s / 2
            if now >= next_status:
                next_status = now + 1.0
                self._health(loop)
            if loop.mode in (FAILSAFE, COMPLETE) and loop.ended_ns is not None:
                held = (now_ns - loop.ended_ns) * 1e-9
                at_rest = getattr(self.platform, "at_rest", None)
                if held >= loop.policy.hold or (loop.mode == COMPLETE and at_rest and held >= 0.5):
                    if loop.mode == COMPLETE:
                        return Outcome(EXIT_OK, "mission_complete", loop)
                    return Outcome(EXIT_FAILSAFE, loop.reason or "failsafe", loop)

    def _health(self, loop: ControlLoop) -> None:
        c = loop.counters
        health = {"mode": loop.mode, "t": round(loop.mission_time(time.monotonic_ns()), 3), "ticks": c.ticks,
                  "overruns": c.overruns, "skipped": loop.rate.skipped,
                  "lateness_p99_ms": round(c.lateness.recent_percentile(99) * 1e3, 3),
                  "compute_p99_ms": round(c.compute.recent_percentile(99) * 1e3, 3),
                  "replans": int(getattr(loop.controller, "replans", 0)),
                  "replan_failures": int(getattr(loop.controller, "replan_failures", 0)),
                  "refits": int(getattr(loop.controller, "refits", 0)),
                  "worker_errors": c.worker_errors, "send_errors": c.send_errors,
                  "fallbacks": int(getattr(loop.controller, "fallbacks", 0)),
                  "progress_m": round(loop.progress.covered, 1) if loop.progress is not None else None,
                  "reason": loop.reason}
        self.notifier.status(f"{loop.mode} t={health['t']:.1f}s ticks={c.ticks} overruns={c.overruns} "
                             f"late_p99={health['lateness_p99_ms']:.2f}ms compute_p99={health['compute_p99_ms']:.2f}ms")
        if self.telemetry is not None:
            self.telemetry.offer_health(health)

    async def _shutdown(self, loop: ControlLoop, *, started: bool, reason: str = "", prepared: bool = False) -> None:
        """Safe stop in at most about 2 s: stop commanding, the platform's safe action, close all.
        ``prepared``: the platform was prepared (e.g. is flying) though the loop never started."""
        self.notifier.stopping()
        if prepared and not started:
            await self._bounded(self.platform.failsafe(f"shutdown: {reason}"), 0.5)
        if started:
            if loop.mode == RUNNING:
                loop.mode = STOPPING
                await self._bounded(self.platform.failsafe(f"shutdown: {reason}"), 0.5)
            link_stats = getattr(self.platform, "link_stats", None)
            if link_stats is not None:
                loop.event("link_stats", **link_stats())
            loop.event("stopping", reason=reason)
            loop.stop(0.5)
        await self._bounded(self.platform.close(), 0.5)
        for close in self.closers:
            try:
                close()
            except Exception:                  # shutdown must go on
                log.exception("event=close_failed")

    @staticmethod
    async def _bounded(coro, timeout_s: float) -> None:
        try:
            await asyncio.wait_for(coro, timeout_s)
        except asyncio.TimeoutError:
            log.warning("event=shutdown_step_timeout timeout_s=%.1f", timeout_s)
        except Exception as exc:
            log.warning("event=shutdown_step_failed reason=%s", exc)
