"""`vflpcd bench ml`: the paper's model-uncertainty test (section IV, "Model Uncertainties Learning").

``racing_track`` driven by the mismatched "exact" vehicle with process noise, two laps, for each
seed: VF-LPC without the online GP (w/o ML: the offline Koopman model alone) and with it (w/ ML,
``vflpc_ml``). Per run: the RMS lateral error of lap 2 (the laps split where the distance driven
reaches the track's length), J_MC, J_Con, the longitudinal jerk p99 / max, the GP refits, and
the seconds in which the applied a_x touched both of its limits (chatter), and the lap-2 mean lateral
error in left and in right curves (the steady offset a model mismatch leaves). Prints one row per run
and the means; writes ``bench_ml.json`` and ``bench_ml.png`` (lateral error over time, both runs,
as in the paper's figure).
"""

from __future__ import annotations

import json
import logging
from dataclasses import replace
from pathlib import Path

import numpy as np

from sim.runner import run_closed_loop
from vflpcd.config.scenarios import load_scenario
from vflpcd.controllers import make_controller
from vflpcd.controllers.vflpc import limits_for
from sim.plot import save_png

CONTROLLERS = (("w/o ML", "vflpc"), ("w/ ML", "vflpc_ml"))
CURVE_KAPPA = 0.02  # 1/m: a route curvature beyond this counts as a curve (tightest: 1/18 m)


def lap_two(record, length: float) -> np.ndarray:
    """Indices of the steps of lap 2: from where the distance driven reaches ``length`` on."""
    step = np.linalg.norm(np.diff(record.position, axis=0), axis=1)
    driven = np.concatenate([[0.0], np.cumsum(step)])
    return np.flatnonzero(driven >= length)


def chatter_seconds(t: np.ndarray, a_x: np.ndarray, a_min: float, a_max: float) -> int:
    """Whole seconds of the run in which the applied a_x touched both limits."""
    tol = 1e-6 * (a_max - a_min)
    sec = np.floor(t).astype(int)
    low, high = a_x <= a_min + tol, a_x >= a_max - tol
    return int(sum(np.any(low[sec == s]) and np.any(high[sec == s]) for s in np.unique(sec)))


def curve_offsets(scenario, record, steps: np.ndarray, kappa_min: float = CURVE_KAPPA) -> tuple[float, float]:
    """Mean signed lateral error (m) over ``steps`` where the route bends left (curvature at the
    body's projection above kappa_min) and where it bends right (below -kappa_min): the steady
    offset in curves that a model mismatch leaves (NaN where the steps hold no such curve)."""
    path = scenario.path
    kappa = np.array([path.curvature_at(path.project(p).s) for p in record.position[steps]]).reshape(-1)
    e = record.lateral[steps]
    left, right = e[kappa > kappa_min], e[kappa < -kappa_min]
    return (float(left.mean()) if left.size else float("nan"), float(right.mean()) if right.size else float("nan"))


def run_one(scenario, name: str, label: str, seed: int) -> dict:
    controller = make_controller(name, scenario)
    record = run_closed_loop(scenario, controller, seed=seed)
    m = record.metrics
    lap2 = lap_two(record, scenario.path.length)
    ok = np.isfinite(record.lateral[lap2])
    a = record.control_names.index("a_x")
    applied = record.applied[:, a]
    fin = np.isfinite(applied)
    lim = limits_for(scenario, scenario.control_period)
    left, right = curve_offsets(scenario, record, lap2) if lap2.size else (None, None)
    return {"label": label, "controller": name, "seed": seed, "outcome": m["outcome"],
            "rms_lateral_lap2": float(np.sqrt(np.mean(record.lateral[lap2][ok] ** 2))) if ok.any() else None,
            "J_MC": m["J_MC"], "J_Con": m["J_Con"], "jerk_p99": m["jerk_p99"], "jerk_max": m["jerk_max"],
            "refits": controller.status().refits, "collisions": m["collisions"],
            "offset_left": left, "offset_right": right,
            "chatter_s": chatter_seconds(record.t[fin], applied[fin], float(lim.u_min[a]), float(lim.u_max[a])),
            "t": record.t.tolist(), "lateral": record.lateral.tolist()}


