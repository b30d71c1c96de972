"""`vflpcd bench impc`: the paper's comparison of integrated motion planning and control.

Three tables, each from closed-loop runs of ``sim.runner`` (t_cal is the wall time of the
controller's ``step``, the command's latency; the GP sample that VF-LPC w/ ML takes after the
command, ``settle``, is timed apart as t_settle; replans and GP refits are worker work, timed apart
as t_background):

1. ``carsim_avoidance`` on the nominal plant: VF-LPC, NMPC (MPC-CBF, CasADi + IPOPT), the same
   problem by real-time iterations (NMPC-RTI: one Gauss-Newton step per tick, HPIPM; the label
   says whether its QP data ran compiled, "C", or interpreted), the Koopman-MPC (OSQP) and pure
   pursuit (no planning);
2. the same road on the paper's mismatched "exact" vehicle: VF-LPC without and with the online
   GP compensation (w/o ML, w/ ML);
3. ``uav_3d``: VF-LPC, the Koopman-MPC and the PD tracker.

Columns: J_MC, L_p, t_com, t_cal median and p99, collisions, minimum clearance of the exact
body, peak lateral acceleration, fallbacks, the background jobs' (replans, GP refits) median, p99
and max, and the safety
supervisor's interventions and median cost per tick (every controller runs behind it), the median
``settle`` per tick. Below the tables
the acceptance figures are printed: VF-LPC's t_cal against 1 ms and 0.25 ms (median) and 3 ms and
1 ms (p99), its speed-up over the NMPC and the Koopman-MPC, its median against half the NMPC-RTI's,
its background jobs against 50 ms (p99) and 100 ms (max), and its J_MC against the NMPC's. JSON and a PNG
(trajectories around the obstacles, t_cal distributions, lateral error w/ and w/o ML) go to --out.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vflpcd.controllers import make_controller
from sim.runner import RunRecord, run_closed_loop
from vflpcd.config.scenarios import Scenario, load_scenario
from sim.plot import save_png

NOMINAL = ("vflpc", "nmpc_cbf", "nmpc_rti", "koopman_mpc", "pure_pursuit")
EXACT = ("vflpc", "vflpc_ml")
AERIAL = ("vflpc", "koopman_mpc", "pd_tracker")
LABELS = {"vflpc": "VF-LPC", "vflpc_ml": "VF-LPC w/ ML", "nmpc_cbf": "NMPC (MPC-CBF)", "nmpc_rti": "NMPC-RTI (HPIPM)",
          "koopman_mpc": "Koopman-MPC (OSQP)", "pure_pursuit": "pure pursuit", "pd_tracker": "PD tracker"}
COUNTERS = ("fallbacks", "replans", "replan_failures", "refits")


@dataclass
class Run:
    table: str
    controller: str
    label: str
    record: RunRecord
    metrics: dict
    wall: float

    def as_dict(self) -> dict:
        keep = {k: v for k, v in self.metrics.items() if not isinstance(v, (list, dict, np.ndarray))}
        return {"table": self.table, "controller": self.controller, "label": self.label, "wall_s": self.wall, **keep}


def run_one(table: str, name: str, scenario: Scenario, label: str | None = None) -> Run:
    controller = make_controller(name, scenario)
    t0 = time.perf_counter()
    record = run_closed_loop(scenario, controller)
    wall = time.perf_counter() - t0
    metrics = dict(record.metrics)
    for counter in COUNTERS:
        if hasattr(controller, counter):
            metrics[counter] = int(getattr(controller, counter))
    label = label or LABELS[name]
    if hasattr(controller, "compiled"):          # whether its derivatives ran compiled C or interpreted
        metrics["compiled"] = bool(controller.compiled)
        label += " C" if controller.compiled else " interp."
    return Run(table, name, label, record, metrics, wall)


def _fmt(v, scale: float = 1.0, digits: int = 3) -> str:
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v * scale:.{digits}g}" if isinstance(v, float) else str(v)


def table(title: str, runs: list[Run]) -> str:
    head = (f"{'controller':<20} {'outcome':<10} {'J_MC':>7} {'L_p m':>7} {'t_com s':>8} {'t_cal med ms':>13} "
            f"{'p99 ms':>8} {'coll':>5} {'clear m':>8} {'a_lat max':>10} {'fallb':>6} {'bg med/p99/max ms':>18} {'interv':>6} "
            f"{'sup med us':>10} {'settle med us':>13} {'RMS lat m':>9} {'peak lat':>8} {'jerk p99':>8} {'jerk max':>8}")
    lines = [title, head, "-" * len(head)]
    for r in runs:
        m = r.metrics
        lines.append(f"{r.label:<20} {m['outcome']:<10} {_fmt(m['J_MC']):>7} {_fmt(m['L_p'], digits=4):>7} "
                     f"{_fmt(m['t_com'], digits=4):>8} {_fmt(m['t_cal_median'], 1e3):>13} "
                     f"{_fmt(m['t_cal_p99'], 1e3):>8} {m['collisions']:>5} {_fmt(m['min_clearance']):>8} "
                     f"{_fmt(m['peak_lateral_acceleration']):>10} {m.get('fallbacks', '-'):>6} "
                     f"{_background(m):>18} {m['interventions']:>6} "
                     f"{m['t_sup_median'] * 1e6:>10.0f} {m['t_settle_median'] * 1e6:>13.0f} "
                     f"{_fmt(m['rms_lateral_error']):>9} "
                     f"{_fmt(m['peak_lateral_error']):>8} {_fmt(m['jerk_p99']):>8} {_fmt(m['jerk_max']):>8}")
    return "\n".join(lines)


def _background(m: dict) -> str:
    """The background jobs' (replans, refits) median / p99 / max in ms, "-" when none ran."""
    if not m.get("background_jobs"):
        return "-"
    return "/".join(f"{m[k] * 1e3:.0f}" for k in ("t_background_median", "t_background_p99", "t_background_max"))


