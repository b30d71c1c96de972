"""`vflpcd sim` as a user runs it: a real process, its table, its files."""

import json
import os
import subprocess
import sys
from pathlib import Path

VFLPCD = [sys.executable, "-m", "vflpcd.app.cli"]


def refused(args: list[str]) -> list[str]:
    """Run ``vflpcd args``, which must exit 2 with nothing on stdout; its stderr lines."""
    proc = subprocess.run(VFLPCD + args, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stdout == "", proc.stderr
    return proc.stderr.strip().splitlines()


def test_sim_carsim_avoidance_pure_pursuit_stops_behind_the_supervisor(tmp_path):
    # pure pursuit does not avoid anything: the supervisor stops it in front of the parked car
    out = tmp_path / "run"
    proc = subprocess.run(VFLPCD + ["sim", "carsim_avoidance", "--controller", "pure_pursuit", "--out", str(out)],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 3, proc.stderr
    for label in ("J_MC", "L_p", "t_com", "t_cal median / p99", "min clearance", "collisions",
                  "supervisor interventions"):
        assert label in proc.stdout
    doc = json.loads((out / "results.json").read_text())
    assert doc["scenario"] == "carsim_avoidance" and doc["controller"] == "pure_pursuit"
    m = doc["metrics"]
    assert m["outcome"] == "stopped" and m["collisions"] == 0 and m["interventions"] >= 1
    assert "parked_car" in m["failsafe"] and 0.0 < m["min_clearance"] < 1.5
    assert len(m["min_clearance_per_obstacle"]) == 5
    png = (out / "plot.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 50_000


def test_sim_without_the_supervisor_reports_the_collision_and_exits_5(tmp_path):
    out = tmp_path / "bare"
    proc = subprocess.run(VFLPCD + ["sim", "carsim_avoidance", "--controller", "pure_pursuit", "--no-supervisor",
                                    "--no-plot", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 5, proc.stderr
    m = json.loads((out / "results.json").read_text())["metrics"]
    assert m["outcome"] == "collision" and m["collisions"] >= 1 and 240.0 < m["L_p"] < 260.0
    assert "first at 6.94 m/s" in proc.stdout


def test_bad_scenario_file_exits_2_in_one_line(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text('name = "x"\nplatform = "boat"\n')
    proc = subprocess.run(VFLPCD + ["sim", str(bad)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert lines == [f"vflpcd: error: {bad}: platform: expected one of ground, aerial, got 'boat'"]
    assert proc.stdout == ""
    assert not Path("results").joinpath("x-pure_pursuit-s0").exists()


def test_bench_guidance_prints_the_planning_table_and_writes_json_and_png(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "guidance", "--repeat", "3", "--astar-repeat", "1", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    for label in ("L_p (m)", "t_cal median (s)", "SD (clearance >= 0 m)", "min clearance (m)", "grid precompute",
                  "peak curvature"):
        assert label in proc.stdout
    doc = json.loads((tmp_path / "bench_guidance.json").read_text())
    gvf, astar = doc["planners"]["VF-LPC guidance"], doc["planners"]["Hybrid A*"]
    assert doc["planners"]["VF-LPC guidance (virtual)"]["virtual_obstacles"] > 0
    assert gvf["reached_goal"] and astar["success"]
    assert gvf["t_cal_runs"] == 3 and gvf["grid_precompute_median"] > 0
    assert gvf["max_v2_kappa_over_a_max"] <= 1.01
    assert 45.0 < gvf["L_p"] < 52.0 and 45.0 < astar["L_p"] < 52.0       # both to the goal at 47 m
    assert (tmp_path / "bench_guidance.png").read_bytes()[:4] == b"\x89PNG"


def test_bench_loop_refuses_a_bad_baseline_in_one_line(tmp_path):
    for bad in ("-1", "nan", "0.5", "601"):
        (line,) = refused(["bench", "loop", "--baseline", bad, "--duration", "1", "--out", str(tmp_path)])
        assert "--baseline" in line and "expected 0 (none) or 1 to 600 seconds" in line
    assert not (tmp_path / "bench_loop.json").exists()


def test_bench_guidance_refuses_an_aerial_scenario(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "guidance", "--scenario", "uav_3d", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and "needs a ground scenario" in proc.stderr


def test_collect_through_the_vflpcd_command(tmp_path):
    proc = subprocess.run(VFLPCD + ["collect", "dynamic_bicycle", "--minutes", "0.1", "--seed", "3", "--out",
                                    str(tmp_path)], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    (log,) = sorted(tmp_path.glob("*.npz"))
    from vflpcd.training.datasets import load_log

    assert load_log(log).states.shape == (120, 6)
    bad = subprocess.run(VFLPCD + ["collect", "submarine", "--minutes", "1"], capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "unknown plant 'submarine'" in bad.stderr


def test_bench_dynamics_measures_and_compensation_halves_the_one_step_error(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "dynamics", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    for label in ("encoder + lift", "GP mean + Jacobian", "GP full refit", "one-step RMSE", "1-s open-loop RMSE",
                  "steering response"):
        assert label in proc.stdout
    doc = json.loads((tmp_path / "bench_dynamics.json").read_text())
    assert [r["speed"] for r in doc["steering_response"]] == [1.5, 3.0, 6.0, 10.0, 15.0]
    from vflpcd.controllers.vflpc import load_params

    shipped = load_params("ground")                         # the bench measures the GP that vflpc_ml ships
    assert doc["timings"]["gp_inducing"] == shipped.gp_m_max and doc["timings"]["gp_samples"] == shipped.gp_n_max
    assert doc["timings"]["gp_outputs"] == len(shipped.gp_channels)
    for demo in doc["compensation"]:
        one = demo["one_step_rmse"]
        assert demo["gp_fitted"] and demo["learn_samples"] > 100
        for channel in ("vy", "omega"):
            assert one["compensated"][channel] <= 0.5 * one["nominal"][channel]


def test_train_koopman_through_the_vflpcd_command(tmp_path):
    data = tmp_path / "logs"
    assert subprocess.run(VFLPCD + ["collect", "dynamic_bicycle", "--minutes", "3", "--out", str(data)],
                          capture_output=True, timeout=120).returncode == 0
    out = tmp_path / "model.npz"
    proc = subprocess.run(VFLPCD + ["train", "koopman", "--data", str(data), "--val", "dynamic_bicycle_0_002",
                                    "--n-lift", "10", "--epochs", "3", "--windows-per-epoch", "256", "--no-compare",
                                    "--quiet", "--out", str(out)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    from vflpcd.config.koopman_file import load_koopman

    model = load_koopman(out, state_names=("X", "Y", "psi", "vx", "vy", "omega"), control_names=("a_x", "delta_f"))
    assert model.n_K == 10
    manifest = json.loads(out.with_suffix(".manifest.json").read_text())
    assert manifest["seed"] == 0
    bad = subprocess.run(VFLPCD + ["train", "koopman", "--data", str(data), "--val", "nope", "--n-lift", "10",
                                   "--out", str(out)], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1


def test_bench_safety_runs_a_scene_with_and_without_the_supervisor_and_writes_json_and_png(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "safety", "--scene", "wall_across", "--controller", "pure_pursuit",
                                    "--out", str(tmp_path)], capture_output=True, text=True, timeout=300,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    assert "supervisor cost per tick" in proc.stdout and "[met] zero collisions behind the supervisor" in proc.stdout
    doc = json.loads((tmp_path / "bench_safety.json").read_text())
    on, off = doc["runs"]
    assert on["supervised"] and on["outcome"] == "stopped" and on["collisions"] == 0 and 0 < on["rest_gap"] < 1.5
    assert not off["supervised"] and off["outcome"] == "collision" and off["impact_speed"] > 6.0
    assert doc["supervisor_us"]["ticks"] > 100 and doc["supervisor_us"]["median"] > 0
    assert (tmp_path / "bench_safety.png").read_bytes()[:4] == b"\x89PNG"


def test_bench_safety_refuses_an_unknown_scene_in_one_line(tmp_path):
    assert refused(["bench", "safety", "--scene", "nope", "--out", str(tmp_path)]) == [
        "vflpcd: error: command line: --scene: no such scene 'nope' (have: wall_across, narrow_turn, "
        "pedestrian_close, tight_gap, dense_corridor, cut_in)"]


def test_bench_ml_runs_both_models_on_the_exact_vehicle_and_writes_json_and_png(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "ml", "--seeds", "1", "--out", str(tmp_path)], capture_output=True,
                          text=True, timeout=300, env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    doc = json.loads((tmp_path / "bench_ml.json").read_text())
    wo, w = doc["runs"]
    assert (wo["label"], w["label"]) == ("w/o ML", "w/ ML") and doc["params"] == "exact" and doc["laps"] == 2
    assert wo["refits"] == 0 and w["refits"] > 0                       # the GP learned during the run
    assert all(r["outcome"] == "completed" and r["collisions"] == 0 and r["rms_lateral_lap2"] > 0 for r in (wo, w))
    assert doc["rms_lap2_reduction"] == 1.0 - w["rms_lateral_lap2"] / wo["rms_lateral_lap2"]
    assert "means over 1 seeds" in proc.stdout
    assert (tmp_path / "bench_ml.png").read_bytes()[:4] == b"\x89PNG"


def test_bench_ml_refuses_a_single_lap_in_one_line(tmp_path):
    assert refused(["bench", "ml", "--laps", "1", "--out", str(tmp_path)]) == [
        "vflpcd: error: command line: --seeds/--laps: expected at least one seed and two laps (lap 2 is measured)"]


def test_bench_suite_runs_one_scene_with_pure_pursuit_and_writes_json_and_png(tmp_path):
    proc = subprocess.run(VFLPCD + ["bench", "suite", "--only", "oncoming_car", "--controllers", "pure_pursuit",
                                    "--out", str(tmp_path)], capture_output=True, text=True, timeout=120,
                          env={**os.environ, "MPLBACKEND": "Agg"})
    assert proc.returncode == 0, proc.stderr
    for label in ("scenario", "outcome", "clear m", "J_MC", "RMS lat", "peak lat", "jerk p99", "t_cal ms",
                  "totals over 1 scenes", "completed without collision 1/1"):
        assert label in proc.stdout
    doc = json.loads((tmp_path / "bench_suite.json").read_text())
    (r,) = doc["rows"]
    assert (r["scenario"], r["controller"], r["outcome"], r["collisions"]) == ("oncoming_car", "pure_pursuit",
                                                                               "completed", 0)
    assert r["min_clearance"] > 0.5 and r["t_cal_median"] > 0
    pp = doc["totals"]["controllers"]["pure_pursuit"]
    assert pp == {"clean": 1, "collisions": 0, "lowest_J_MC": 1, "runs": 1, "background": None}   # no replans
    assert r["background_s"] == []
    assert doc["totals"]["vflpc_peak_lateral_over_nmpc"] is None
    assert (tmp_path / "bench_suite.png").read_bytes()[:4] == b"\x89PNG"


def test_bench_suite_refuses_an_unknown_scene_and_controller_in_one_line(tmp_path):
    (line,) = refused(["bench", "suite", "--only", "oncoming_car", "nope", "--out", str(tmp_path)])
    assert line.startswith("vflpcd: error: command line: --only: no such suite scenario 'nope' (have: ")
    assert "slalom_cones" in line
    (line,) = refused(["bench", "suite", "--controllers", "vflpc,pd_tracker", "--out", str(tmp_path)])
    assert line.startswith("vflpcd: error: command line: --controllers: expected ground controllers") \
        and "'pd_tracker'" in line
    assert not (tmp_path / "bench_suite.json").exists()
