"""`vflpcd bench tick`: where a VF-LPC control tick spends its time, and how ticks and replans scale.

1. Breakdown. VF-LPC runs the closed loop of ``carsim_avoidance`` (the vehicle) and ``uav_3d``
   (the quadrotor); each phase of every ``step`` is timed by wrapping the controller method that
   does it: inputs (checks), guidance check (the first plan; whether a replan is due is checked
   after the command, in ``settle``, with the path projection, the solver shift and the GP sample,
   none of them in the step's time; the replan itself is background work, timed apart), reference
   (sampling the plan over the horizon), lift (window frame and Koopman lift of the robot and the
   reference), error model (the horizon problem, and its increment form), barrier (game region
   and the threats' safety points), solve (Eb-RHRL), and the rest of the step (the weights' mode,
   the divergence test, the clip into the actuator limits), which is the total less the phases.
   Where the horizon is one compiled call (``tick_horizon.CompiledHorizon``; the table says so)
   the solve's time holds the problem, its increment form and the clip, and the error model's
   only the GP's arrays gathered. Median and p99 per phase, in microseconds.
2. Scaling. A 200 m straight road at 25 km/h with N static posts beside the lane and M
   pedestrians crossing it ahead of the car (N in 0 .. 40, M in 0 .. 8): the tick's median and
   p99 and the background jobs' (replans) median, p99 and max per (N, M).

3. Paced. VF-LPC with the online GP on ``racing_track`` (the controller of ``vflpcd bench loop``)
   ticks back to back, as in the offline runner, and paced: each tick starts a 10 ms period and
   the rest of it is slept, as the daemon's 100 Hz loop does. Median and p99 of each, and each
   phase's median in both (the phase timers run in both): the same code on the same states takes
   longer after an idle gap (caches and predictors cooled), which is why the daemon's compute is
   not the offline tick's. Then the machine alone (``cold_calls``): a numpy add and a compiled call
   that does nothing, each the first call after a 10 ms sleep and the same call again at once.

JSON (the three tables and the machine's calls) and a PNG (the breakdown as bars, the scaling as
lines) go to --out.
"""

from __future__ import annotations

import json
import logging
import time
from functools import wraps
from pathlib import Path

import numpy as np

from sim.plot import save_png
from sim.runner import run_closed_loop
from vflpcd.config.scenarios import Scenario, line_scenario_toml, load_scenario
from vflpcd.controllers import make_controller
from vflpcd.core.control.tick_horizon import CompiledHorizon

PLATFORMS = (("vehicle", "carsim_avoidance"), ("quadrotor", "uav_3d"))
#: phase name -> (attribute path of the controller method that does it)
#: (the tick's horizon: its begin builds the problem call by call, ``ProblemHorizon``; a
#: ``CompiledHorizon``'s solve builds it, solves and clips the command in one compiled call)
PHASES = (("inputs", "_inputs"), ("guidance check", "_guidance"), ("reference", "_reference"),
          ("lift", "errors.frame"), ("error model", "_tick_horizon.begin"), ("barrier", "_barrier"),
          ("solve", "_tick_horizon.solve"))
RATE_PHASE = "error model"      # the increment form of the problem (each mode's RateForm.increments)
REST = "mode, checks, clip"
SCALING = ((0, 0), (10, 0), (20, 0), (40, 0), (10, 2), (10, 4), (10, 8), (40, 8))
PACED = ("racing_track", "vflpc_ml", 0.01)      # scene, controller, period s: the bench loop's
ROAD_M, SPEED = 200.0, 25.0 / 3.6


def _owner(obj, path: str):
    *parents, name = path.split(".")
    for p in parents:
        obj = getattr(obj, p, None)
        if obj is None:
            return None, name
    return obj, name