def acceptance(nominal: dict[str, Run]) -> tuple[str, dict]:
    """The issue's figures from table 1, each with whether it holds."""
    lpc, nmpc, qp = nominal["vflpc"].metrics, nominal["nmpc_cbf"].metrics, nominal["koopman_mpc"].metrics
    rti = nominal["nmpc_rti"].metrics
    figures = {
        "nmpc_rti_t_cal_median_ms": rti["t_cal_median"] * 1e3, "nmpc_rti_compiled": rti.get("compiled"),
        "vflpc_over_nmpc_rti_median": lpc["t_cal_median"] / rti["t_cal_median"],
        "vflpc_background_p99_ms": lpc["t_background_p99"] * 1e3, "vflpc_background_max_ms": lpc["t_background_max"] * 1e3,
        "vflpc_t_cal_median_ms": lpc["t_cal_median"] * 1e3,
        "vflpc_t_cal_p99_ms": lpc["t_cal_p99"] * 1e3,
        "speedup_over_nmpc_median": nmpc["t_cal_median"] / lpc["t_cal_median"],
        "speedup_over_koopman_mpc_median": qp["t_cal_median"] / lpc["t_cal_median"],
        "vflpc_J_MC": lpc["J_MC"], "nmpc_J_MC": nmpc["J_MC"],
        "vflpc_collisions": lpc["collisions"],
    }
    checks = [
        ("VF-LPC median t_cal <= 1 ms", figures["vflpc_t_cal_median_ms"] <= 1.0, f"{figures['vflpc_t_cal_median_ms']:.3f} ms"),
        ("VF-LPC p99 t_cal <= 3 ms", figures["vflpc_t_cal_p99_ms"] <= 3.0, f"{figures['vflpc_t_cal_p99_ms']:.3f} ms"),
        ("at least 100x faster than the NMPC (median)", figures["speedup_over_nmpc_median"] >= 100.0,
         f"{figures['speedup_over_nmpc_median']:.1f}x"),
        ("no slower than the Koopman-MPC (median)", figures["speedup_over_koopman_mpc_median"] >= 1.0,
         f"{figures['speedup_over_koopman_mpc_median']:.2f}x"),
        ("J_MC no worse than the NMPC's", lpc["J_MC"] <= nmpc["J_MC"], f"{lpc['J_MC']:.3f} vs {nmpc['J_MC']:.3f}"),
        ("VF-LPC median t_cal <= 0.25 ms", figures["vflpc_t_cal_median_ms"] <= 0.25,
         f"{figures['vflpc_t_cal_median_ms']:.3f} ms"),
        ("VF-LPC median t_cal <= 0.5 x NMPC-RTI's", figures["vflpc_over_nmpc_rti_median"] <= 0.5,
         f"{figures['vflpc_over_nmpc_rti_median']:.2f} x ({figures['nmpc_rti_t_cal_median_ms']:.3f} ms, "
         f"{'compiled' if rti.get('compiled') else 'interpreted'})"),
        ("VF-LPC p99 t_cal <= 1 ms", figures["vflpc_t_cal_p99_ms"] <= 1.0, f"{figures['vflpc_t_cal_p99_ms']:.3f} ms"),
        ("VF-LPC background jobs p99 <= 50 ms, max <= 100 ms",
         figures["vflpc_background_p99_ms"] <= 50.0 and figures["vflpc_background_max_ms"] <= 100.0,
         f"{figures['vflpc_background_p99_ms']:.0f} / {figures['vflpc_background_max_ms']:.0f} ms"),
        ("zero collisions", lpc["collisions"] == 0, str(lpc["collisions"])),
    ]
    figures["checks"] = {name: bool(ok) for name, ok, _ in checks}
    text = "\n".join(f"  [{'met' if ok else 'MISSED'}] {name}: {value}" for name, ok, value in checks)
    return "acceptance figures (table 1):\n" + text, figures


