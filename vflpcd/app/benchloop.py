"""``vflpcd bench loop``: the daemon's fixed-rate loop measured under load.

Runs a mission (default ``config/missions/bench_loop.toml``: VF-LPC with the online GP on the
closed racing track, the in-process plant, a guidance refresh and a GP refit check every second,
telemetry on) at ``rate`` Hz for ``duration`` seconds through the real daemon, with a live Zenoh
subscriber counting the telemetry it receives; then reads the flight log and prints the start
lateness and compute histograms (compute: ``controller.step``, the command's latency), the
controller's ``settle`` after the command and the tick's whole work, the counts that the acceptance
asks for (ticks whose compute exceeded the period, p99 start lateness), and the worker activity.
Writes JSON and PNG.

Before the daemon, in the same run, an empty loop ticks for ``baseline`` seconds at the same
rate, with the same rate keeper and scheduling: how late the machine itself starts a thread that
does nothing (a virtual machine's host can hold a vCPU for several milliseconds). Its ticks
started a period or more late are overruns that no work in the tick could avoid.

The host's holds come and go, so the baseline minute need not see those of the daemon's minute:
beside both runs the machine's steal counter is sampled (``steal.StealSampler``), and the bench
prints the share of CPU time the host took and how many of the late ticks and overruns began
while it was taking some (within a sampling period). The acceptance counts stay those of every
tick; the split only says where to look.
"""

from __future__ import annotations

import json
import threading
from dataclasses import replace
from pathlib import Path

import numpy as np

from vflpcd.app.steal import StealSampler
from vflpcd.base.paths import config_dir

EDGES_MS = (0.0, 0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 3.0, 5.0, 10.0, np.inf)


def histogram(values_ms: np.ndarray) -> list[tuple[str, int]]:
    counts, _ = np.histogram(values_ms, bins=np.array(EDGES_MS))
    labels = [f"{a:g}-{b:g} ms" if np.isfinite(b) else f">= {a:g} ms" for a, b in zip(EDGES_MS[:-1], EDGES_MS[1:])]
    return list(zip(labels, counts.tolist()))


class TelemetryCounter:
    """A second Zenoh session that counts the messages of each telemetry topic."""

    def __init__(self, vehicle_id: str, endpoint: str) -> None:
        import zenoh

        cfg = zenoh.Config()
        cfg.insert_json5("mode", '"peer"')
        cfg.insert_json5("connect/endpoints", json.dumps([endpoint]))
        cfg.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(cfg)
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self.sub = self.session.declare_subscriber(f"vflpc/{vehicle_id}/**", self._on)

    def _on(self, sample) -> None:
        topic = str(sample.key_expr).rsplit("/", 1)[-1]
        with self._lock:
            self.counts[topic] = self.counts.get(topic, 0) + 1

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def empty_loop(rate_hz: float, duration_s: float, sched_fifo: bool, priority: int) -> dict:
    """Start lateness of a thread that does nothing at ``rate_hz`` for ``duration_s``, with the
    daemon's rate keeper and (with ``sched_fifo``, where permitted) its SCHED_FIFO ``priority``:
    percentiles in ms, the ticks started more than 2 ms and a period or more late."""
    from vflpcd.daemon.ratekeeper import RateKeeper, set_realtime

    period_s = 1.0 / rate_hz
    late: list[int] = []
    realtime: list[bool] = []

    def run() -> None:
        realtime.append(set_realtime(priority) if sched_fifo else False)
        rate = RateKeeper(period_s)
        end = rate.start() + int(duration_s * 1e9)
        while True:
            tick = rate.wait()
            if tick.deadline_ns >= end:
                break
            late.append((tick.start_ns, tick.lateness_ns))

    thread = threading.Thread(target=run, name="empty-loop")
    steal = StealSampler().start()
    thread.start()
    thread.join()
    steal.stop()
    starts, lateness = np.array(late, dtype=np.int64).reshape(-1, 2).T
    ms = lateness * 1e-6
    return {"duration_s": duration_s, "sched_fifo": bool(realtime and realtime[0]), "ticks": len(ms),
            "lateness_p50_ms": float(np.percentile(ms, 50)), "lateness_p99_ms": float(np.percentile(ms, 99)),
            "lateness_max_ms": float(ms.max()), "late_over_2ms": int(np.sum(ms > 2.0)),
            "late_a_period": int(np.sum(ms >= period_s * 1e3)),
            "steal": steal_figures(steal, starts, ms > 2.0, ms >= period_s * 1e3)}


