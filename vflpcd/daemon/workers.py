"""Guidance and model workers: replans and GP refits off the control thread.

Two single-worker executors (guidance, model), processes by default (``kind="process"``: the
jobs are pure Python for hundreds of milliseconds, and in a thread they would hold the GIL
against the control thread) or threads (``kind="thread"``). The guidance planner is handed to
each worker once, at start-up, by the executor's initializer; a job carries only its inputs
(``vflpcd.core.vflpc.ReplanJob`` / ``RefitJob``). At most one job of each kind is in flight.

Hand-over: a finished job's outcome is appended to a deque by the executor's callback (one
atomic append, never blocking); the control thread ``collect()``s them between ticks and
installs them in the controller there, so a result is taken whole between two ticks. A slow
worker never stalls a tick; a failing job is reported as a ``Finished`` with its error; a worker
process that dies breaks its pool, which is rebuilt on the next submit.

A worker process dies with the daemon, however the daemon ends (SIGKILL included): its
initializer starts ``lifeline.watch`` on the daemon's pid. The multiprocessing resource tracker
then ends too: it exits when the last holder of its pipe's write end (the daemon and each worker,
which inherits it at spawn) is gone. ``PR_SET_PDEATHSIG`` is not used here: the kernel ties it to
the thread that started the process, and a pool's process is started by whichever thread submits
to it first (an event-loop executor thread, the control thread after a rebuild).
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import threading
import time
from collections import deque
from concurrent.futures import Executor, ProcessPoolExecutor, ThreadPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

from vflpcd.daemon import lifeline

log = logging.getLogger("vflpcd.daemon.workers")

_PLANNER = None      # the guidance planner of this worker (set by the initializer)


WORKER_NICE = 2      # workers yield to the control thread (CFS weight 655 against 1024), not to every process


def _init_worker(planner, parent_pid: int | None = None) -> None:
    global _PLANNER
    _PLANNER = planner
    try:
        os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WORKER_NICE)   # this thread / process
    except OSError as exc:
        log.warning("event=worker_nice_failed reason=%s", exc)
    if multiprocessing.current_process().name != "MainProcess":
        signal.signal(signal.SIGINT, signal.SIG_IGN)   # the daemon shuts its workers down itself
        if parent_pid is not None:
            lifeline.watch(parent_pid)                 # its thread inherits the nice value set above


def _run_replan(job):
    from vflpcd.core.jobs import run_replan

    return run_replan(_PLANNER, job)


def _run_refit(job):
    from vflpcd.core.jobs import run_refit

    return run_refit(job)


def _warm_up() -> bool:
    import vflpcd.core.jobs  # noqa: F401  (imports the planning code once, before the first job)

    if _PLANNER is not None:
        _PLANNER.warm()      # and loads its compiled loops
    return True


@dataclass(frozen=True)
class Finished:
    """A job's outcome: kind ("replan" | "refit"), the job, its result or its error, seconds from
    submit to completion."""

    kind: str
    job: object
    result: object
    error: BaseException | None
    latency_s: float


class Workers:
    """The guidance and model workers of one controller."""

    KINDS = ("replan", "refit")

    def __init__(self, kind: str, planner) -> None:
        if kind not in ("process", "thread"):
            raise ValueError(f"worker kind must be process or thread, got {kind!r}")
        self.kind, self.planner = kind, planner
        self._executors: dict[str, Executor | None] = {k: None for k in self.KINDS}
        self._busy = {k: False for k in self.KINDS}
        self._done: deque[Finished] = deque()
        self.latencies: dict[str, list[float]] = {k: [] for k in self.KINDS}
        self.restarts = 0

    def _executor(self, which: str) -> Executor:
        ex = self._executors[which]
        if ex is None:
            if self.kind == "process":
                ex = ProcessPoolExecutor(max_workers=1, mp_context=multiprocessing.get_context("spawn"),
                                         initializer=_init_worker, initargs=(self.planner, os.getpid()))
            else:
                ex = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"worker-{which}",
                                        initializer=_init_worker, initargs=(self.planner,))
            self._executors[which] = ex
        return ex

    def start(self, timeout_s: float = 60.0) -> None:
        """Start both workers and wait until they have imported the planning code and loaded the
        planner's compiled loops (``PlannerBase.warm``)."""
        futures = [self._executor(k).submit(_warm_up) for k in self.KINDS]
        for f in futures:
            f.result(timeout=timeout_s)

    def busy(self, which: str) -> bool:
        return self._busy[which]

    def submit(self, which: str, job) -> bool:
        """Start a job of kind ``which`` unless one is in flight; True when started."""
        if self._busy[which]:
            return False
        fn = _run_replan if which == "replan" else _run_refit
        t0 = time.monotonic()
        try:
            future = self._executor(which).submit(fn, job)
        except (BrokenProcessPool, RuntimeError) as exc:     # a dead worker: rebuild and report
            self._rebuild(which, exc)
            self._done.append(Finished(which, job, None, exc, 0.0))
            return False
        self._busy[which] = True

        def done(f, which=which, job=job, t0=t0):
            err = f.exception()
            res = None if err is not None else f.result()
            self._done.append(Finished(which, job, res, err, time.monotonic() - t0))
        future.add_done_callback(done)
        return True

    def collect(self) -> list[Finished]:
        """The jobs finished since the last call (control thread, between ticks)."""
        out = []
        while self._done:
            f = self._done.popleft()
            self._busy[f.kind] = False
            if f.error is None:
                self.latencies[f.kind].append(f.latency_s)
            elif isinstance(f.error, BrokenProcessPool):
                self._rebuild(f.kind, f.error)
            out.append(f)
        return out

    def _rebuild(self, which: str, exc: BaseException) -> None:
        log.error("event=worker_lost worker=%s reason=%s action=restart", which, exc)
        ex, self._executors[which] = self._executors[which], None
        self.restarts += 1
        if ex is not None:
            ex.shutdown(wait=False, cancel_futures=True)

    def close(self) -> None:
        """Stop both workers without waiting for a running job (its result is dropped)."""
        for which, ex in self._executors.items():
            if ex is None:
                continue
            processes = list((ex._processes or {}).values()) if isinstance(ex, ProcessPoolExecutor) else []
            ex.shutdown(wait=False, cancel_futures=True)
            for p in processes:              # a long replan must not delay the exit
                if p.is_alive():
                    p.terminate()
            self._executors[which] = None
