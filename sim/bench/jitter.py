"""`vflpcd bench jitter`: a controller on jittered copies of the road suite's scenes.

The suite's scenes are fixed; a controller tuned on them may fail on the same kinds of scene laid
out a little differently. Each copy (seeded, reproducible) moves every static obstacle along the
route by up to 2 m and across it by up to 0.4 m, every mover's start by up to 3 m and 0.3 m and its
speed by up to 20 %, and the desired and start speeds by up to 15 % (all times ``--scale``;
positions in the route's frame, so a bend's obstacle stays in the bend). A copy that puts an
obstacle on the start or the goal is drawn again. Each copy's TOML is written to the output folder,
so a failure can be run again with `vflpcd sim FILE`. Per run it prints the outcome, collisions,
least clearance, J_MC, peak lateral error, failed replans and the failsafe's reason; then the runs
completed without a collision, the collisions and the files of the runs that were not. JSON and a
PNG (least clearance per run, by scene and outcome) go to --out.
"""

from __future__ import annotations

import json
import logging
import tomllib
from pathlib import Path

import numpy as np

from sim.bench.impc import run_one
from sim.bench.suite import suite_dir, suite_names
from sim.plot import save_png
from vflpcd.base.errors import ConfigError
from vflpcd.config.scenarios import load_scenario

DRAWS = 20  # draws per copy before one that leaves the start and the goal free is given up


def toml_text(doc: dict) -> str:
    """A scenario document (tables, arrays of tables, numbers, strings, booleans, lists) as TOML."""
    def value(v) -> str:
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, (int, float)):
            return repr(v)
        if isinstance(v, str):
            return json.dumps(v)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        raise TypeError(f"no TOML for {type(v).__name__} {v!r}")

    def table(d: dict) -> list[str]:
        return [f"{k} = {value(v)}" for k, v in d.items()]

    lines = table({k: v for k, v in doc.items() if not isinstance(v, dict) and not _tables(v)})
    for k, v in doc.items():
        if isinstance(v, dict):
            lines += ["", f"[{k}]"] + table(v)
        elif _tables(v):
            for item in v:
                lines += ["", f"[[{k}]]"] + table(item)
    return "\n".join(lines) + "\n"


def _tables(v) -> bool:
    return isinstance(v, list) and bool(v) and all(isinstance(x, dict) for x in v)


def jittered(doc: dict, path, rng: np.random.Generator, scale: float) -> dict:
    """A copy of the scenario document ``doc`` (its route ``path``) with the obstacles and speeds
    moved as the module docstring says, drawn from ``rng``."""
    out = json.loads(json.dumps(doc))
    f = 1.0 + rng.uniform(-0.15, 0.15) * scale
    out["speed"]["desired"] = round(doc["speed"]["desired"] * f, 3)
    out["start"]["speed"] = round(doc["start"]["speed"] * f, 3)
    out["t_max"] = round(doc["t_max"] * 1.3 / f, 1)
    for o in out.get("obstacles", []):
        moving = any(abs(x) > 0.0 for x in o.get("velocity", [0.0]))
        along, across = (3.0, 0.3) if moving else (2.0, 0.4)
        c = np.asarray(o["center"], float)
        proj = path.project(c[:2])
        s = float(np.clip(proj.s + rng.uniform(-along, along) * scale, 0.0, path.length))
        lateral = proj.lateral + rng.uniform(-across, across) * scale
        psi = float(path.heading_at(s))
        xy = path.point_at(s) + lateral * np.array([np.sin(psi), -np.cos(psi)])   # lateral: to the right
        o["center"] = [round(float(xy[0]), 3), round(float(xy[1]), 3)] + [float(z) for z in c[2:]]
        if moving:
            o["velocity"] = [round(x * (1.0 + rng.uniform(-0.2, 0.2) * scale), 3) for x in o["velocity"]]
    return out


