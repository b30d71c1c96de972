"""`vflpcd bench suite`: every ground controller on the road scenes of ``config/scenarios/suite/``.

The suite (listed in ``config/scenarios/README.md``) holds the kinds of scene a road vehicle
meets: a slalom, a gap between parked cars, obstacles inside and outside bends, oncoming,
crossing and appearing road users, a slow car to follow and one to pass, a tight low-speed
S-curve with cones, a chicane, a double lane change, a roundabout and a mixed urban run. Each
controller (default VF-LPC and the ground baselines NMPC (MPC-CBF), NMPC-RTI, Koopman-MPC and pure pursuit)
runs each scene once, behind the safety supervisor, through ``sim.bench.impc.run_one``.

It prints one row per scene and controller (outcome, collisions, least clearance, J_MC, RMS and
peak lateral error, peak lateral acceleration against the scene's ``a_lat_max`` (the limit the
guidance plans within; the NMPCs, which track the route without it, may exceed it), longitudinal
jerk p99 / max, t_cal median, background jobs median / p99 / max, the safety supervisor's
interventions), then per controller: the scenes completed without a collision, the collisions, the scenes
where its J_MC is the lowest among the controllers that completed that scene without a collision,
its background jobs over every scene taken together (a scene runs a handful of replans, so a row's
p99 is close to its maximum), and for VF-LPC the scenes where its
peak lateral error exceeds the NMPC's by more than 1 m. JSON (rows and totals) and a PNG (J_MC
per scene as grouped bars, and the trajectories of every scene) go to --out.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from sim.bench.impc import LABELS, _background, _fmt, run_one
from sim.runner import job_stats, job_times
from vflpcd.base.paths import config_dir
from vflpcd.config.scenarios import Scenario, load_scenario
from sim.plot import save_png

CONTROLLERS = ("vflpc", "nmpc_cbf", "nmpc_rti", "koopman_mpc", "pure_pursuit")
PEAK_MARGIN = 1.0        # m: VF-LPC's peak lateral error may exceed the NMPC's by this much
KEYS = ("outcome", "collisions", "min_clearance", "J_MC", "rms_lateral_error", "peak_lateral_error",
        "peak_lateral_acceleration", "jerk_p99", "jerk_max", "t_cal_median", "t_com", "failsafe", "interventions", "background_jobs",
        "t_background_median", "t_background_p99", "t_background_max")


def suite_dir() -> Path:
    return config_dir() / "scenarios" / "suite"


def suite_names() -> tuple[str, ...]:
    return tuple(sorted(p.stem for p in suite_dir().glob("*.toml")))


def load(name: str) -> Scenario:
    return load_scenario(suite_dir() / f"{name}.toml")


def clean(row: dict) -> bool:
    """Completed without touching anything."""
    return row["outcome"] == "completed" and row["collisions"] == 0


def pooled_jobs(rows: list[dict]) -> dict | None:
    """The background jobs of rows taken together (a scene runs a handful, so its own p99 is its
    maximum): ``job_stats`` of them, None when no job ran."""
    stats = job_stats([t for r in rows for t in r.get("background_s", ())])
    return stats if stats["jobs"] else None


def totals(rows: list[dict], controllers: tuple[str, ...]) -> dict:
    """Per controller: scenes completed without a collision, collisions, scenes with the lowest J_MC
    among that scene's clean runs, its background jobs over every scene (``pooled_jobs``); and the
    scenes where VF-LPC's peak lateral error exceeds the NMPC's by more than PEAK_MARGIN (None
    unless both ran), with the NMPC's outcome there."""
    scenes = list(dict.fromkeys(r["scenario"] for r in rows))
    out = {c: {"clean": sum(clean(r) for r in rows if r["controller"] == c),
               "collisions": sum(r["collisions"] for r in rows if r["controller"] == c),
               "lowest_J_MC": 0, "runs": sum(r["controller"] == c for r in rows),
               "background": pooled_jobs([r for r in rows if r["controller"] == c])} for c in controllers}
    peak_worse = [] if {"vflpc", "nmpc_cbf"} <= set(controllers) else None
    nmpc_outcome: dict[str, str] = {}       # the NMPC's outcome in those scenes (one that stopped did not pass)
    for s in scenes:
        mine = {r["controller"]: r for r in rows if r["scenario"] == s}
        ok = [r for r in mine.values() if clean(r) and np.isfinite(r["J_MC"])]
        if ok:
            best = min(r["J_MC"] for r in ok)
            for r in ok:
                out[r["controller"]]["lowest_J_MC"] += r["J_MC"] == best
        if peak_worse is not None and "vflpc" in mine and "nmpc_cbf" in mine:
            if mine["vflpc"]["peak_lateral_error"] - mine["nmpc_cbf"]["peak_lateral_error"] > PEAK_MARGIN:
                peak_worse.append(s)
                nmpc_outcome[s] = mine["nmpc_cbf"]["outcome"]
    return {"controllers": out, "vflpc_peak_lateral_over_nmpc": peak_worse, "nmpc_outcome": nmpc_outcome,
            "scenes": len(scenes)}


