"""Text table and JSON file of a run's metrics."""

from __future__ import annotations

import json
from pathlib import Path

from sim.runner import RunRecord
from vflpcd.config.scenarios import Scenario


def _fmt(value, unit: str = "", scale: float = 1.0, digits: int = 3) -> str:
    if value is None:
        return "n/a"
    return f"{value * scale:.{digits}f}{unit}"


def metrics_table(record: RunRecord, scenario: Scenario) -> str:
    """A two-column table of the run's metrics."""
    m = record.metrics
    rows = [
        ("scenario", f"{scenario.name} ({scenario.platform}, {scenario.plant}/{scenario.params})"),
        ("controller", f"{record.controller} (seed {record.seed})"),
        ("outcome", f"{record.outcome} after {m['steps']} steps" + (f" ({record.failsafe})" if record.failsafe else "")),
        ("supervisor interventions", f"{m['interventions']} ({m['override_ticks']} ticks overridden; "
                                     f"{m['t_sup_median'] * 1e6:.0f} / {m['t_sup_p99'] * 1e6:.0f} us median / p99)"),
        ("J_MC", _fmt(m["J_MC"], digits=4)),
        ("  J_Lat / J_Heading / J_Con", f"{m['J_Lat']:.4f} / {m['J_Heading']:.4f} / {m['J_Con']:.4f}"),
        ("L_p", _fmt(m["L_p"], " m", digits=2)),
        ("t_com", _fmt(m["t_com"], " s", digits=2)),
        ("t_cal median / p99", f"{m['t_cal_median'] * 1e3:.3f} / {m['t_cal_p99'] * 1e3:.3f} ms"),
        ("min clearance", _fmt(m["min_clearance"], " m", digits=2)),
        ("collisions", str(m["collisions"]) + (f" (first at {m['impact_speed']:.2f} m/s)"
                                               if m["impact_speed"] is not None else "")),
        ("RMS / peak lateral error", f"{_fmt(m['rms_lateral_error'], digits=3)} / "
                                     f"{_fmt(m['peak_lateral_error'], ' m', digits=3)}"),
        ("peak lateral acceleration", _fmt(m["peak_lateral_acceleration"], " m/s^2", digits=2)),
        ("longitudinal jerk p99 / max", f"{_fmt(m['jerk_p99'], digits=3)} / {_fmt(m['jerk_max'], ' m/s^3', digits=3)}"),
    ]
    for o, c in zip(scenario.obstacles, m["min_clearance_per_obstacle"]):
        rows.append((f"  clearance to {o.id}", _fmt(c, " m", digits=2) if c is not None else "never present"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)


def write_results(record: RunRecord, scenario: Scenario, path: str | Path) -> Path:
    """results.json: what was run and every metric."""
    path = Path(path)
    doc = {
        "scenario": scenario.name, "scenario_file": str(scenario.file), "controller": record.controller,
        "seed": record.seed, "plant": scenario.plant, "params": scenario.params,
        "control_period": scenario.control_period, "outcome": record.outcome,
        "obstacles": [o.id for o in scenario.obstacles], "metrics": record.metrics,
    }
    path.write_text(json.dumps(doc, indent=2) + "\n")
    return path