def timed_phases(controller) -> dict[str, list[float]]:
    """Wrap the phase methods of a VF-LPC controller (and its step) with timers; returns the
    per-tick seconds of each phase ("total" for the whole step), filled as the controller runs. A
    phase run inside another (the increment form, which the call-by-call horizon builds when a solve
    asks for it) counts in its own phase only."""
    ticks: dict[str, list[float]] = {"total": []}
    current: dict[str, float] = {}
    nested: list[float] = []        # per open timer, the seconds of the timers run inside it

    def wrap(fn, phase):
        @wraps(fn)
        def timed(*a, **k):
            nested.append(0.0)
            t0 = time.perf_counter_ns()
            try:
                return fn(*a, **k)
            finally:
                elapsed = (time.perf_counter_ns() - t0) * 1e-9
                current[phase] = current.get(phase, 0.0) + elapsed - nested.pop()     # its own time only
                if nested:
                    nested[-1] += elapsed
        return timed

    for phase, path in PHASES:
        owner, name = _owner(controller, path)
        if owner is not None and hasattr(owner, name):
            setattr(owner, name, wrap(getattr(owner, name), phase))
            ticks.setdefault(phase, [])
    modes = (getattr(controller, "_cruise_mode", None), getattr(controller, "_threat_mode", None),
             getattr(controller, "_light_mode", None), *(m for _, m in getattr(controller, "_slow_modes", ())))
    for mode in modes:
        if mode is not None and mode[0] is not None:            # (RateForm, solver); frozen, so set directly
            object.__setattr__(mode[0], "increments", wrap(mode[0].increments, RATE_PHASE))   # problem() calls it
    step = controller.step

    @wraps(step)
    def timed_step(*a, **k):
        current.clear()
        t0 = time.perf_counter_ns()
        u = step(*a, **k)
        total = (time.perf_counter_ns() - t0) * 1e-9
        ticks["total"].append(total)
        for phase in ticks:
            if phase not in ("total", REST):
                ticks[phase].append(current.get(phase, 0.0))
        ticks.setdefault(REST, []).append(total - sum(current.values()))
        return u

    controller.step = timed_step
    return ticks


def breakdown(scenario_name: str) -> dict:
    scenario = load_scenario(scenario_name)
    controller = make_controller("vflpc", scenario)
    ticks = timed_phases(controller)
    record = run_closed_loop(scenario, controller)
    stats = {phase: {"median_us": float(np.median(v) * 1e6), "p99_us": float(np.percentile(v, 99) * 1e6)}
             for phase, v in ticks.items() if v}
    return {"scenario": scenario.name, "ticks": len(ticks["total"]), "outcome": record.outcome, "phases": stats,
            "compiled_horizon": isinstance(controller._tick_horizon, CompiledHorizon)}


def paced(scenario: Scenario, name: str, period: float) -> dict:
    """Controller ``name``'s step times on ``scenario`` ticking back to back and paced (``period`` s
    from one tick's start to the next, the rest slept): per mode the ticks, their median and p99 us
    (``times``: every tick's seconds) and each phase's median us (``timed_phases``)."""
    out = {}
    for mode in ("back to back", "paced"):
        controller = make_controller(name, scenario)
        phases = timed_phases(controller)
        ticks: list[float] = []
        step = controller.step

        @wraps(step)
        def timed(*a, _step=step, _mode=mode, **k):
            if _mode == "paced" and ticks:
                time.sleep(max(period - ticks[-1], 0.0))
            t0 = time.perf_counter_ns()
            u = _step(*a, **k)
            ticks.append((time.perf_counter_ns() - t0) * 1e-9)
            return u

        controller.step = timed
        run_closed_loop(scenario, controller)
        out[mode] = {"ticks": len(ticks), "median_us": float(np.median(ticks) * 1e6),
                     "p99_us": float(np.percentile(ticks, 99) * 1e6), "times": ticks,
                     "phases_median_us": {p: float(np.median(v) * 1e6) for p, v in phases.items() if v}}
    return {"scenario": scenario.name, "controller": name, "period_s": period, "modes": out}


def cold_calls(period: float, samples: int = 200) -> dict:
    """The machine's cost of a call whose code went cold: a numpy add of two (21, 11) arrays and a
    compiled call that does nothing (numba; absent without it), each timed as the first call after
    sleeping ``period`` s and again at once; medians in us over ``samples`` sleeps."""
    a, out = np.ones((21, 11)), np.empty((21, 11))
    calls = {"numpy add (21 x 11)": lambda: np.add(a, a, out=out)}
    try:
        import numba
    except ImportError:
        numba = None
    if numba is not None:
        noop = numba.njit(lambda x: 0)
        noop(a)
        calls["compiled call, no work"] = lambda: noop(a)
    result = {}
    for label, call in calls.items():
        first, again = [], []
        for _ in range(samples):
            time.sleep(period)
            t0 = time.perf_counter_ns()
            call()
            t1 = time.perf_counter_ns()
            call()
            first.append(t1 - t0)
            again.append(time.perf_counter_ns() - t1)
        result[label] = {"after_sleep_us": float(np.median(first) * 1e-3), "again_us": float(np.median(again) * 1e-3)}
    return result


