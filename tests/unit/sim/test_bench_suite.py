"""`vflpcd bench suite`: its totals on made-up rows, and the suite's scenario files."""

import math

import numpy as np
import pytest

from sim.bench.suite import load, suite_dir, suite_names, totals, totals_text
from sim.runner import job_times
from vflpcd.config.vehicles import BicycleConfig


def row(scenario, controller, outcome="completed", collisions=0, J=1.0, peak=0.5):
    return {"scenario": scenario, "controller": controller, "outcome": outcome, "collisions": collisions,
            "J_MC": J, "peak_lateral_error": peak}


def test_totals_count_clean_runs_collisions_and_the_lowest_j_mc_among_clean_runs():
    rows = [
        # a: NMPC lowest, but it collided; among the clean runs VF-LPC is lowest
        row("a", "vflpc", J=0.5), row("a", "nmpc_cbf", "collision", 1, J=0.1), row("a", "koopman_mpc", J=0.7),
        row("a", "pure_pursuit", "stopped", J=0.05),
        # b: a tie between the Koopman-MPC and pure pursuit; VF-LPC 1.2 m wider than the NMPC
        row("b", "vflpc", J=0.9, peak=2.3), row("b", "nmpc_cbf", J=0.8, peak=1.1), row("b", "koopman_mpc", J=0.3),
        row("b", "pure_pursuit", J=0.3),
        # c: nobody completes cleanly; VF-LPC only 0.9 m wider than the NMPC
        row("c", "vflpc", "failsafe", J=0.2, peak=1.9), row("c", "nmpc_cbf", "timeout", J=0.2, peak=1.0),
        row("c", "koopman_mpc", "collision", 2, J=0.2), row("c", "pure_pursuit", "collision", 1, J=0.2),
    ]
    t = totals(rows, ("vflpc", "nmpc_cbf", "koopman_mpc", "pure_pursuit"))
    c = t["controllers"]
    assert {k: v["clean"] for k, v in c.items()} == {"vflpc": 2, "nmpc_cbf": 1, "koopman_mpc": 2, "pure_pursuit": 1}
    assert {k: v["collisions"] for k, v in c.items()} == {"vflpc": 0, "nmpc_cbf": 1, "koopman_mpc": 2,
                                                          "pure_pursuit": 1}
    assert {k: v["lowest_J_MC"] for k, v in c.items()} == {"vflpc": 1, "nmpc_cbf": 0, "koopman_mpc": 1,
                                                           "pure_pursuit": 1}
    assert t["vflpc_peak_lateral_over_nmpc"] == ["b"] and t["scenes"] == 3
    text = totals_text(t)
    assert "completed without collision 2/3, collisions 0, lowest J_MC among the clean runs in 1" in text
    assert "VF-LPC peak lateral error > NMPC's + 1 m in 1 scenes: b (the NMPC completed)" in text


def test_the_peak_lateral_comparison_says_where_the_nmpc_stopped_short():
    rows = [row("a", "vflpc", peak=1.8), row("a", "nmpc_cbf", "stopped", peak=0.0),
            row("b", "vflpc", peak=3.5), row("b", "nmpc_cbf", peak=0.8), row("c", "vflpc"), row("c", "nmpc_cbf")]
    t = totals(rows, ("vflpc", "nmpc_cbf"))
    assert t["vflpc_peak_lateral_over_nmpc"] == ["a", "b"] and t["nmpc_outcome"] == {"a": "stopped", "b": "completed"}
    assert "in 2 scenes: a (the NMPC stopped), b (the NMPC completed)" in totals_text(t)


def test_totals_without_the_nmpc_have_no_peak_comparison_and_nan_j_mc_never_wins():
    rows = [row("a", "vflpc", J=float("nan")), row("a", "pure_pursuit", J=2.0)]
    t = totals(rows, ("vflpc", "pure_pursuit"))
    assert t["vflpc_peak_lateral_over_nmpc"] is None
    assert t["controllers"]["vflpc"]["lowest_J_MC"] == 0 and t["controllers"]["pure_pursuit"]["lowest_J_MC"] == 1
    assert "peak lateral" not in totals_text(t)


def test_background_jobs_are_pooled_over_the_scenes_per_controller():
    # a scene runs a handful of replans, so its own p99 is its maximum: the totals take them together
    a, b = row("a", "vflpc"), row("b", "vflpc")
    a["background_s"] = job_times([0.0, 0.010, 0.0, 0.030]).tolist()
    b["background_s"] = job_times(np.r_[np.full(97, 0.020), 0.040, 0.0, 0.090]).tolist()
    nm = row("a", "nmpc_cbf")
    nm["background_s"] = []
    t = totals([a, b, nm], ("vflpc", "nmpc_cbf"))
    bg = t["controllers"]["vflpc"]["background"]
    assert a["background_s"] == [0.010, 0.030] and bg["jobs"] == 101
    assert bg["median"] == 0.020 and bg["max"] == 0.090
    assert bg["p99"] == pytest.approx(0.040)      # the 100th of 101 in order: not the one 90 ms job
    assert t["controllers"]["nmpc_cbf"]["background"] is None
    text = totals_text(t)
    assert f"background jobs 101: 20 / {bg['p99'] * 1e3:.0f} / 90 ms" in text
    assert text.count("background jobs") == 1


def test_the_suite_has_at_least_14_ground_scenes_named_as_their_files():
    names = suite_names()
    assert len(names) >= 14
    assert sorted(p.stem for p in suite_dir().glob("*.toml")) == list(names)


@pytest.mark.parametrize("name", suite_names())
def test_every_suite_scene_loads_fairly_and_leaves_the_start_free(name):
    sc = load(name)
    assert sc.name == name and sc.description and "\n" not in sc.description
    assert (sc.platform, sc.plant, sc.params, sc.control_period) == ("ground", "dynamic_bicycle", "nominal", 0.05)
    assert 1.5 <= sc.v_desired <= 8.0
    assert sc.t_max >= math.floor(2 * sc.goal_at / sc.v_desired + 10.0)
    assert (sc.weights.q1, sc.weights.q2) == (1.0, 1.0) and np.allclose(sc.weights.R, [[0.1, 0.0], [0.0, 1.0]])
    position, yaw = sc.start[:2], sc.start[2]
    for o in sc.obstacles:
        if o.trigger != "appear":                    # present at t = 0: must not touch the body at the start
            assert sc.footprint.clearance(o.shape, o.center, o.yaw, position, yaw) > 0.5, o.id
        else:
            assert 12.0 <= o.trigger_distance <= 18.0


def test_the_gap_between_the_parked_cars_is_a_metre_wider_than_the_car():
    sc = load("narrow_gap_parked")
    width = BicycleConfig.load("nominal").body.width
    left = min(o.center[1] - o.shape.width / 2 for o in sc.obstacles if o.center[1] > 0)
    right = max(o.center[1] + o.shape.width / 2 for o in sc.obstacles if o.center[1] < 0)
    assert left - right >= width + 1.0
    assert right < 0.0 < left                        # the path runs through the gap