HEAD = (f"{'scenario':<24} {'controller':<20} {'outcome':<10} {'coll':>4} {'clear m':>7} {'J_MC':>7} "
        f"{'RMS lat':>7} {'peak lat':>8} {'a_lat/limit':>11} {'jerk p99':>8} {'jerk max':>8} {'t_cal ms':>8} {'bg med/p99/max ms':>18} "
        f"{'interv':>6}")


def row_line(r: dict) -> str:
    return (f"{r['scenario']:<24} {LABELS[r['controller']]:<20} {r['outcome']:<10} {r['collisions']:>4} "
            f"{_fmt(r['min_clearance']):>7} {_fmt(r['J_MC']):>7} {_fmt(r['rms_lateral_error']):>7} "
            f"{_fmt(r['peak_lateral_error']):>8} {_a_lat(r):>11} {_fmt(r['jerk_p99']):>8} {_fmt(r['jerk_max']):>8} "
            f"{_fmt(r['t_cal_median'], 1e3):>8} {_background(r):>18} {r['interventions']:>6}")


def _a_lat(r: dict) -> str:
    """"peak / limit" lateral acceleration (m/s^2) of a row."""
    return f"{_fmt(r['peak_lateral_acceleration'], digits=2)}/{r['a_lat_max']:g}"


def totals_text(t: dict) -> str:
    lines = [f"totals over {t['scenes']} scenes:"]
    for c, v in t["controllers"].items():
        lines.append(f"  {LABELS[c]:<20} completed without collision {v['clean']}/{v['runs']}, collisions "
                     f"{v['collisions']}, lowest J_MC among the clean runs in {v['lowest_J_MC']}"
                     + _jobs_text(v["background"]))
    worse = t["vflpc_peak_lateral_over_nmpc"]
    if worse is not None:
        where = [f"{s} (the NMPC {t['nmpc_outcome'][s]})" for s in worse]
        lines.append(f"  VF-LPC peak lateral error > NMPC's + {PEAK_MARGIN:g} m in {len(worse)} scenes"
                     + (f": {', '.join(where)}" if worse else ""))
    return "\n".join(lines)


def _jobs_text(b: dict | None) -> str:
    """", background jobs N, median / p99 / max ms" over the suite, or nothing when none ran."""
    if not b:
        return ""
    return f", background jobs {b['jobs']}: {b['median'] * 1e3:.0f} / {b['p99'] * 1e3:.0f} / {b['max'] * 1e3:.0f} ms"


