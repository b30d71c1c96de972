"""The daemon: asyncio orchestration around the control thread.

``Daemon.run()``:
1. connects the platform and waits for its first state (``failsafe.connect_timeout``); a platform
   with ``prepare()`` is then brought to the route's start (the quadrotor arms and takes off);
2. plans the first reference and starts the workers (off the event loop);
3. enables the platform (arm / engage), starts the control thread, sends READY=1;
4. monitors health every ``monitor_s``: a stalled control thread trips the failsafe; WATCHDOG=1 is
   sent only while ticks finish on time; STATUS= and health telemetry once a second;
5. ends when the mission is complete or a failsafe has held for ``failsafe.hold`` seconds, or on
   SIGTERM/SIGINT (a stop request; during the take-off it cancels it);
6. shuts down (``_shutdown``): stops commanding, hands the vehicle to the platform's safe action
   (a quadrotor holds, then lands; a ground vehicle brakes), waits until the platform reports it
   at rest (landed and disarmed: at most ``failsafe.land_timeout`` s; standing still: at most
   ``failsafe.brake_timeout`` s; counted from the start of the safe action; WATCHDOG=1 goes on
   meanwhile), then flushes the log and closes everything (about 2 s more at most). A platform
   that was never enabled (nor prepared) has not moved and is not waited for.
Exit codes: 0 stopped (SIGTERM/SIGINT) or mission complete, with the vehicle at rest; 1 the
platform never connected or start-up failed; 2 no first plan from where the vehicle is (the route
does not fit); 3 failsafe latched (also when a stop request came during its hold; systemd does not
restart it); 4 the vehicle was not at rest within ``failsafe.land_timeout`` /
``failsafe.brake_timeout`` (it may still be flying or rolling: systemd does not restart it); 5 a
collision: the body touched an obstacle the daemon knew of (a failsafe of kind ``collision``, or
contact found in the flight log afterwards by ``vflpcd run``; systemd does not restart it).
"""

from __future__ import annotations

import asyncio
import logging
import signal
import time
from dataclasses import dataclass

from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.ports import PlatformBase
from vflpcd.daemon.control_loop import COMPLETE, FAILSAFE, RUNNING, STOPPING, ControlLoop
from vflpcd.daemon.sdnotify import SystemdNotifier

log = logging.getLogger("vflpcd.daemon")

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT, EXIT_FAILSAFE, EXIT_NOT_AT_REST, EXIT_COLLISION = 0, 1, 2, 3, 4, 5


def failsafe_exit(reason: str | None) -> int:
    """The exit code of a latched failsafe: 5 when it was a collision, 3 otherwise."""
    return EXIT_COLLISION if (reason or "").startswith("collision") else EXIT_FAILSAFE


@dataclass
class Outcome:
    """How the run ended: exit code, why, and the control loop (its counters and timings)."""

    code: int
    reason: str
    loop: ControlLoop | None


