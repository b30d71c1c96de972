"""The fixed-rate control task: one dedicated thread ("control") that ticks on absolute deadlines.

Every tick (``_tick``):
1. finished worker jobs are installed in the controller (a plan or a GP model, taken whole);
2. the platform's latest state is checked (link, age, finiteness: ``FailsafeMonitor``);
3. while running: the mission's and the perceived obstacles, ``controller.step`` (timed: compute),
   the command checked, passed through the safety guard (``vflpcd.core.safety``: the supervisor's
   collision check, which may replace it with the emergency manoeuvre, and the monitors of the plan,
   the tracking and the vehicle's response, any of which may trip the failsafe) and handed to the
   platform on the asyncio loop (never awaited here), then the controller's work that the command
   did not wait for (``controller.settle``: VF-LPC's GP sample; timed: settle);
4. the tick is recorded (flight log) and offered to telemetry (both non-blocking);
5. progress along the path: at the goal the vehicle is brought to rest (mission complete);
6. overrun accounting (the tick's work ran past the next deadline), due worker jobs submitted,
   garbage collected when there is slack.
A fault trips the failsafe: the platform's safe action is scheduled at once (it takes effect
within two ticks), the event is logged, and the loop keeps ticking without commanding, recording
what the vehicle does, until the daemon exits. The thread never awaits I/O and never blocks on
a worker.
"""

from __future__ import annotations

import asyncio
import logging
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.ports import ControllerBase, PlatformBase
from vflpcd.core.safety.guard import SafetyGuard
from vflpcd.daemon.config import FailsafePolicy, LoopConfig, WorkerConfig
from vflpcd.daemon.failsafe import FailsafeMonitor
from vflpcd.daemon.progress import Progress
from vflpcd.daemon.ratekeeper import ManualGC, RateKeeper, set_realtime
from vflpcd.log.records import Event, ObstacleRecord, TickRecord
from vflpcd.daemon.stats import TimingStats
from vflpcd.daemon.workers import Workers

log = logging.getLogger("vflpcd.daemon.control_loop")

RUNNING, FAILSAFE, COMPLETE, STOPPING = "running", "failsafe", "complete", "stopping"


@dataclass
class Sinks:
    """Where ticks and events go (each optional, each non-blocking): the flight recorder, the
    telemetry publisher, and a callback for events (the daemon's)."""

    recorder: object | None = None
    telemetry: object | None = None
    on_event: Callable[[Event], None] | None = None


@dataclass
class Counters:
    ticks: int = 0
    overruns: int = 0
    commands: int = 0
    send_errors: int = 0
    worker_errors: int = 0
    lateness: TimingStats = field(default_factory=TimingStats)
    compute: TimingStats = field(default_factory=TimingStats)
    work: TimingStats = field(default_factory=TimingStats)
    supervise: TimingStats = field(default_factory=TimingStats)
    settle: TimingStats = field(default_factory=TimingStats)