def bench_ml(out: Path, seeds: int = 5, laps: int = 2) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)
    base = load_scenario("racing_track")
    scenario = replace(base, params="exact", process_noise=True, laps=laps,
                       t_max=laps * base.path.length / base.v_desired + 30.0)
    head = (f"{'run':<8} {'seed':>4} {'outcome':<10} {'RMS lat lap2 m':>14} {'J_MC':>7} {'J_Con':>7} "
            f"{'jerk p99':>8} {'jerk max':>8} {'refits':>6} {'chatter s':>9} {'offset L/R m':>13}")
    print(head + "\n" + "-" * len(head), flush=True)
    runs = []
    for seed in range(seeds):
        for label, name in CONTROLLERS:
            r = run_one(scenario, name, label, seed)
            runs.append(r)
            print(f"{label:<8} {seed:>4} {r['outcome']:<10} {_f(r['rms_lateral_lap2'], 4):>14} {_f(r['J_MC'], 4):>7} "
                  f"{_f(r['J_Con'], 4):>7} {_f(r['jerk_p99'], 2):>8} {_f(r['jerk_max'], 2):>8} {r['refits']:>6} "
                  f"{r['chatter_s']:>9} {_f(r['offset_left'], 3):>6}/{_f(r['offset_right'], 3):<6}", flush=True)
    summary = {}
    for label, _ in CONTROLLERS:
        mine = [r for r in runs if r["label"] == label]
        summary[label] = {k: _mean([r[k] for r in mine]) for k in ("rms_lateral_lap2", "J_MC", "J_Con", "jerk_p99",
                                                                   "jerk_max", "refits", "chatter_s", "offset_left",
                                                                   "offset_right")}
        summary[label]["without_lap2"] = sum(r["rms_lateral_lap2"] is None for r in mine)
    wo, w = summary["w/o ML"], summary["w/ ML"]
    better = sum(lap2_better(a["rms_lateral_lap2"], b["rms_lateral_lap2"]) for a, b in
                 zip([r for r in runs if r["label"] == "w/o ML"], [r for r in runs if r["label"] == "w/ ML"]))
    print(f"\nmeans over {seeds} seeds (of the runs that drove a lap 2):")
    for label in summary:
        s = summary[label]
        print(f"  {label:<7} RMS lat lap 2 {s['rms_lateral_lap2']:.4f} m, J_MC {s['J_MC']:.4f}, J_Con {s['J_Con']:.4f}, "
              f"jerk p99/max {s['jerk_p99']:.2f}/{s['jerk_max']:.2f} m/s^3, refits {s['refits']:.1f}, "
              f"chatter {s['chatter_s']:.1f} s, lap-2 offset in left/right curves {s['offset_left']:+.3f}/"
              f"{s['offset_right']:+.3f} m" + (f"; {s['without_lap2']} run(s) never drove a lap 2" if s["without_lap2"] else ""))
    change = 1.0 - w["rms_lateral_lap2"] / wo["rms_lateral_lap2"]
    print(f"  w/ ML against w/o ML: lap-2 RMS lateral {abs(change) * 100:.1f} % {'lower' if change > 0 else 'higher'}, "
          f"lower in {better}/{seeds} seeds; J_Con {(w['J_Con'] / wo['J_Con'] - 1.0) * 100:+.1f} %")
    doc = {"scenario": "racing_track", "params": "exact", "process_noise": True, "laps": laps, "seeds": seeds,
           "summary": summary, "rms_lap2_reduction": change, "seeds_better": better,
           "runs": [{k: v for k, v in r.items() if k not in ("t", "lateral")} for r in runs]}
    path = out / "bench_ml.json"
    path.write_text(json.dumps(doc, indent=2) + "\n")
    png = plot(runs, out / "bench_ml.png")
    print(f"wrote {path}\nwrote {png}")
    return doc


def plot(runs: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(10, 4))
    for r in runs:
        if r["seed"] == 0:
            ax.plot(r["t"], r["lateral"], label=r["label"], lw=1.0)
    ax.set(xlabel="t (s)", ylabel="lateral error (m)", title="racing_track, exact vehicle with process noise, seed 0")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_png(fig, path, 120)


def lap2_better(without: float | None, with_ml: float | None) -> bool:
    """Whether the run w/ ML tracked better on lap 2 than the run w/o ML of the same seed: a lower
    RMS, or a lap 2 where the other run drove none (None: the run stopped before it)."""
    if with_ml is None:
        return False
    return without is None or with_ml < without


def _mean(values) -> float:
    """The mean of the values that exist (not None, finite); NaN when none does."""
    v = [x for x in values if x is not None and np.isfinite(x)]
    return float(np.mean(v)) if v else float("nan")


def _f(v, digits: int) -> str:
    return "n/a" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"
