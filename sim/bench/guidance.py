"""`vflpcd bench guidance`: the paper's planning table (VF-LPC guidance against Hybrid A*).

Both planners get the same query on a ground scenario (default ``dense_static``): from the start
pose to the end of the reference path, around the scenario's obstacles. Reported per planner:
route length L_p, computation time t_cal (median and p99 over repeated runs), the smallest
clearance between the car's exact outline, posed along the planned path with the path's heading,
and every obstacle's physical boundary, and SD (safe distance kept: that clearance >= the safe
distance) and the peak curvature of the path. The guidance runs twice, with and without the
virtual obstacles of the kinodynamic field, and also reports the grid precompute time, measured
separately from t_cal.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from vflpcd.controllers.loops import guidance_loops
from vflpcd.core.guidance.grid import forget_local_grids
from vflpcd.controllers.hybrid_astar import HybridAStarParams, plan_scenario
from vflpcd.core.obstacle_world import ObstacleWorld
from vflpcd.config.scenarios import Scenario
from vflpcd.core.guidance.planner import GuidancePlanner, Prepared
from vflpcd.core.guidance.speed import menger_curvature
from sim.plot import save_png


@dataclass
class PlannerRow:
    name: str
    xy: np.ndarray
    length: float
    t_cal: list[float]
    min_clearance: float
    sd: bool
    extra: dict

    def as_dict(self) -> dict:
        return {"L_p": self.length, "t_cal_median": float(np.median(self.t_cal)),
                "t_cal_p99": float(np.percentile(self.t_cal, 99)), "t_cal_runs": len(self.t_cal),
                "min_clearance": self.min_clearance, "safe_distance_kept": self.sd, **self.extra}


def path_clearance(scenario: Scenario, xy: np.ndarray) -> float:
    """Least clearance of the car outline, posed along xy (K, 2) with the path heading, to every obstacle."""
    d = np.gradient(xy, axis=0)
    heading = np.arctan2(d[:, 1], d[:, 0])
    return float(min(scenario.footprint.clearance(o.shape, o.center, o.yaw, p, h)
                     for o in scenario.obstacles for p, h in zip(xy, heading)))


def run_guidance(scenario: Scenario, repeat: int, safe_distance: float,
                 virtual: str | None = None) -> tuple[PlannerRow, Prepared]:
    """The guidance with the scenario's parameters (``virtual`` overrides their virtual-obstacle mode)."""
    params = scenario.guidance if virtual is None else replace(scenario.guidance, virtual=virtual)
    planner = GuidancePlanner(scenario.path, params, scenario.v_desired, scenario.a_lat_max,
                              scenario.footprint.radius, scenario.control_period, loops=guidance_loops)
    obstacles = ObstacleWorld(scenario.obstacles).snapshot(0.0)
    planner.warm()              # its compiled loops loaded, as a daemon's workers do at start
    t_pre = []
    for _ in range(3):          # every static obstacle's local grid computed (none kept from before)
        forget_local_grids()
        t0 = time.perf_counter()
        prepared = planner.prepare(0.0, obstacles)
        t_pre.append(time.perf_counter() - t0)
    t_cal = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        plan = planner.plan(prepared, scenario.start[:2], 0.0, scenario.start[3], heading=scenario.start[2])
        t_cal.append(time.perf_counter() - t0)
    clearance = path_clearance(scenario, plan.xy)
    cells = prepared.grid.path.data.shape[0] * prepared.grid.path.data.shape[1] + sum(
        g.data.shape[0] * g.data.shape[1] for g in prepared.grid.obstacles)
    extra = {"reached_goal": plan.reached, "grid_precompute_median": float(np.median(t_pre)), "grid_cells": cells,
             "virtual_obstacles": len(prepared.field.virtuals), "inherited_steps": plan.inherited,
             "duration": plan.trajectory.duration, "peak_curvature": float(np.max(plan.kappa)),
             "max_v2_kappa_over_a_max": float(np.max(plan.v ** 2 * plan.kappa) / scenario.a_lat_max)}
    length = float(np.sum(np.linalg.norm(np.diff(plan.xy, axis=0), axis=1)))
    name = "VF-LPC guidance" + (" (virtual)" if params.virtual == "auto" else "")
    return PlannerRow(name, plan.xy, length, t_cal, clearance,
                      bool(plan.reached and clearance >= safe_distance), extra), prepared


