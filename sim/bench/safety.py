"""`vflpcd bench safety`: every controller behind the safety supervisor on scenes built to hurt.

The scenes are in ``config/scenarios/safety/``: where no collision-free drivable path exists (a
dead end, a corridor narrower than the car's turning needs), where one exists only tightly (a
2.5 m gap, a corridor with posts), one where physics forbids a stop (a pedestrian who steps
out inside the stopping distance: ``UNAVOIDABLE``), and one where stopping is the wrong way out (a
pass whose route cuts back in ahead of the slower car while the rear is still beside it). Each controller runs each scene twice in the
same process: behind the supervisor (as everywhere) and without it, for comparison.

Per run it prints: outcome (and the guard's failsafe reason), collisions, least clearance of the
exact body, the gap to the nearest obstacle where the body came to rest, supervisor
interventions, and the impact speed at the first contact. The acceptance lines below the table:
zero collisions behind the supervisor except in the unavoidable scene, where the impact speed
must be lower than without it; every supervised run either completed or stopped; and the
supervisor's per-tick cost (median, p99) over all supervised runs. JSON and a PNG (the paths
with and without the supervisor, per scene) go to --out.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from vflpcd.controllers import make_controller
from sim.runner import RunRecord, run_closed_loop
from vflpcd.config.scenarios import Scenario, load_scenario
from vflpcd.core.safety.guard import REST_SPEED
from vflpcd.base.paths import config_dir
from sim.plot import save_png

SCENES = ("wall_across", "narrow_turn", "pedestrian_close", "tight_gap", "dense_corridor", "cut_in")
UNAVOIDABLE = ("pedestrian_close",)
CONTROLLERS = ("vflpc", "nmpc_cbf", "koopman_mpc", "pure_pursuit")
STOPPED = ("stopped", "failsafe", "timeout")   # the body ends at rest without reaching the goal


def scene(name: str) -> Scenario:
    return load_scenario(config_dir() / "scenarios" / "safety" / f"{name}.toml")


def rest_gap(record: RunRecord) -> float | None:
    """Clearance (m) to the nearest obstacle where the body ended at rest, None if it did not."""
    if not len(record.t) or np.linalg.norm(record.velocity[-1]) >= 2 * REST_SPEED:
        return None
    last = record.clearance[-1]
    return float(np.nanmin(last)) if np.any(np.isfinite(last)) else None


def run(name: str, sc: Scenario, controller: str, supervised: bool) -> dict:
    ctl = make_controller(controller, sc)
    t0 = time.perf_counter()
    rec = run_closed_loop(sc, ctl, supervised=supervised)
    m = rec.metrics
    return {"scene": name, "controller": controller, "supervised": supervised, "outcome": m["outcome"],
            "failsafe": m["failsafe"], "collisions": int(m["collisions"]), "min_clearance": m["min_clearance"],
            "rest_gap": rest_gap(rec), "interventions": m["interventions"], "impact_speed": m["impact_speed"],
            "t_com": m["t_com"], "wall_s": time.perf_counter() - t0, "t_sup": rec.t_sup[rec.t_sup > 0],
            "path": rec.position[:, :2]}


def _f(v, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else f"{v:.{digits}f}"


def checks(rows: list[dict]) -> list[tuple[str, bool, str]]:
    sup = [r for r in rows if r["supervised"]]
    free = [r for r in sup if r["scene"] not in UNAVOIDABLE]
    hit = [r for r in free if r["collisions"]]
    out = [("zero collisions behind the supervisor where a stop is possible", not hit,
            ", ".join(f"{r['scene']}/{r['controller']}" for r in hit) or "0")]
    for r in (r for r in sup if r["scene"] in UNAVOIDABLE):
        bare = next(b for b in rows if not b["supervised"] and b["scene"] == r["scene"]
                    and b["controller"] == r["controller"])
        v_sup, v_bare = r["impact_speed"], bare["impact_speed"]
        ok = v_sup is None or (v_bare is not None and v_sup < v_bare)
        out.append((f"{r['scene']}/{r['controller']}: impact speed lower than without the supervisor", ok,
                    f"{_f(v_sup)} vs {_f(v_bare)} m/s"))
    bad = [r for r in free if r["outcome"] not in ("completed",) + STOPPED]
    out.append(("every supervised run completes or stops", not bad,
                ", ".join(f"{r['scene']}/{r['controller']}: {r['outcome']}" for r in bad) or "all"))
    t = np.concatenate([r["t_sup"] for r in sup]) * 1e6
    out.append(("supervisor cost per tick, median <= 200 us", bool(np.median(t) <= 200.0),
                f"median {np.median(t):.0f} us, p99 {np.percentile(t, 99):.0f} us over {t.size} ticks"))
    return out


def plot(rows: list[dict], scenes: dict[str, Scenario], out: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from vflpcd.core.shapes import top_view

    fig, axes = plt.subplots(len(scenes), 1, figsize=(12, 3.6 * len(scenes)))
    for ax, (name, sc) in zip(np.atleast_1d(axes), scenes.items()):
        p = sc.path.points
        ax.plot(p[:, 0], p[:, 1], "k--", lw=0.7)
        for o in sc.obstacles:
            xy = top_view(o.shape).outline(o.center[:2], o.yaw)
            ax.fill(xy[:, 0], xy[:, 1], color="0.5", alpha=0.6, lw=0)
        for i, r in enumerate(r for r in rows if r["scene"] == name):
            ax.plot(r["path"][:, 0], r["path"][:, 1], lw=1.2 if r["supervised"] else 0.8,
                    ls="-" if r["supervised"] else ":", color=f"C{CONTROLLERS.index(r['controller'])}",
                    label=f"{r['controller']}{'' if r['supervised'] else ' (no supervisor)'}: {r['outcome']}")
        ax.set_aspect("equal", adjustable="datalim")
        ax.set(title=name, xlabel="X (m)", ylabel="Y (m)")
        ax.legend(fontsize=7, loc="upper left", ncol=2)
    fig.tight_layout()
    return save_png(fig, out, 100)


def bench_safety(out: Path, scenes: tuple[str, ...] = SCENES, controllers: tuple[str, ...] = CONTROLLERS) -> dict:
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)     # replan failures are counted
    logging.getLogger("vflpcd.controllers").setLevel(logging.ERROR)
    loaded = {name: scene(name) for name in scenes}
    head = (f"{'scene':<17} {'controller':<13} {'supervisor':<10} {'outcome':<10} {'coll':>4} {'clear m':>8} "
            f"{'rest gap m':>10} {'interv':>6} {'impact m/s':>10}  failsafe")
    print(head + "\n" + "-" * len(head), flush=True)
    rows = []
    for name, sc in loaded.items():
        for controller in controllers:
            for supervised in (True, False):
                r = run(name, sc, controller, supervised)
                rows.append(r)
                print(f"{name:<17} {controller:<13} {'on' if supervised else 'off':<10} {r['outcome']:<10} "
                      f"{r['collisions']:>4} {_f(r['min_clearance']):>8} {_f(r['rest_gap']):>10} "
                      f"{r['interventions']:>6} {_f(r['impact_speed']):>10}  {r['failsafe'][:90]}", flush=True)
    results = checks(rows)
    print("\nacceptance:\n" + "\n".join(f"  [{'met' if ok else 'MISSED'}] {what}: {value}"
                                       for what, ok, value in results))
    t = np.concatenate([r["t_sup"] for r in rows if r["supervised"]])
    doc = {"scenes": list(scenes), "controllers": list(controllers),
           "supervisor_us": {"median": float(np.median(t) * 1e6), "p99": float(np.percentile(t, 99) * 1e6),
                             "ticks": int(t.size)},
           "runs": [{k: v for k, v in r.items() if k not in ("t_sup", "path")} for r in rows],
           "checks": {what: bool(ok) for what, ok, _ in results}}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_safety.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    png = plot(rows, loaded, out / "bench_safety.png")
    print(f"wrote {out / 'bench_safety.json'}\nwrote {png}")
    return doc