def plot(rows: list[dict], paths: dict, scenes: dict[str, Scenario], controllers: tuple[str, ...], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vflpcd.core.shapes import top_view

    names = list(scenes)
    cols = 4
    grid_rows = int(np.ceil(len(names) / cols))
    fig = plt.figure(figsize=(16, 4 + 3.2 * grid_rows))
    gs = fig.add_gridspec(1 + grid_rows, cols, height_ratios=[1.3] + [1.0] * grid_rows)
    ax = fig.add_subplot(gs[0, :])
    width = 0.8 / len(controllers)
    for i, c in enumerate(controllers):
        by = {r["scenario"]: r for r in rows if r["controller"] == c}
        x = np.arange(len(names)) + (i - (len(controllers) - 1) / 2) * width
        j = [by[n]["J_MC"] if n in by and np.isfinite(by[n]["J_MC"]) else 0.0 for n in names]
        bars = ax.bar(x, j, width, label=LABELS[c], color=f"C{i}")
        for b, n in zip(bars, names):
            if n in by and not clean(by[n]):
                b.set_hatch("//")
                b.set_alpha(0.5)
    ax.set_xticks(np.arange(len(names)), names, rotation=20, fontsize=8, ha="right")
    ax.set_yscale("symlog", linthresh=1e-3)
    ax.set_ylim(bottom=0.0)
    ax.set(ylabel="J_MC", title="J_MC per scene (hatched: not completed, or a collision)")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    for k, n in enumerate(names):
        ax = fig.add_subplot(gs[1 + k // cols, k % cols])
        sc = scenes[n]
        p = sc.path.points
        ax.plot(p[:, 0], p[:, 1], "k--", lw=0.6)
        for o in sc.obstacles:
            xy = top_view(o.shape).outline(o.center[:2], o.yaw)
            ax.fill(xy[:, 0], xy[:, 1], color="0.5", alpha=0.6, lw=0)
            if np.any(o.velocity[:2]):     # a mover: its velocity for 2 s
                ax.annotate("", o.center[:2] + 2.0 * o.velocity[:2], o.center[:2],
                            arrowprops={"arrowstyle": "->", "color": "0.3"})
        for i, c in enumerate(controllers):
            if (n, c) in paths:
                ax.plot(paths[n, c][:, 0], paths[n, c][:, 1], lw=1.0, color=f"C{i}")
        extent = np.ptp(p[:, :2], axis=0)
        if extent.min() > 0.2 * extent.max():     # true to scale, unless a straight road would be a thin line
            ax.set_aspect("equal", adjustable="datalim")
        else:                                     # along the road: as far as it and the runs reach
            xs = np.concatenate([p[:, 0]] + [paths[n, c][:, 0] for c in controllers if (n, c) in paths])
            ax.set_xlim(xs.min() - 5.0, xs.max() + 5.0)
            ax.set_ylabel("Y (m), not to scale", fontsize=7)
        ax.set_title(n, fontsize=9)
        ax.tick_params(labelsize=7)
    fig.tight_layout()
    return save_png(fig, out, 90)


def bench_suite(out: Path, controllers: tuple[str, ...] = CONTROLLERS, only: tuple[str, ...] | None = None) -> dict:
    """Run every (or ``only`` these) suite scenes with each controller; print, write JSON and PNG."""
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)     # replan failures show as outcomes
    logging.getLogger("vflpcd.controllers").setLevel(logging.ERROR)
    logging.getLogger("vflpcd.config.koopman_file").setLevel(logging.WARNING)   # one "loaded" line per run
    scenes = {n: load(n) for n in (only or suite_names())}
    print(HEAD + "\n" + "-" * len(HEAD), flush=True)
    rows, paths = [], {}
    for name, sc in scenes.items():
        for c in controllers:
            run = run_one("suite", c, sc)
            r = {"scenario": name, "controller": c, "wall_s": run.wall, "a_lat_max": sc.a_lat_max,
                 **{k: run.metrics[k] for k in KEYS},
                 "background_s": job_times(run.record.t_background).tolist()}
            rows.append(r)
            paths[name, c] = run.record.position[:, :2]
            print(row_line(r), flush=True)
    t = totals(rows, controllers)
    print("\n" + totals_text(t))
    doc = {"scenes": list(scenes), "controllers": list(controllers), "rows": rows, "totals": t}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_suite.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    png = plot(rows, paths, scenes, controllers, out / "bench_suite.png")
    print(f"wrote {out / 'bench_suite.json'}\nwrote {png}")
    return doc