def scaling_scenario(posts: int, walkers: int) -> str:
    """TOML of the scaling road: posts alternately 3.5 m left and right of the lane every
    ROAD_M / (posts + 1) m, walkers crossing 60 .. 180 m ahead, each set off when the car is 35 m away."""
    text = ""
    for i in range(posts):
        x = (i + 1) * ROAD_M / (posts + 1)
        y = 3.5 if i % 2 == 0 else -3.5
        text += f'\n[[obstacles]]\nid = "post{i}"\nshape = "circle"\nradius = 0.2\ncenter = [{x:.2f}, {y}]\n'
    for j in range(walkers):
        x = 60.0 + j * 120.0 / max(walkers, 1)
        side = -6.0 if j % 2 == 0 else 6.0
        text += (f'\n[[obstacles]]\nid = "walker{j}"\nshape = "circle"\nradius = 0.35\ncenter = [{x:.2f}, {side}]\n'
                 f'velocity = [0.0, {-np.sign(side) * 1.4}]\ntrigger = "move"\ntrigger_distance = 35.0\n')
    return line_scenario_toml(f"scaling_{posts}_{walkers}", length=ROAD_M, speed=SPEED, t_max=ROAD_M / SPEED + 30.0,
                              obstacles=text)


def scaling(folder: Path) -> list[dict]:
    rows = []
    folder.mkdir(parents=True, exist_ok=True)
    for posts, walkers in SCALING:
        f = folder / f"scaling_{posts}_{walkers}.toml"
        f.write_text(scaling_scenario(posts, walkers))
        scenario = load_scenario(f)
        record = run_closed_loop(scenario, make_controller("vflpc", scenario))
        m = record.metrics
        rows.append({"static": posts, "movers": walkers, "outcome": record.outcome, "collisions": m["collisions"],
                     "min_clearance": m["min_clearance"], "J_MC": m["J_MC"],
                     "tick_median_ms": m["t_cal_median"] * 1e3, "tick_p99_ms": m["t_cal_p99"] * 1e3,
                     "replans": m["background_jobs"], "replan_median_ms": m["t_background_median"] * 1e3,
                     "replan_p99_ms": m["t_background_p99"] * 1e3, "replan_max_ms": m["t_background_max"] * 1e3})
    return rows


def plot(parts: dict, rows: list[dict], path: Path) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(13, 4.5))
    names = [p for p in next(iter(parts.values()))["phases"] if p != "total"]
    x = np.arange(len(names))
    for i, (platform, part) in enumerate(parts.items()):
        a.bar(x + (i - 0.5) * 0.4, [part["phases"].get(n, {}).get("median_us", 0.0) for n in names], 0.4,
              label=f"{platform} (total {part['phases']['total']['median_us']:.0f} us)")
    a.set_xticks(x, names, rotation=30, ha="right", fontsize=8)
    a.set(ylabel="median per tick (us)", title="VF-LPC tick breakdown")
    a.legend(fontsize=8)
    for walkers in sorted({r["movers"] for r in rows}):
        mine = [r for r in rows if r["movers"] == walkers]
        b.plot([r["static"] for r in mine], [r["replan_p99_ms"] for r in mine], "o-", label=f"replan p99, {walkers} movers")
    mine = [r for r in rows if r["movers"] == 0]
    b.plot([r["static"] for r in mine], [r["tick_median_ms"] for r in mine], "s--", label="tick median, no mover")
    b.set(xlabel="static obstacles", ylabel="ms", yscale="log", title="scaling (200 m road, 25 km/h)")
    b.legend(fontsize=8)
    fig.tight_layout()
    return save_png(fig, path, 100)


