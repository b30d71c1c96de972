"""The end-of-run summary of ``vflpcd run``, computed from its flight log and the mission's route:
outcome, timing of the fixed-rate loop, worker activity, events, and the least clearance to every
obstacle (the vehicle's exact footprint against each obstacle's recorded position)."""

from __future__ import annotations

import numpy as np

from vflpcd.log.reader import FlightLog


def clearances(log: FlightLog, scenario) -> dict[str, float]:
    """Least body clearance (m, negative: contact) to each obstacle over the ticks with a state."""
    from vflpcd.core.shapes import Circle, Sphere

    names = log.header.state_names
    idx = [names.index(n) for n in ("X", "Y", "Z")[: scenario.dim]]
    yaw_i = names.index("psi") if "psi" in names else None
    shapes = {o.id: (o.shape, o.yaw) for o in scenario.obstacles}
    out: dict[str, float] = {}
    ok = np.all(np.isfinite(log.state), axis=1)
    for oid, centres in log.obstacles.items():
        shape, yaw = shapes.get(oid, ((Sphere if scenario.dim == 3 else Circle)(log.obstacle_radius[oid]), 0.0))
        rows = np.flatnonzero(ok & np.all(np.isfinite(centres), axis=1))
        if len(rows) == 0:
            continue
        # coarse pass with bounding circles, exact footprint only near the closest approach
        d = np.linalg.norm(log.state[rows][:, idx] - centres[rows], axis=1)
        near = rows[d <= d.min() + 3.0]
        out[oid] = min(scenario.footprint.clearance(shape, centres[i], yaw, log.state[i, idx],
                                                    float(log.state[i, yaw_i]) if yaw_i is not None else 0.0)
                       for i in near)
    return out


def touched_obstacles(clear: dict[str, float]) -> list[str]:
    """The obstacles whose least clearance is contact (<= 0), from ``clearances``."""
    return [oid for oid, gap in clear.items() if gap <= 0.0]


KILLED = "no closing record (the writer was killed or the process died)"


def run_span(outcome) -> tuple[int, float] | None:
    """(ticks, seconds) the daemon ran, from the outcome's control loop; None without one."""
    loop = outcome.loop if outcome is not None else None
    if loop is None or loop.t0_ns is None:
        return None
    return loop.counters.ticks, loop.mission_time(loop.last_tick_ns)


def log_stop_line(log: FlightLog, run: tuple[int, float] | None = None, stop_reason: str | None = None) -> str | None:
    """When and why the log stopped before the end of the run, None when it did not: e.g. "stopped
    at 13.60 s of a 40.20 s run: disk full (ENOSPC)". ``run``: the daemon's ``run_span``;
    ``stop_reason``: the recorder's own account (``FlightRecorder.stop_reason``), which comes
    before the log's ``log_stopped`` event; without either the writer was killed."""
    if not log.truncated and stop_reason is None:
        return None
    of_run = f" of a {run[1]:.2f} s run" if run is not None else ""
    return f"stopped at {log.logged_s:.2f} s{of_run}: {stop_reason or log.stop_reason or KILLED}"


def summary_lines(log: FlightLog, scenario, outcome=None, stop_reason: str | None = None) -> list[str]:
    """The summary as aligned ``label value`` lines; ``stop_reason``: the recorder's, when the run
    wrote the log in this process (``log_stop_line``)."""
    period = 1.0 / log.header.rate_hz
    stepped = log.compute_s > 0
    late, comp = log.lateness_s * 1e3, log.compute_s[stepped] * 1e3
    lines = []

    def add(label: str, value: str) -> None:
        lines.append(f"{label:<28} {value}")

    if outcome is not None:
        add("outcome", f"{outcome.reason} (exit code {outcome.code})")
    add("vehicle / platform", f"{log.header.vehicle_id} / {log.header.platform} ({log.header.controller})")
    run = run_span(outcome)
    stopped = log_stop_line(log, run, stop_reason)
    if stopped is not None and run is not None:
        add("ticks", f"{run[0]} at {log.header.rate_hz:g} Hz over {run[1]:.2f} s "
                     f"({len(log)} logged, to {log.logged_s:.2f} s)")
    else:
        add("ticks", f"{len(log)} at {log.header.rate_hz:g} Hz over {log.logged_s:.2f} s")
    if len(log):
        add("start lateness p50/p99/max", f"{np.percentile(late, 50):.3f} / {np.percentile(late, 99):.3f} / "
                                          f"{late.max():.3f} ms")
    if comp.size:
        add("compute p50/p99/max", f"{np.percentile(comp, 50):.3f} / {np.percentile(comp, 99):.3f} / "
                                   f"{comp.max():.3f} ms (period {period * 1e3:g} ms)")
        add("compute over the period", f"{int(np.sum(comp > period * 1e3))}")
    add("overruns", f"{int(np.sum(log.overrun))}")
    if len(log):
        add("plans / GP models", f"{int(log.plan_version.max())} / {int(log.model_version.max())}")
    kinds = [e.kind for e in log.events]
    brakes = [e for e in log.events if e.kind == "supervisor_brake"]
    add("supervisor interventions", f"{len(brakes)}" + (f" (first at t={brakes[0].t:.2f} s: "
                                                         f"{brakes[0].detail.get('reason', '')})" if brakes else "")[:160])
    for kind in ("failsafe", "replan_failed", "worker_error"):
        if kind in kinds:
            first = next(e for e in log.events if e.kind == kind)
            add(kind, f"{kinds.count(kind)} (first at t={first.t:.2f} s: {first.detail.get('reason', '')})"[:160])
    for kind, what in (("perception_rejected", "reason"), ("perception_dropped", "budget_hz")):
        reports = [e for e in log.events if e.kind == kind]     # aggregated: the last one has the total
        if reports:
            last = reports[-1].detail
            add(kind, f"{last.get('total', len(reports))} messages ({what} {last.get(what, '')})"[:160])
    link = next((e.detail for e in log.events if e.kind == "link_stats"), None)
    if link:
        add("platform link", ", ".join(f"{k} {v}" for k, v in link.items())[:200])
    clear = clearances(log, scenario)
    if clear:
        worst = min(clear, key=clear.get)
        add("min clearance", f"{clear[worst]:.2f} m ({worst})")
        touched = touched_obstacles(clear)
        add("collisions", f"{len(touched)} obstacles touched" + (f" ({', '.join(touched)})" if touched else ""))
    if stopped is not None:
        add("log", stopped)
    add("log file", str(log.path))
    return lines