def steal_figures(steal: StealSampler, starts_ns: np.ndarray, late: np.ndarray, overrun: np.ndarray) -> dict | None:
    """The host's steal beside a run: its share of the CPU time, and of the ticks started at
    ``starts_ns`` the ``late`` ones (more than 2 ms) and the ``overrun`` ones that began while the
    host was taking CPU time (``StealSampler.stolen_near``), and the fraction of all its ticks
    that did (what chance alone would put there); None where it is not sampled."""
    near = steal.stolen_near(starts_ns)
    if near is None:
        return None
    return {"share": steal.share(), "ticks_while_stolen": float(np.mean(near)) if len(near) else 0.0,
            "late_over_2ms_while_stolen": int(np.sum(late & near)), "overruns_while_stolen": int(np.sum(overrun & near))}


def bench_loop(mission_path: Path | None, rate_hz: float, duration_s: float, executor: str | None, out: Path,
               baseline_s: float | None = None) -> int:
    """The bench (module docstring); ``baseline_s``: the empty loop's seconds (None: ``duration_s``,
    0: none). 0 when no tick's compute exceeded the period and the p99 start lateness is at most
    2 ms, else 1."""
    from vflpcd.log.reader import read_flight_log
    from vflpcd.config.mission import load_mission
    from vflpcd.app.run import run_mission

    baseline_s = duration_s if baseline_s is None else baseline_s
    mission = load_mission(mission_path or config_dir() / "missions" / "bench_loop.toml")
    if executor is not None:
        mission = replace(mission, workers=replace(mission.workers, executor=executor))
    out.mkdir(parents=True, exist_ok=True)
    machine = (empty_loop(rate_hz, baseline_s, mission.loop.sched_fifo, mission.loop.priority)
               if baseline_s > 0 else None)
    counter: list[TelemetryCounter] = []
    if mission.telemetry.enabled and mission.telemetry.listen:   # subscribe once the daemon listens
        timer = threading.Timer(3.0, lambda: counter.append(
            TelemetryCounter(mission.vehicle_id, mission.telemetry.listen[0])))
        timer.start()
    else:
        timer = None
    steal = StealSampler().start()
    try:
        result = run_mission(mission, rate_hz=rate_hz, log_dir=out / "logs", stop_after_s=duration_s)
    finally:
        steal.stop()
        if timer is not None:
            timer.cancel()
    counts = dict(counter[0].counts) if counter else {}
    for c in counter:
        c.close()
    log = read_flight_log(result.log_path)
    period_ms = 1e3 / rate_hz
    running = log.compute_s > 0
    timed = log.mode == "running"                 # the timed run, not the braking to rest after it
    late = log.lateness_s[timed] * 1e3
    comp = log.compute_s[running & timed] * 1e3
    loop = result.outcome.loop
    figures = {
        "rate_hz": rate_hz, "duration_s": duration_s, "executor": mission.workers.executor,
        "ticks": int(np.sum(timed)), "outcome": result.outcome.reason,
        "compute_over_period": int(np.sum(comp > period_ms)),
        "lateness_p50_ms": float(np.percentile(late, 50)), "lateness_p99_ms": float(np.percentile(late, 99)),
        "lateness_max_ms": float(late.max()), "late_over_2ms": int(np.sum(late > 2.0)),
        "compute_p50_ms": float(np.percentile(comp, 50)), "compute_p99_ms": float(np.percentile(comp, 99)),
        "compute_max_ms": float(comp.max()), "overruns": int(np.sum(log.overrun[timed])),
        "settle_p50_ms": loop.counters.settle.percentile(50) * 1e3 if loop is not None else None,
        "settle_p99_ms": loop.counters.settle.percentile(99) * 1e3 if loop is not None else None,
        "work_p50_ms": loop.counters.work.percentile(50) * 1e3 if loop is not None else None,
        "work_p99_ms": loop.counters.work.percentile(99) * 1e3 if loop is not None else None,
        "skipped": int(loop.rate.skipped) if loop is not None else None,
        "replans": len(loop.workers.latencies["replan"]) if loop and loop.workers else None,
        "refits": len(loop.workers.latencies["refit"]) if loop and loop.workers else None,
        "replan_latency_max_s": max(loop.workers.latencies["replan"], default=0.0) if loop and loop.workers else None,
        "refit_latency_max_s": max(loop.workers.latencies["refit"], default=0.0) if loop and loop.workers else None,
        "telemetry_messages": counts, "machine_baseline": machine,
        "steal": steal_figures(steal, log.stamp_ns[timed], late > 2.0, log.overrun[timed]),
        "lateness_histogram": histogram(late), "compute_histogram": histogram(comp),
        "log": str(result.log_path),
    }
    _print(figures)
    (out / "bench_loop.json").write_text(json.dumps(figures, indent=2))
    from vflpcd.log.plot import plot_flight_log

    png = plot_flight_log(log, out / "bench_loop.png")
    print(f"wrote {out / 'bench_loop.json'}\nwrote {png}")
    ok = figures["compute_over_period"] == 0 and figures["lateness_p99_ms"] <= 2.0
    return 0 if ok else 1


