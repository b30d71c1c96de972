"""PNG of a flight log: map, tracking error, commands and tick timing (``vflpcd plot``).

Header obstacles are dicts; the keys read here are ``id``, ``outline`` ((n, 2) closed top-view
polygon), ``center`` (d,), ``velocity`` (d,) and ``radius`` (a circle is drawn when there is no
outline).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vflpcd.log.reader import FlightLog, read_flight_log
from vflpcd.log.summary import log_stop_line


def positions(log: FlightLog) -> np.ndarray:
    """(M, d) positions from the state columns named X, Y (and Z in 3-D); NaN where there was no
    state, or everywhere when the state has no such columns."""
    names = ("X", "Y", "Z")[: log.header.dim]
    if not all(n in log.header.state_names for n in names):
        return np.full((len(log), len(names)), np.nan)
    cols = [log.header.state_names.index(n) for n in names]
    return log.state[:, cols]


def plot_flight_log(log: FlightLog, out: str | Path) -> Path:
    """Write the log's figure to ``out`` (PNG) and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    pos = positions(log)
    fig = plt.figure(figsize=(13, 11), constrained_layout=True)
    grid = fig.add_gridspec(3, 2, height_ratios=[1.6, 1, 1])
    _draw_map(fig.add_subplot(grid[0, :]), log, pos)
    _draw_tracking(fig.add_subplot(grid[1, 0]), log, pos)
    _draw_commands(fig.add_subplot(grid[1, 1]), log)
    _draw_timing(fig.add_subplot(grid[2, 0]), log.lateness_s, log.header.rate_hz, "Tick start lateness")
    _draw_timing(fig.add_subplot(grid[2, 1]), log.compute_s, log.header.rate_hz, "Controller compute time")
    h = log.header
    duration = float(log.t[-1] - log.t[0]) if len(log) else 0.0
    fig.suptitle(f"{h.vehicle_id} ({h.platform}) / {h.controller} at {h.rate_hz:g} Hz: {len(log)} ticks, "
                 f"{duration:.1f} s, {int(log.overrun.sum())} overruns"
                 + (f", log {line}" if (line := log_stop_line(log)) else ""))
    fig.savefig(out, dpi=110)
    plt.close(fig)
    return out


def _draw_map(ax, log: FlightLog, pos: np.ndarray) -> None:
    h = log.header
    path = np.asarray(h.path, float).reshape(-1, h.dim) if h.path else np.zeros((0, h.dim))
    if len(path):
        ax.plot(path[:, 0], path[:, 1], color="k", lw=0.8, label="reference path")
    header_ids = set()
    for o in h.obstacles:
        oid = str(o.get("id", ""))
        header_ids.add(oid)
        xy = _outline(o)
        if xy is not None:
            ax.fill(xy[:, 0], xy[:, 1], color="0.45", alpha=0.6, lw=0)
            ax.annotate(oid, (xy[:, 0].mean(), xy[:, 1].max()), fontsize=7, ha="center", va="bottom", color="0.2")
    for oid, centres in log.obstacles.items():
        present = np.isfinite(centres[:, 0])
        if not present.any():
            continue
        c = centres[present]
        moves = np.ptp(c[:, :2], axis=0).max() > 1e-6
        if moves or oid not in header_ids:
            ax.plot(c[:, 0], c[:, 1], color="0.3", ls="--", lw=0.8)
            ring = _circle(c[-1, :2], log.obstacle_radius.get(oid, 0.0))
            ax.plot(ring[:, 0], ring[:, 1], color="0.3", lw=0.8)
            if oid not in header_ids:
                ax.annotate(oid, c[-1, :2], fontsize=7, color="0.2")
    ok = np.isfinite(pos[:, 0])
    if ok.any():
        ax.plot(pos[ok, 0], pos[ok, 1], color="C0", lw=1.4, label="driven")
        first, last = np.flatnonzero(ok)[[0, -1]]
        ax.annotate("SP", pos[first, :2], fontsize=9, weight="bold")
        ax.annotate("EP", pos[last, :2], fontsize=9, weight="bold")
    ref = log.reference
    if np.isfinite(ref[:, 0]).any():
        ax.plot(ref[:, 0], ref[:, 1], color="C1", ls=":", lw=1.2, label="reference position")
    fs = _event_positions(log, pos, "failsafe")
    if len(fs):
        ax.plot(fs[:, 0], fs[:, 1], "rX", ms=10, label="failsafe")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="X (m)", ylabel="Y (m)",
           title="Map" + (" (top view)" if h.dim == 3 else "") + "; dashed: recorded obstacle centres")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(loc="best", fontsize=8)