def run_hybrid_astar(scenario: Scenario, repeat: int, safe_distance: float) -> PlannerRow:
    params = HybridAStarParams.load()
    t_cal = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        result = plan_scenario(scenario, params)
        t_cal.append(time.perf_counter() - t0)
    xy = result.path[:, :2] if result.success else np.zeros((0, 2))
    clearance = path_clearance(scenario, xy) if result.success else float("nan")
    return PlannerRow("Hybrid A*", xy, result.length if result.success else float("nan"), t_cal, clearance,
                      bool(result.success and clearance >= safe_distance),
                      {"success": result.success, "expansions": result.expansions, "reason": result.reason,
                       "peak_curvature": float(np.max(menger_curvature(xy))) if len(xy) > 2 else float("nan")})


def table(rows: list[PlannerRow], safe_distance: float) -> str:
    lines = [f"{'metric':<26}" + "".join(f"{r.name:>28}" for r in rows)]
    fmt = [("L_p (m)", lambda r: f"{r.length:.2f}"),
           ("t_cal median (s)", lambda r: f"{np.median(r.t_cal):.4f}"),
           ("t_cal p99 (s)", lambda r: f"{np.percentile(r.t_cal, 99):.4f}"),
           (f"SD (clearance >= {safe_distance:g} m)", lambda r: "yes" if r.sd else "no"),
           ("min clearance (m)", lambda r: f"{r.min_clearance:.3f}"),
           ("peak curvature (1/m)", lambda r: f"{r.extra['peak_curvature']:.3f}")]
    for label, f in fmt:
        lines.append(f"{label:<26}" + "".join(f"{f(r):>28}" for r in rows))
    return "\n".join(lines)


def plot(scenario: Scenario, rows: list[PlannerRow], prepared: Prepared, out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(14, 6), constrained_layout=True)
    dirs = np.column_stack([np.cos(np.linspace(0, 2 * np.pi, 240)), np.sin(np.linspace(0, 2 * np.pi, 240))])
    for o in scenario.obstacles:
        xy = o.shape.outline(o.center, o.yaw)
        ax.fill(xy[:, 0], xy[:, 1], color="0.35")
    for t in prepared.field.statics:
        im = t.implicit
        for level, style in ((0.0, dict(color="k", lw=0.6)), (im.c, dict(color="r", lw=0.6))):
            b = im.center + (dirs * ((1.0 + level) / im.norm(dirs))[:, None]) @ im.Rz.T
            ax.plot(b[:, 0], b[:, 1], **style)
    for v in prepared.field.virtuals:
        im = v.implicit
        for level in (0.0, im.c):
            b = im.center + dirs * (1.0 + level) * im.axes[0]
            ax.plot(b[:, 0], b[:, 1], color="tab:blue", ls="--", lw=0.5)
    ax.plot(scenario.path.points[:, 0], scenario.path.points[:, 1], "k:", lw=0.8, label="reference path")
    for r, color in zip(rows, ("tab:purple", "tab:green", "tab:orange")):
        if len(r.xy):
            ax.plot(r.xy[:, 0], r.xy[:, 1], color=color, lw=1.6,
                    label=f"{r.name}: {r.length:.2f} m, {np.median(r.t_cal) * 1e3:.1f} ms, clearance {r.min_clearance:.2f} m")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="X (m)", ylabel="Y (m)",
           title=f"{scenario.name}: planned paths (obstacles grey; reactive boundaries black, repulsive red, "
                 "virtual blue)")
    ax.legend(loc="upper left", fontsize=8)
    return save_png(fig, out, 110)


def bench_guidance(scenario: Scenario, out: Path, repeat: int = 20, astar_repeat: int = 3,
                   safe_distance: float = 0.0) -> dict:
    """Run both planners, print the table, write ``out/bench_guidance.json`` and ``.png``."""
    gvf, prepared = run_guidance(scenario, repeat, safe_distance)
    other = "auto" if scenario.guidance.virtual == "off" else "off"
    gvf_other, _ = run_guidance(scenario, repeat, safe_distance, virtual=other)
    astar = run_hybrid_astar(scenario, astar_repeat, safe_distance)
    rows = [gvf, gvf_other, astar]
    print(table(rows, safe_distance))
    print(f"grid precompute (median of 3): {gvf.extra['grid_precompute_median']:.3f} s for "
          f"{gvf.extra['grid_cells']} cells; speed-up of t_cal over Hybrid A*: "
          f"{np.median(astar.t_cal) / np.median(gvf.t_cal):.0f}x; L_p ratio {gvf.length / astar.length:.3f}")
    out.mkdir(parents=True, exist_ok=True)
    doc = {"scenario": scenario.name, "safe_distance": safe_distance,
           "planners": {r.name: r.as_dict() for r in rows}}
    (out / "bench_guidance.json").write_text(json.dumps(doc, indent=2) + "\n")
    plot(scenario, rows, prepared, out / "bench_guidance.png")
    print(f"wrote {out / 'bench_guidance.json'}\nwrote {out / 'bench_guidance.png'}")
    return doc