def _print(f: dict) -> None:
    print(f"loop at {f['rate_hz']:g} Hz for {f['duration_s']:g} s ({f['executor']} workers): {f['ticks']} ticks, "
          f"ended: {f['outcome']}")
    print(f"{'bin':>14} {'start lateness':>15} {'compute':>9}")
    for (label, a), (_, b) in zip(f["lateness_histogram"], f["compute_histogram"]):
        print(f"{label:>14} {a:>15} {b:>9}")
    print(f"start lateness p50 / p99 / max   {f['lateness_p50_ms']:.4f} / {f['lateness_p99_ms']:.4f} / "
          f"{f['lateness_max_ms']:.4f} ms")
    print(f"compute p50 / p99 / max          {f['compute_p50_ms']:.3f} / {f['compute_p99_ms']:.3f} / "
          f"{f['compute_max_ms']:.3f} ms")
    if f["settle_p50_ms"] is not None:
        print(f"after the command: the controller's settle p50 / p99 {f['settle_p50_ms']:.3f} / "
              f"{f['settle_p99_ms']:.3f} ms; the tick's whole work p50 / p99 {f['work_p50_ms']:.3f} / "
              f"{f['work_p99_ms']:.3f} ms")
    print(f"overruns {f['overruns']}, skipped deadlines {f['skipped']}, replans {f['replans']} "
          f"(longest {f['replan_latency_max_s']:.3f} s), GP refits {f['refits']} "
          f"(longest {f['refit_latency_max_s']:.3f} s)")
    print(f"telemetry received by a live subscriber: {f['telemetry_messages']}")
    print(f"the host's steal beside the daemon: {_steal(f['steal'], f['late_over_2ms'], f['overruns'], 'overruns')}")
    m = f["machine_baseline"]
    if m is not None:
        print(f"the machine alone (an empty loop at {f['rate_hz']:g} Hz for {m['duration_s']:g} s before the daemon, "
              f"{'SCHED_FIFO' if m['sched_fifo'] else 'not real-time'}): start lateness p50 / p99 / max "
              f"{m['lateness_p50_ms']:.4f} / {m['lateness_p99_ms']:.4f} / {m['lateness_max_ms']:.4f} ms, "
              f"{m['late_over_2ms']} ticks more than 2 ms late, {m['late_a_period']} a period or more late; "
              f"steal: {_steal(m['steal'], m['late_over_2ms'], m['late_a_period'], 'a period or more late')}")
    print(f"ticks whose compute exceeded the period: {f['compute_over_period']}   "
          f"{'PASS' if f['compute_over_period'] == 0 else 'FAIL'}")
    print(f"p99 start lateness <= 2 ms: {f['lateness_p99_ms']:.4f} ms   "
          f"{'PASS' if f['lateness_p99_ms'] <= 2.0 else 'FAIL'}")


def _steal(st: dict | None, late: int, overruns: int, what: str) -> str:
    """One line of ``steal_figures``' figures for a run with ``late`` ticks more than 2 ms late and
    ``overruns`` ticks counted as ``what``."""
    if st is None:
        return "not sampled (no /proc/stat)"
    return (f"{100.0 * st['share']:.2f} % of the CPU time; of the {late} ticks more than 2 ms late "
            f"{st['late_over_2ms_while_stolen']}, of the {overruns} {what} {st['overruns_while_stolen']} "
            f"began while the host was taking CPU time (as did {100.0 * st['ticks_while_stolen']:.1f} % of all ticks)")