class Daemon:
    """``make_loop(aio)`` builds the ControlLoop once the event loop exists; ``first_plan(state)``
    plans the first reference (may take a second); ``closers``: callables run at shutdown, in order
    (workers, telemetry, recorder), each bounded in time by its own implementation; ``clock``: the
    monotonic clock (ns) that time-outs, holds and stalls are judged on (the control loop's)."""

    def __init__(self, platform: PlatformBase, make_loop, *, first_plan=None, workers=None, closers=(),
                 notifier: SystemdNotifier | None = None, telemetry=None, monitor_s: float = 0.05,
                 stop_after_s: float | None = None, clock=time.monotonic_ns) -> None:
        self.platform, self.make_loop, self.first_plan = platform, make_loop, first_plan
        self.workers, self.closers = workers, list(closers)
        self.notifier = notifier or SystemdNotifier.from_env()
        self.telemetry, self.monitor_s, self.stop_after_s = telemetry, monitor_s, stop_after_s
        self.clock = clock
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

    def _now_s(self) -> float:
        return self.clock() * 1e-9

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
            return await self._end(loop, Outcome(EXIT_ERROR, reason, loop), started=False)
        if self._signal:
            return await self._end(loop, Outcome(EXIT_OK, self._signal, loop), started=False)
        prepares = self.platform.prepares
        if prepares:                        # e.g. the quadrotor arms and takes off to the route's start
            self.notifier.status("preparing the platform")
            try:
                if await self._unless_stopped(self.platform.prepare()):
                    first = await self._first_state(policy.connect_timeout, after_ns=self.clock())
            except Exception as exc:
                reason = f"platform preparation failed: {type(exc).__name__}: {exc}"
                log.error("event=prepare_failed reason=%s", reason)
                return await self._end(loop, Outcome(EXIT_ERROR, reason, loop), started=False, prepared=True)
            if self._signal:
                return await self._end(loop, Outcome(EXIT_OK, self._signal, loop), started=False, prepared=True)
        self.notifier.status("planning the first reference")
        try:
            if self.first_plan is not None:
                await aio.run_in_executor(None, self.first_plan, first.state)
        except (GuidanceError, ValueError) as exc:     # e.g. the vehicle starts inside an obstacle
            reason = f"no first plan from the vehicle's state: {exc}"
            log.error("event=first_plan_failed reason=%s", reason)
            return await self._end(loop, Outcome(EXIT_BAD_INPUT, reason, loop), started=False,
                                   prepared=prepares)
        try:
            if self.workers is not None:
                await aio.run_in_executor(None, self.workers.start)
            await self.platform.enable()
        except Exception as exc:
            reason = f"start-up failed: {type(exc).__name__}: {exc}"
            log.exception("event=startup_failed")
            return await self._end(loop, Outcome(EXIT_ERROR, reason, loop), started=False,
                                   prepared=prepares)
        loop.start()
        if self.stop_after_s is not None:
            aio.call_later(self.stop_after_s, self.request_stop, f"ran {self.stop_after_s:g} s")
        loop.event("started", rate_hz=loop.cfg.rate_hz, controller=loop.controller.name,
                   realtime=loop.cfg.sched_fifo)
        self.notifier.ready()
        loop.event("ready")
        return await self._end(loop, await self._monitor(loop), started=True)

    async def _unless_stopped(self, coro) -> bool:
        """Run ``coro`` to its end (True), or cancel it when a stop is requested first (False)."""
        task = asyncio.ensure_future(coro)
        stop = asyncio.ensure_future(self._wake.wait())
        try:
            await asyncio.wait({task, stop}, return_when=asyncio.FIRST_COMPLETED)
        finally:
            stop.cancel()
        if task.done():
            task.result()
            return True
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
        return False

    async def _first_state(self, timeout_s: float, after_ns: int = 0):
        """The platform's first state (stamped at or after ``after_ns``)."""
        deadline = self._now_s() + timeout_s
        while True:
            s = self.platform.latest_state()
            if s is not None and s.stamp_ns >= after_ns:
                return s
            if self._signal:
                return None
            if self._now_s() > deadline:
                raise asyncio.TimeoutError("no state received")
            await asyncio.sleep(0.01)

    async def _monitor(self, loop: ControlLoop) -> Outcome:
        period_ns = loop.rate.period_ns
        pet_s = self.notifier.watchdog_period_s
        next_pet = next_status = self._now_s()
        while True:
            try:
                await asyncio.wait_for(self._wake.wait(), self.monitor_s)
            except asyncio.TimeoutError:
                pass
            if self._signal:
                if loop.mode == FAILSAFE:        # latched before the stop request: it stays the outcome
                    return Outcome(failsafe_exit(loop.reason), f"{loop.reason or 'failsafe'} (then {self._signal})", loop)
                return Outcome(EXIT_OK, self._signal, loop)
            now_ns = self.clock()
            stall = loop.monitor.stalled(now_ns, loop.last_tick_ns)
            if stall is not None and loop.mode == RUNNING:
                loop.trip(stall)
            on_time = now_ns - loop.last_tick_ns <= max(3 * period_ns, int(0.05e9))
            now = self._now_s()
            if pet_s is not None and on_time and now >= next_pet:
                self.notifier.watchdog()
                next_pet = now + pet_s / 2
            if now >= next_status:
                next_status = now + 1.0
                self._health(loop)
            if loop.mode in (FAILSAFE, COMPLETE) and loop.ended_ns is not None:
                held = (now_ns - loop.ended_ns) * 1e-9
                if held >= loop.policy.hold or (loop.mode == COMPLETE and self._at_rest() and held >= 0.5):
                    if loop.mode == COMPLETE:
                        return Outcome(EXIT_OK, "mission_complete", loop)
                    return Outcome(failsafe_exit(loop.reason), loop.reason or "failsafe", loop)

    def _health(self, loop: ControlLoop) -> None:
        c, status = loop.counters, loop.controller.status()
        health = {"mode": loop.mode, "t": round(loop.mission_time(self.clock()), 3), "ticks": c.ticks,
                  "overruns": c.overruns, "skipped": loop.rate.skipped,
                  "lateness_p99_ms": round(c.lateness.recent_percentile(99) * 1e3, 3),
                  "compute_p99_ms": round(c.compute.recent_percentile(99) * 1e3, 3),
                  "replans": status.replans, "replan_failures": status.replan_failures,
                  "stale_replans": status.stale_replans, "refits": status.refits,
                  "worker_errors": c.worker_errors, "send_errors": c.send_errors, "fallbacks": status.fallbacks,
                  "progress_m": round(loop.progress.covered, 1) if loop.progress is not None else None,
                  "reason": loop.reason}
        self.notifier.status(f"{loop.mode} t={health['t']:.1f}s ticks={c.ticks} overruns={c.overruns} "
                             f"late_p99={health['lateness_p99_ms']:.2f}ms compute_p99={health['compute_p99_ms']:.2f}ms")
        if self.telemetry is not None:
            self.telemetry.offer_health(health)

    async def _end(self, loop: ControlLoop, outcome: Outcome, *, started: bool, prepared: bool = False) -> Outcome:
        """Shut down; a vehicle not at rest in time turns the outcome into exit code 4."""
        failure = await self._shutdown(loop, started=started, reason=outcome.reason, prepared=prepared)
        if failure is None:
            return outcome
        return Outcome(EXIT_NOT_AT_REST, f"{outcome.reason}; {failure}", loop)

    async def _shutdown(self, loop: ControlLoop, *, started: bool, reason: str = "",
                        prepared: bool = False) -> str | None:
        """Safe stop: stop commanding, the platform's safe action, the wait until the vehicle is at
        rest (``_come_to_rest``), then close all (about 2 s). ``prepared``: the platform was
        prepared (e.g. is flying) though the loop never started. Returns None, or why the vehicle
        is not at rest."""
        self.notifier.stopping()
        since_ns = self.clock()
        if prepared and not started:
            await self._bounded(self.platform.failsafe(f"shutdown: {reason}"), 0.5)
        if started:
            if loop.mode == RUNNING:
                loop.mode = STOPPING
                await self._bounded(self.platform.failsafe(f"shutdown: {reason}"), 0.5)
            elif loop.ended_ns is not None:          # failsafe or mission complete: its safe action runs
                since_ns = loop.ended_ns
        failure = await self._come_to_rest(loop, since_ns) if started or prepared else None
        if started:
            loop.event("stopping", reason=reason if failure is None else f"{reason}; {failure}")
            loop.stop(0.5)
        await self._bounded(self.platform.close(), 0.5)
        if started:                             # after the close: every frame the link sent, the hand-back too
            link_stats = self.platform.link_stats()
            if link_stats:
                loop.event("link_stats", **link_stats)
        for close in self.closers:
            try:
                close()
            except Exception:                  # shutdown must go on
                log.exception("event=close_failed")
        return failure

    def _at_rest(self) -> bool | None:
        """The platform's ``at_rest`` (landed and disarmed / standing still); None: it cannot tell."""
        value = self.platform.at_rest
        return None if value is None else bool(value)

    async def _come_to_rest(self, loop: ControlLoop, since_ns: int) -> str | None:
        """Wait until the platform reports the vehicle at rest, at most ``failsafe.land_timeout``
        (aerial) or ``failsafe.brake_timeout`` (ground) after ``since_ns`` (the start of the safe
        action). The event loop runs the safe action meanwhile, so WATCHDOG=1 goes on, and the
        control thread keeps recording. Returns None when at rest (or the platform cannot tell),
        else why not (also logged as ``rest_timeout``)."""
        if self._at_rest() is None:
            return None
        aerial = "Z" in self.platform.state_names
        setting, timeout_s = loop.policy.rest_timeout(aerial)
        what, phrase = ("landed", "landed") if aerial else ("standstill", "at a standstill")
        deadline_ns = since_ns + int(timeout_s * 1e9)
        self.notifier.status(f"stopping: waiting until the vehicle is {phrase} (failsafe.{setting} = {timeout_s:g} s)")
        pet_s = self.notifier.watchdog_period_s
        next_pet = next_status = 0.0
        while not self._at_rest():
            now_ns, now = self.clock(), self._now_s()
            if now_ns >= deadline_ns:
                motion = self._motion()
                where = ", ".join(f"{k.split('_')[0]}={v:.2f} {'m' if k == 'z_m' else 'm/s'}"
                                  for k, v in motion.items()) or "no state"
                log.error("event=rest_timeout setting=%s timeout_s=%g %s", setting, timeout_s,
                          " ".join(f"{k}={v:.3f}" for k, v in motion.items()))
                loop.event("rest_timeout", setting=setting, timeout_s=timeout_s, **motion)
                return f"the vehicle was not {phrase} within failsafe.{setting} = {timeout_s:g} s ({where})"
            if pet_s is not None and now >= next_pet:
                self.notifier.watchdog()
                next_pet = now + pet_s / 2
            if now >= next_status:
                next_status = now + 1.0
                self._health(loop)
            await asyncio.sleep(min(self.monitor_s, (deadline_ns - now_ns) * 1e-9))
        rest_ns = self.clock()
        loop.event("at_rest", what=what, waited_s=round((rest_ns - since_ns) * 1e-9, 2))
        if loop.t0_ns is not None:
            await self._recorded_after(loop, rest_ns)
        return None

    async def _recorded_after(self, loop: ControlLoop, since_ns: int) -> None:
        """Wait (at most 5 control periods) until the control thread has recorded a tick that began
        after a state stamped at or after ``since_ns``, so that the flight log ends at rest."""
        period_ns = loop.rate.period_ns
        deadline_ns, fresh_ns = since_ns + 5 * period_ns, None
        while (now_ns := self.clock()) < deadline_ns:
            s = self.platform.latest_state()
            if fresh_ns is None and s is not None and s.stamp_ns >= since_ns:
                fresh_ns = now_ns
            if fresh_ns is not None and loop.last_tick_ns >= fresh_ns + period_ns:
                return
            await asyncio.sleep(period_ns * 0.25e-9)

    def _motion(self) -> dict:
        """The vehicle's last height (``z_m``, aerial) and speed (``speed_m_s``); empty without a state."""
        s = self.platform.latest_state()
        if s is None:
            return {}
        names, x = list(self.platform.state_names), s.state
        out = {"z_m": float(x[names.index("Z")])} if "Z" in names else {}
        out["speed_m_s"] = sum(float(x[names.index(n)]) ** 2 for n in ("vx", "vy", "vz") if n in names) ** 0.5
        return out

    @staticmethod
    async def _bounded(coro, timeout_s: float) -> None:
        try:
            await asyncio.wait_for(coro, timeout_s)
        except asyncio.TimeoutError:
            log.warning("event=shutdown_step_timeout timeout_s=%.1f", timeout_s)
        except Exception as exc:
            log.warning("event=shutdown_step_failed reason=%s", exc)