def jittered_scene(name: str, seed: int, scale: float, folder: Path) -> Path:
    """Write copy ``seed`` of suite scene ``name`` to ``folder`` (drawn again while it puts an
    obstacle on the start or the goal) and return its file."""
    source = suite_dir() / f"{name}.toml"
    doc = tomllib.loads(source.read_text())
    path = load_scenario(source).path
    rng = np.random.default_rng([seed, sum(map(ord, name))])
    folder.mkdir(parents=True, exist_ok=True)
    f = folder / f"{name}-{seed}.toml"
    for _ in range(DRAWS):
        copy = jittered(doc, path, rng, scale)
        copy["name"] = f"{name}-{seed}"
        f.write_text(f"# bench jitter: {name}, seed {seed}, scale {scale:g}\n" + toml_text(copy))
        try:
            load_scenario(f)
            return f
        except ConfigError:
            continue
    raise ConfigError(str(f), "obstacles", f"no copy in {DRAWS} draws leaves the start and the goal free")


def bench_jitter(out: Path, n: int = 3, first_seed: int = 0, scale: float = 1.0, controller: str = "vflpc",
                 only: tuple[str, ...] | None = None) -> dict:
    """Run ``controller`` on ``n`` jittered copies of every (or ``only`` these) suite scenes; print,
    write JSON and PNG."""
    logging.getLogger("vflpcd.core.vflpc").setLevel(logging.ERROR)     # failed replans are counted per run
    logging.getLogger("vflpcd.config.koopman_file").setLevel(logging.WARNING)
    folder = out / "jitter"
    folder.mkdir(parents=True, exist_ok=True)
    head = (f"{'scene':<24} {'seed':>4} {'outcome':<10} {'coll':>4} {'clear m':>8} {'J_MC':>7} {'peak lat':>8} "
            f"{'replan fails':>12}  failsafe")
    print(head + "\n" + "-" * len(head), flush=True)
    rows = []
    for name in only or suite_names():
        for seed in range(first_seed, first_seed + n):
            f = jittered_scene(name, seed, scale, folder)
            m = run_one("jitter", controller, load_scenario(f)).metrics
            r = {"scene": name, "seed": seed, "file": str(f), **{k: m.get(k) for k in (
                "outcome", "collisions", "min_clearance", "J_MC", "peak_lateral_error", "replan_failures", "failsafe")}}
            rows.append(r)
            print(f"{name:<24} {seed:>4} {r['outcome']:<10} {r['collisions']:>4} {r['min_clearance']:>8.3f} "
                  f"{r['J_MC']:>7.3f} {r['peak_lateral_error']:>8.2f} {r['replan_failures'] or 0:>12}  "
                  f"{r['failsafe'] or ''}"[:220], flush=True)
    clean = [r["outcome"] == "completed" and r["collisions"] == 0 for r in rows]
    summary = {"controller": controller, "scale": scale, "runs": len(rows), "completed_without_collision": sum(clean),
               "collisions": sum(r["collisions"] for r in rows),
               "not_clean": [r["file"] for r, ok in zip(rows, clean) if not ok]}
    print(f"\n{sum(clean)}/{len(rows)} runs completed without a collision, {summary['collisions']} collisions"
          + "".join(f"\n  not clean: {f}" for f in summary["not_clean"]))
    (out / "bench_jitter.json").write_text(json.dumps({"summary": summary, "runs": rows}, indent=2,
                                                      default=float) + "\n")
    png = plot(rows, out / "bench_jitter.png")
    print(f"wrote {out / 'bench_jitter.json'}\nwrote {png}")
    return summary


def plot(rows: list[dict], out: Path) -> Path:
    """Least clearance of every run by scene: completed without a collision, not completed, collided."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(dict.fromkeys(r["scene"] for r in rows))
    fig, ax = plt.subplots(figsize=(12, 4.5))
    for r in rows:
        x = names.index(r["scene"])
        kind = ("collision", "C3", "x") if r["collisions"] else (
            ("completed", "C0", "o") if r["outcome"] == "completed" else ("not completed", "C1", "s"))
        ax.plot(x, r["min_clearance"], kind[2], color=kind[1], label=kind[0])
    handles = dict(zip(*reversed(ax.get_legend_handles_labels())))
    ax.legend(handles.values(), handles.keys(), fontsize=8)
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xticks(range(len(names)), names, rotation=20, ha="right", fontsize=8)
    ax.set(ylabel="least clearance (m)", title="jittered copies of the road suite")
    fig.tight_layout()
    return save_png(fig, out, 90)
