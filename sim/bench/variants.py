"""`vflpcd bench variants`: VF-LPC on seeded road variants with moving obstacles.

Each variant is a 160 m straight road at 25 km/h (``vflpcd.config.scenarios.line_scenario_toml``, written
to the output folder) with a pedestrian who starts crossing when the car is 20-35 m away
(0.8-1.8 m/s, from either side, at 35-55 m), a slow car that drives off ahead (1-3 m/s, at
75-90 m) and, in half of them, a static barrel between the two. Per seed it prints the outcome,
collisions, the minimum clearance and which obstacle came closest; then the totals. A run counts
as safe when it has no collision.
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from vflpcd.controllers.vflpc import make_vflpc
from sim.runner import run_closed_loop
from vflpcd.config.scenarios import line_scenario_toml, load_scenario

def variant_toml(seed: int) -> str:
    """The scenario TOML of variant ``seed``."""
    rng = np.random.default_rng(seed)
    side = rng.choice([-1.0, 1.0])
    speed = rng.uniform(0.8, 1.8)
    heading = -side * np.pi / 2 + rng.uniform(-0.3, 0.3)
    text = f"""
[[obstacles]]
id = "pedestrian"
shape = "circle"
radius = {rng.uniform(0.3, 0.5):.3f}
center = [{rng.uniform(35.0, 55.0):.3f}, {side * rng.uniform(3.0, 5.0):.3f}]
velocity = [{speed * np.cos(heading):.3f}, {speed * np.sin(heading):.3f}]
trigger = "move"
trigger_distance = {rng.uniform(20.0, 35.0):.3f}

[[obstacles]]
id = "slow_car"
shape = "box"
length = 4.5
width = 1.9
center = [{rng.uniform(75.0, 90.0):.3f}, {rng.uniform(-0.5, 0.5):.3f}]
velocity = [{rng.uniform(1.0, 3.0):.3f}, 0.0]
trigger = "move"
trigger_distance = {rng.uniform(20.0, 30.0):.3f}
"""
    if rng.random() < 0.5:
        text += f"""
[[obstacles]]
id = "barrel"
shape = "circle"
radius = 0.6
center = [{rng.uniform(60.0, 68.0):.3f}, {rng.uniform(-1.0, 1.0):.3f}]
"""
    return line_scenario_toml(f"variant{seed}", length=160.0, speed=6.944, t_max=60.0, obstacles=text)


def run_variant(seed: int, folder: Path) -> dict:
    f = folder / f"variant{seed}.toml"
    f.write_text(variant_toml(seed))
    scenario = load_scenario(f)
    controller = make_vflpc(scenario)
    record = run_closed_loop(scenario, controller, seed=seed)
    m = record.metrics
    nearest = np.nanmin(record.clearance, axis=0)
    worst = int(np.nanargmin(nearest))
    k = int(np.nanargmin(record.clearance[:, worst]))
    return {"seed": seed, "outcome": m["outcome"], "collisions": m["collisions"], "min_clearance": m["min_clearance"],
            "closest": scenario.obstacles[worst].id, "t_closest": float(record.t[k]),
            "speed_closest": float(np.linalg.norm(record.velocity[k])), "t_com": m["t_com"],
            "t_cal_median": m["t_cal_median"], "t_cal_p99": m["t_cal_p99"], "fallbacks": controller.fallbacks,
            "replan_failures": controller.replan_failures, "interventions": m["interventions"],
            "failsafe": m["failsafe"], "peak_lateral_error": m["peak_lateral_error"],
            "jerk_p99": m["jerk_p99"], "jerk_max": m["jerk_max"]}


def bench_variants(out: Path, n: int = 50, first_seed: int = 0) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    folder = out / "variants"
    folder.mkdir(exist_ok=True)
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)  # replan failures are counted per run
    rows = []
    print(f"{'seed':>4} {'outcome':<10} {'coll':>4} {'clear m':>8} {'closest':<11} {'at t s':>7} {'speed':>6} "
          f"{'t_cal med ms':>12} {'p99 ms':>7} {'replan fails':>12} {'interv':>6} {'peak lat':>8} "
          f"{'jerk p99':>8} {'jerk max':>8}")
    for seed in range(first_seed, first_seed + n):
        r = run_variant(seed, folder)
        rows.append(r)
        print(f"{seed:>4} {r['outcome']:<10} {r['collisions']:>4} {r['min_clearance']:>8.2f} {r['closest']:<11} "
              f"{r['t_closest']:>7.2f} {r['speed_closest']:>6.2f} {r['t_cal_median'] * 1e3:>12.3f} "
              f"{r['t_cal_p99'] * 1e3:>7.3f} {r['replan_failures']:>12} {r['interventions']:>6} "
              f"{r['peak_lateral_error']:>8.2f} {r['jerk_p99']:>8.2f} {r['jerk_max']:>8.2f}"
              + (f"  {r['failsafe']}" if r["failsafe"] else ""), flush=True)
    safe = sum(r["collisions"] == 0 for r in rows)
    done = sum(r["outcome"] == "completed" for r in rows)
    summary = {"variants": n, "without_collision": safe, "completed": done,
               "interventions": sum(r["interventions"] for r in rows),
               "seeds_with_collision": [r["seed"] for r in rows if r["collisions"]]}
    print(f"\n{safe}/{n} variants without collision, {done}/{n} completed, "
          f"{summary['interventions']} supervisor interventions; "
          f"collisions in seeds {summary['seeds_with_collision'] or 'none'}")
    (out / "bench_variants.json").write_text(json.dumps({"summary": summary, "runs": rows}, indent=2,
                                                        default=float) + "\n")
    print(f"wrote {out / 'bench_variants.json'}")
    return summary