class ControlLoop:
    """The control thread of one mission.

    ``obstacles(t, state)``: the mission's obstacles at mission time t (list of ObstacleState);
    ``perception``: an object with ``snapshot(now_unix, t)`` or None; ``progress``: the path goal
    or None (then the mission runs until stopped); ``guard``: the safety guard every command passes
    (``vflpcd.config.safety.guard_for``), or None; ``clock``/``sleep``: the monotonic clock (ns) that
    deadlines, state ages, overruns and events are judged on, and how to wait on it.
    """

    def __init__(self, platform: PlatformBase, controller: ControllerBase, loop: LoopConfig,
                 workers_cfg: WorkerConfig, policy: FailsafePolicy, aio: asyncio.AbstractEventLoop, *,
                 obstacles: Callable[[float, np.ndarray], Sequence[ObstacleState]] = lambda t, x: (),
                 perception=None, progress: Progress | None = None, workers: Workers | None = None,
                 sinks: Sinks | None = None, guard: SafetyGuard | None = None,
                 clock: Callable[[], int] = time.monotonic_ns, sleep: Callable[[float], None] = time.sleep) -> None:
        self.platform, self.controller, self.cfg, self.wcfg = platform, controller, loop, workers_cfg
        self.aio = aio
        self.obstacles, self.perception, self.progress, self.workers = obstacles, perception, progress, workers
        self.sinks = sinks or Sinks()
        self.guard = guard
        self.n_u = len(platform.control_names)
        self.monitor = FailsafeMonitor(policy, len(platform.state_names))
        self.policy = policy
        self.clock = clock
        self.rate = RateKeeper(loop.period_s, clock=clock, sleep=sleep)
        self.gc = ManualGC(self.rate.period_ns) if loop.manual_gc else None
        self.mode = RUNNING
        self.reason: str | None = None
        self.counters = Counters()
        self.t0_ns: int | None = None
        self.last_tick_ns = clock()
        self.ended_ns: int | None = None          # when the vehicle was handed to its safe action
        self.failsafe_tick: int | None = None
        self.realtime = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._jobs = controller.jobs if workers is not None else None
        self._next_refresh = workers_cfg.replan_period if workers_cfg.replan_period > 0 else None
        self._next_refit = workers_cfg.refit_period

    # ------------------------------------------------------------------ life cycle
    def start(self) -> None:
        # A thread that wants the GIL waits until the holder's switch interval ends (5 ms by
        # default): bound that wait for the control thread to a tenth of the period.
        sys.setswitchinterval(min(sys.getswitchinterval(), self.cfg.period_s / 10))
        self.t0_ns = self.rate.start()
        self.last_tick_ns = self.t0_ns
        self._thread = threading.Thread(target=self._run, name="control", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 0.5) -> bool:
        """Ask the thread to end; True if it did within ``timeout_s`` (a hung step may not)."""
        self._stop.set()
        if self._thread is None:
            return True
        self._thread.join(timeout_s)
        return not self._thread.is_alive()

    def mission_time(self, now_ns: int) -> float:
        return (now_ns - self.t0_ns) * 1e-9 if self.t0_ns is not None else 0.0

    def _run(self) -> None:
        if self.cfg.sched_fifo:
            self.realtime = set_realtime(self.cfg.priority)
        if self.gc is not None:
            self.gc.start()
        try:
            while not self._stop.is_set():
                self.tick_once()
        except Exception as exc:                      # a bug in the loop itself: fail safe, then end
            log.exception("event=control_loop_error")
            self.trip(f"controller_error: control loop: {type(exc).__name__}: {exc}")
        finally:
            if self.gc is not None:
                self.gc.stop()

    # ------------------------------------------------------------------ one tick
    def tick_once(self) -> None:
        """Wait for the next deadline (``clock``/``sleep``) and run that tick, unless stopped meanwhile."""
        tick = self.rate.wait()
        if not self._stop.is_set():
            self._tick(tick)

    def _tick(self, tick) -> None:
        c = self.counters
        t = (tick.deadline_ns - self.t0_ns) * 1e-9
        c.lateness.add(tick.lateness_ns * 1e-9)
        self._install_finished(t)
        stamped = self.platform.latest_state()
        reason = self.monitor.check_state(stamped, tick.start_ns, self.platform.fault())
        state = np.asarray(stamped.state, dtype=float) if stamped is not None else None
        command, compute, obstacles = (), 0.0, ()
        if self.mode == RUNNING and reason is None:
            obstacles = list(self.obstacles(t, state))
            if self.perception is not None:
                obstacles += self.perception.snapshot(time.time(), t)
            c0 = time.perf_counter_ns()
            try:
                u = np.asarray(self.controller.step(state, t, obstacles), dtype=float)
                reason = self.monitor.check_command(u, self.n_u)
            except Exception as exc:
                reason = f"controller_error: {type(exc).__name__}: {exc}"
            compute = (time.perf_counter_ns() - c0) * 1e-9
            c.compute.add(compute)
            if reason is None and self.guard is not None:
                u, reason = self._supervise(t, state, u, obstacles)
            if reason is None:
                self._send(u)
                command = tuple(u.tolist())
                s0 = time.perf_counter_ns()
                try:
                    self.controller.settle()
                except Exception as exc:
                    reason = f"controller_error: {type(exc).__name__}: {exc}"
                c.settle.add((time.perf_counter_ns() - s0) * 1e-9)
        if reason is not None and self.mode == RUNNING:
            self.trip(reason)
        work_end = self.clock()
        c.work.add((work_end - tick.start_ns) * 1e-9)
        overrun = work_end > tick.deadline_ns + self.rate.period_ns
        c.overruns += overrun
        c.ticks += 1
        self._record(tick, t, state, stamped, command, compute, overrun, obstacles)
        if self.mode == RUNNING:
            streak = self.monitor.after_tick(overrun)
            if streak is not None:
                self.trip(streak)
            elif self.progress is not None and state is not None and self.progress.update(state):
                self._complete(t)
        if self.mode == RUNNING and self._jobs is not None:
            self._dispatch(t)
        self.last_tick_ns = self.clock()
        if self.gc is not None:
            self.gc.between_ticks(tick.deadline_ns + self.rate.period_ns - self.last_tick_ns)

    def _supervise(self, t: float, state: np.ndarray, u: np.ndarray, obstacles) -> tuple[np.ndarray, str | None]:
        """The guard's command for this tick and a failsafe reason (or None); interventions are events."""
        s0 = time.perf_counter_ns()
        route_error = self.progress.lateral if self.progress is not None else float("nan")
        gs = self.guard.step(t, state, u, obstacles, self.controller, route_error=route_error)
        self.counters.supervise.add((time.perf_counter_ns() - s0) * 1e-9)
        v = gs.verdict
        if v.engaged:
            self.event("supervisor_brake", reason=v.reason, obstacle=v.nearest, clearance_m=round(v.clearance, 3))
        elif v.released:
            self.event("supervisor_release", obstacle=v.nearest, clearance_m=round(v.clearance, 3))
        return gs.command, gs.trip

    def _send(self, u: np.ndarray) -> None:
        future = asyncio.run_coroutine_threadsafe(self.platform.send(u), self.aio)
        future.add_done_callback(self._sent)
        self.counters.commands += 1

    def _sent(self, future) -> None:
        if future.cancelled() or future.exception() is None:
            return
        self.counters.send_errors += 1
        log.warning("event=send_failed reason=%s", future.exception())

    def _record(self, tick, t, state, stamped, command, compute, overrun, obstacles) -> None:
        sinks = self.sinks
        if sinks.recorder is None and sinks.telemetry is None:
            return
        ctl = self.controller
        ref = ctl.reference_at(t) if self.mode == RUNNING else None
        status = ctl.status()
        rec = TickRecord(
            k=tick.k, t=t, stamp_ns=tick.start_ns, mode=self.mode,
            state=tuple(state.tolist()) if state is not None else (),
            state_age_s=(tick.start_ns - stamped.stamp_ns) * 1e-9 if stamped is not None else float("nan"),
            reference=tuple(ref.tolist()) if ref is not None else (), command=command,
            lateness_s=tick.lateness_ns * 1e-9, compute_s=compute, overrun=bool(overrun),
            threats=status.threats, plan_version=status.replans, model_version=status.refits,
            obstacles=tuple(ObstacleRecord(o.id, tuple(o.center_at(t).tolist()), tuple(np.asarray(o.velocity).tolist()),
                                           float(o.shape.bounding_radius()),
                                           "perception" if o.id.startswith("perception:") else "mission")
                            for o in obstacles))
        if sinks.recorder is not None:
            sinks.recorder.record_tick(rec)
        if sinks.telemetry is not None:
            sinks.telemetry.offer_tick(rec)

    # ------------------------------------------------------------------ failsafe and completion
    def trip(self, reason: str) -> None:
        """Hand the vehicle to its safe action (once): scheduled now, effective within two ticks."""
        if self.mode not in (RUNNING,):
            return
        self.mode, self.reason = FAILSAFE, reason
        self.failsafe_tick = self.counters.ticks
        self.ended_ns = self.clock()
        asyncio.run_coroutine_threadsafe(self.platform.failsafe(reason), self.aio)
        self.event("failsafe", reason=reason, action=self.platform.safe_action)

    def _complete(self, t: float) -> None:
        self.mode = COMPLETE
        self.ended_ns = self.clock()
        asyncio.run_coroutine_threadsafe(self.platform.failsafe("mission_complete"), self.aio)
        self.event("mission_complete", progress_m=round(self.progress.covered, 2))

    def event(self, kind: str, **detail) -> None:
        now = self.clock()
        ev = Event(t=self.mission_time(now), stamp_ns=now, kind=kind, detail=detail)
        log.log(logging.WARNING if kind in ("failsafe", "worker_error", "replan_failed", "supervisor_brake")
                else logging.INFO,
                "event=%s t=%.3f %s", kind, ev.t, " ".join(f"{k}={v}" for k, v in detail.items()))
        if self.sinks.recorder is not None:
            self.sinks.recorder.record_event(ev)
        if self.sinks.telemetry is not None:
            self.sinks.telemetry.offer_event(ev)
        if self.sinks.on_event is not None:
            self.sinks.on_event(ev)

    # ------------------------------------------------------------------ workers
    def _install_finished(self, t: float) -> None:
        if self._jobs is None:
            return
        ctl, c = self._jobs, self.counters
        for f in self.workers.collect():
            if f.kind == "replan":
                if f.error is None:
                    ctl.install_plan(f.job, f.result)
                    continue
                ctl.replan_failed(f.job, str(f.error))
                if isinstance(f.error, GuidanceError):
                    self.event("replan_failed", reason=str(f.error)[:200])
                    continue
            elif f.error is None:
                ctl.install_model(f.job, f.result)
                continue
            c.worker_errors += 1
            self.event("worker_error", job=f.kind, reason=f"{type(f.error).__name__}: {f.error}"[:200])

    def _dispatch(self, t: float) -> None:
        ctl, w = self._jobs, self.workers
        if not w.busy("replan"):
            force = None
            if self._next_refresh is not None and t >= self._next_refresh:
                force = t
                self._next_refresh = t + self.wcfg.replan_period
            job = ctl.take_replan(force_at=force)
            if job is not None:
                w.submit("replan", job)
        if t >= self._next_refit and not w.busy("refit"):
            self._next_refit = t + self.wcfg.refit_period
            job = ctl.take_refit()
            if job is not None:
                w.submit("refit", job)
