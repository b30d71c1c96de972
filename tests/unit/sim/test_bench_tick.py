"""`vflpcd bench tick`: the phase timers add up to the tick, and the scaling scenes hold what they say."""

import numpy as np

import time

from sim.bench.tick import REST, paced, scaling_scenario, timed_phases
from sim.runner import run_closed_loop
from vflpcd.config.scenarios import load_scenario
from vflpcd.controllers import make_controller
from vflpcd.core.control.tick_horizon import ProblemHorizon


def test_the_phases_of_every_tick_add_up_to_its_total(line_scenario):
    s = line_scenario("tick_line", length=30.0)
    ctrl = make_controller("vflpc", s)
    ticks = timed_phases(ctrl)
    rec = run_closed_loop(s, ctrl)
    assert rec.outcome == "completed"
    n = len(ticks["total"])
    assert n == len(rec.t) and n > 50                  # every step was timed
    phases = [p for p in ticks if p != "total"]
    assert {"inputs", "reference", "lift", "error model", "barrier", "solve", REST} <= set(phases)
    assert all(len(ticks[p]) == n for p in phases)
    np.testing.assert_allclose(np.sum([ticks[p] for p in phases], axis=0), ticks["total"], rtol=1e-9, atol=1e-12)
    assert np.all(np.array(ticks["solve"]) > 0.0) and np.median(ticks["solve"]) < np.median(ticks["total"])


def test_the_error_model_phase_times_every_modes_increment_form(line_scenario):
    """On the call-by-call horizon, the increment form (``RateForm.increments``, which its solve asks
    for) of every weight mode a tick may solve with (cruise, light, threat, the slow bands) is timed
    in the error model's phase, not in the solve's or the rest."""
    s = line_scenario("tick_modes", length=30.0)
    ctrl = make_controller("vflpc", s)
    ctrl._tick_horizon = ProblemHorizon(ctrl.errors, ctrl._command_loop)
    forms = [m[0] for m in (ctrl._cruise_mode, ctrl._light_mode, ctrl._threat_mode, *(m for _, m in ctrl._slow_modes))
             if m is not None]
    assert len(forms) >= 3
    ticks = timed_phases(ctrl)
    assert all(hasattr(f.increments, "__wrapped__") for f in forms)
    run_closed_loop(s, ctrl)
    assert np.all(np.array(ticks["error model"]) > 0.0)
    phases = [p for p in ticks if p != "total"]
    np.testing.assert_allclose(np.sum([ticks[p] for p in phases], axis=0), ticks["total"], rtol=1e-9, atol=1e-12)
    assert np.all(np.array(ticks[REST]) >= 0.0)           # no phase counted twice


def test_the_scaling_road_has_its_posts_beside_the_lane_and_its_walkers_crossing(tmp_path):
    f = tmp_path / "scaling.toml"
    f.write_text(scaling_scenario(40, 8))
    s = load_scenario(f)
    posts = [o for o in s.obstacles if o.id.startswith("post")]
    walkers = [o for o in s.obstacles if o.id.startswith("walker")]
    assert len(posts) == 40 and len(walkers) == 8
    assert all(abs(o.center[1]) == 3.5 and 0.0 < o.center[0] < s.path.length for o in posts)
    assert all(o.velocity[1] * o.center[1] < 0.0 for o in walkers)         # each walks towards the lane


def test_paced_ticks_are_timed_a_period_apart_and_back_to_back_ones_are_not(line_scenario):
    """Both runs time every tick of the same closed loop; the paced one sleeps the rest of each
    period, so it lasts at least the ticks' periods."""
    s = line_scenario("paced_line", length=20.0)
    t0 = time.perf_counter()
    back = paced(s, "vflpc", 0.0)["modes"]
    t1 = time.perf_counter()
    out = paced(s, "vflpc", 0.02)
    t2 = time.perf_counter()
    runs = out["modes"]
    assert runs["back to back"]["ticks"] == runs["paced"]["ticks"] == back["paced"]["ticks"] > 50
    n = runs["paced"]["ticks"]
    assert t2 - t1 >= 0.02 * (n - 1) > t1 - t0
    times = np.array(runs["paced"]["times"])
    assert np.all(times > 0.0)
    assert np.median(times) < 0.5 * 0.02           # the tick alone: a timed sleep would reach the period


def test_each_phase_is_timed_in_both_paced_modes(line_scenario):
    """The paced comparison carries every phase's median in both modes: the solve's below the
    step's, the step's within the timed tick's (the timers run inside it)."""
    s = line_scenario("paced_phases", length=20.0)
    runs = paced(s, "vflpc", 0.0)["modes"]
    for mode in ("back to back", "paced"):
        phases = runs[mode]["phases_median_us"]
        assert {"total", "inputs", "lift", "error model", "solve", REST} <= set(phases)
        assert all(v >= 0.0 for v in phases.values())
        assert 0.0 < phases["solve"] < phases["total"] <= runs[mode]["median_us"] * 1.5


def test_the_cold_call_probe_times_each_call_after_a_sleep_and_again():
    from sim.bench.tick import cold_calls

    t0 = time.perf_counter()
    out = cold_calls(0.002, samples=20)
    assert time.perf_counter() - t0 >= 20 * 0.002 * len(out)        # it slept before every first call
    assert "numpy add (21 x 11)" in out
    for c in out.values():
        assert 0.0 < c["again_us"] and 0.0 < c["after_sleep_us"] < 2000.0