def plot(nominal: list[Run], exact: list[Run], aerial: list[Run], scenario: Scenario, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vflpcd.core.shapes import top_view

    fig = plt.figure(figsize=(14, 10))
    ax = fig.add_subplot(2, 1, 1)
    path = scenario.path.points
    ax.plot(path[:, 0], path[:, 1], color="k", lw=0.8, ls="--", label="reference path")
    rec0 = nominal[0].record
    for j, o in enumerate(scenario.obstacles):
        shape = top_view(o.shape)
        present = np.isfinite(rec0.clearance[:, j])
        ks = np.flatnonzero(present)
        for n, k in enumerate(ks[:: max(len(ks) // 5, 1)] if len(ks) else []):
            xy = shape.outline(rec0.obstacle_center[k, j, :2], o.yaw)
            ax.fill(xy[:, 0], xy[:, 1], color=str(0.3 + 0.1 * n), alpha=0.6, lw=0)
    for r in nominal:
        ax.plot(r.record.position[:, 0], r.record.position[:, 1], lw=1.3, label=r.label)
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="X (m)", ylabel="Y (m)", title=f"{scenario.name}: trajectories (nominal plant)")
    ax.legend(fontsize=8, loc="upper left")

    ax = fig.add_subplot(2, 2, 3)
    data = [np.asarray(r.record.t_cal) * 1e3 for r in nominal + aerial]
    labels = [r.label + (" (uav)" if r in aerial else "") for r in nominal + aerial]
    ax.boxplot(data, vert=False, whis=(1, 99), showfliers=False)
    ax.set_yticks(range(1, len(labels) + 1), labels, fontsize=8)
    ax.set_xscale("log")
    ax.set(xlabel="t_cal per control step (ms, whiskers p1-p99)", title="computation time")

    ax = fig.add_subplot(2, 2, 4)
    for r in exact:
        ax.plot(r.record.t, r.record.lateral, lw=1.0, label=r.label)
    ax.set(xlabel="t (s)", ylabel="lateral error to the path (m)", title="exact (mismatched) vehicle")
    ax.legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, out, 110)


def bench_impc(out: Path, scenario: str = "carsim_avoidance", aerial: str = "uav_3d") -> dict:
    """Run the three tables, print them and the acceptance figures, write JSON and PNG."""
    ground = load_scenario(scenario)
    nominal = [run_one("nominal", name, ground) for name in NOMINAL]
    print(table(f"Table 1: {ground.name}, nominal vehicle", nominal), flush=True)
    exact_scenario = replace(ground, params="exact")
    exact = [run_one("exact", name, exact_scenario, LABELS[name] + (" w/o ML" if name == "vflpc" else ""))
             for name in EXACT]
    print("\n" + table(f"Table 2: {ground.name}, exact (mismatched) vehicle", exact), flush=True)
    air = load_scenario(aerial)
    air_runs = [run_one("aerial", name, air) for name in AERIAL]
    print("\n" + table(f"Table 3: {air.name}", air_runs), flush=True)
    text, figures = acceptance({r.controller: r for r in nominal})
    print("\n" + text)
    doc = {"scenario": ground.name, "aerial_scenario": air.name, "runs": [r.as_dict() for r in nominal + exact + air_runs],
           "acceptance": figures}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_impc.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    png = plot(nominal, exact, air_runs, ground, out / "bench_impc.png")
    print(f"wrote {out / 'bench_impc.json'}\nwrote {png}")
    return doc