def _outline(o: dict) -> np.ndarray | None:
    if o.get("outline"):
        return np.asarray(o["outline"], float)[:, :2]
    if "center" in o and "radius" in o:
        return _circle(np.asarray(o["center"], float)[:2], float(o["radius"]))
    return None


def _circle(centre: np.ndarray, r: float, n: int = 64) -> np.ndarray:
    a = np.linspace(0.0, 2.0 * np.pi, n)
    return np.asarray(centre, float)[None, :2] + r * np.column_stack([np.cos(a), np.sin(a)])


def _event_positions(log: FlightLog, pos: np.ndarray, kind: str) -> np.ndarray:
    """(n, 2) positions at the ticks nearest to each event of ``kind`` (those with a position)."""
    if not len(log):
        return np.zeros((0, 2))
    out = []
    for ev in log.events:
        if ev.kind == kind:
            i = int(np.argmin(np.abs(log.t - ev.t)))
            if np.isfinite(pos[i, 0]):
                out.append(pos[i, :2])
    return np.array(out).reshape(-1, 2)


def _draw_tracking(ax, log: FlightLog, pos: np.ndarray) -> None:
    err = np.linalg.norm(pos - log.reference[:, : pos.shape[1]], axis=1)
    ax.plot(log.t, err, label="|position - reference|")
    if log.header.dim == 3:
        ax.plot(log.t, pos[:, 2], label="Z")
        ax.plot(log.t, log.reference[:, 2], ls=":", label="Z reference")
    for ev in log.events:
        if ev.kind == "failsafe":
            ax.axvline(ev.t, color="r", lw=0.8)
    ax.ticklabel_format(axis="y", useOffset=False)
    ax.set(xlabel="t (s)", ylabel="m", title="Tracking error" + (" and altitude" if log.header.dim == 3 else ""))
    ax.legend(loc="upper right", fontsize=8)


def _draw_commands(ax, log: FlightLog) -> None:
    names = log.header.control_names or tuple(f"u{j}" for j in range(log.command.shape[1]))
    for j in range(log.command.shape[1]):
        ax.plot(log.t, log.command[:, j], label=names[j] if j < len(names) else f"u{j}")
    ax.set(xlabel="t (s)", title="Commands sent")
    if log.command.shape[1]:
        ax.legend(loc="upper right", fontsize=8)


def _draw_timing(ax, seconds: np.ndarray, rate_hz: float, title: str) -> None:
    ms = 1e3 * seconds[np.isfinite(seconds)]
    period_ms = 1e3 / rate_hz if rate_hz > 0 else None
    if ms.size:
        p50, p99, top = np.percentile(ms, 50), np.percentile(ms, 99), ms.max()
        hi = max(top, period_ms or 0.0) * 1.05 or 1.0
        lo = min(0.0, ms.min())
        ax.hist(ms, bins=np.linspace(lo, hi, 120), color="C0", log=True,
                label=f"p50 {p50:.2f} ms, p99 {p99:.2f} ms, max {top:.2f} ms")
        ax.set_ylim(bottom=0.5)
    if period_ms is not None:
        ax.axvline(period_ms, color="r", lw=1.0, label=f"period {period_ms:.1f} ms")
    ax.set(xlabel="ms", ylabel="ticks", title=title)
    ax.legend(loc="upper right", fontsize=8)


def main(log_path: str | Path, out: str | Path | None = None) -> Path:
    """Read the flight log, write its PNG (default: the log path with suffix .png), print
    ``wrote PATH`` and return the path."""
    log_path = Path(log_path)
    written = plot_flight_log(read_flight_log(log_path), Path(out) if out else log_path.with_suffix(".png"))
    print(f"wrote {written}")
    return written