def bench_tick(out: Path) -> dict:
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)
    logging.getLogger("vflpcd.config.koopman_file").setLevel(logging.WARNING)
    parts = {platform: breakdown(name) for platform, name in PLATFORMS}
    phases = list(dict.fromkeys(p for part in parts.values() for p in part["phases"]))
    head = f"{'phase':<24}" + "".join(f" {platform + ' med/p99 us':>24}" for platform in parts)
    lines = ["Tick breakdown (VF-LPC)", head, "-" * len(head)]
    for phase in phases:
        cells = []
        for part in parts.values():
            s = part["phases"].get(phase)
            cells.append(f"{s['median_us']:.0f} / {s['p99_us']:.0f}" if s else "-")
        lines.append(f"{phase:<24}" + "".join(f" {c:>24}" for c in cells))
    lines.append("  " + ", ".join(f"{platform}: {part['scenario']} {part['ticks']} ticks, {part['outcome']}"
                                  for platform, part in parts.items()))
    compiled = [platform for platform, part in parts.items() if part["compiled_horizon"]]
    if compiled:
        lines.append(f"  {', '.join(compiled)}: the horizon in one compiled call (tick_horizon.CompiledHorizon): "
                     "the solve's time holds the error model's problem, its increment form and the clip")
    print("\n".join(lines), flush=True)
    rows = scaling(out / "scaling_scenarios")
    head = (f"{'static':>6} {'movers':>6} {'outcome':<10} {'coll':>4} {'clear m':>7} {'J_MC':>7} {'tick med ms':>11} "
            f"{'tick p99 ms':>11} {'replans':>7} {'replan med/p99/max ms':>22}")
    lines = ["", f"Scaling ({ROAD_M:.0f} m road at {SPEED * 3.6:.0f} km/h, posts beside the lane, pedestrians crossing)",
             head, "-" * len(head)]
    for r in rows:
        clear = "-" if r["min_clearance"] is None else f"{r['min_clearance']:.2f}"
        lines.append(f"{r['static']:>6} {r['movers']:>6} {r['outcome']:<10} {r['collisions']:>4} {clear:>7} "
                     f"{r['J_MC']:>7.3f} {r['tick_median_ms']:>11.3f} "
                     f"{r['tick_p99_ms']:>11.3f} {r['replans']:>7} "
                     f"{r['replan_median_ms']:>8.1f}/{r['replan_p99_ms']:.1f}/{r['replan_max_ms']:.1f}")
    print("\n".join(lines), flush=True)
    pace = paced(load_scenario(PACED[0]), *PACED[1:])
    lines = ["", f"Paced ({pace['controller']} on {pace['scenario']}, a tick every {pace['period_s'] * 1e3:.0f} ms "
                 "as in the daemon, against back to back)"]
    lines += [f"  {mode:<13} {m['ticks']:>5} ticks   median {m['median_us']:.0f} us   p99 {m['p99_us']:.0f} us"
              for mode, m in pace["modes"].items()]
    back, slept = (pace["modes"][m]["phases_median_us"] for m in ("back to back", "paced"))
    lines.append(f"  {'phase':<24} {'back to back':>12} {'paced':>8} {'ratio':>6}   (medians, us)")
    lines += [f"  {p:<24} {back[p]:>12.0f} {slept[p]:>8.0f} {slept[p] / back[p] if back[p] > 0 else np.nan:>6.1f}"
              for p in back if p in slept]
    cold = cold_calls(PACED[2])
    lines.append(f"  the machine: a call after a {PACED[2] * 1e3:.0f} ms sleep, and the same call again at once")
    lines += [f"  {label:<24} {c['after_sleep_us']:>8.1f} us   again {c['again_us']:.1f} us" for label, c in cold.items()]
    print("\n".join(lines), flush=True)
    doc = {"breakdown": parts, "scaling": rows, "paced": pace, "cold_calls": cold}
    out.mkdir(parents=True, exist_ok=True)
    (out / "bench_tick.json").write_text(json.dumps(doc, indent=2, default=float) + "\n")
    png = plot(parts, rows, out / "bench_tick.png")
    print(f"wrote {out / 'bench_tick.json'}\nwrote {png}")
    return doc
