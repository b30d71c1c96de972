"""Scenario loading: the shipped files are valid; each kind of bad input is named by file and field."""

import re

import numpy as np
import pytest

from vflpcd.core.obstacle_world import ObstacleWorld
from vflpcd.config.scenarios import available_scenarios, load_scenario
from vflpcd.app.cli import main
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir

BASE = (config_dir() / "scenarios" / "dense_static.toml").read_text()


def test_shipped_scenarios_load():
    names = available_scenarios()
    assert {"dense_static", "carsim_avoidance", "racing_track", "uav_3d"} <= set(names)
    dense = load_scenario("dense_static")
    assert 45.0 <= dense.goal_at <= 50.0 and len(dense.obstacles) >= 6
    carsim = load_scenario("carsim_avoidance")
    assert carsim.goal_at == pytest.approx(250.0, abs=5.0)
    assert carsim.v_desired == pytest.approx(25 / 3.6, rel=1e-3)
    triggers = {o.trigger for o in carsim.obstacles}
    assert {"always", "move"} <= triggers
    assert any(o.trigger == "move" and o.trigger_distance == 25.0 for o in carsim.obstacles)
    track = load_scenario("racing_track")
    assert track.path.closed and track.v_desired == 6.0
    assert np.sqrt(track.a_lat_max / np.abs(track.path.curvature).max()) >= 6.0  # v_d is feasible everywhere
    uav = load_scenario("uav_3d")
    assert uav.dim == 3 and any(o.trigger == "appear" for o in uav.obstacles)
    assert any(np.linalg.norm(o.velocity) == pytest.approx(1.0, abs=0.01) for o in uav.obstacles)


def write(tmp_path, text, name="bad.toml"):
    f = tmp_path / name
    f.write_text(text)
    return f


CASES = {
    "missing field": (BASE.replace("desired = 3.0\n", ""), "speed.desired", "missing required field"),
    "wrong type": (BASE.replace("desired = 3.0", 'desired = "fast"'), "speed.desired", "expected a number"),
    "negative speed": (BASE.replace("desired = 3.0", "desired = -3.0"), "speed.desired", "positive"),
    "negative start speed": (BASE.replace("speed = 3.0", "speed = -1.0"), "start.speed", ">= 0"),
    "obstacle covers start": (BASE.replace("center = [8.0, 1.2]", "center = [1.0, 0.5]"), "obstacles[0]",
                              "covers the start"),
    "missing waypoint file": (BASE.replace('kind = "line"\nstart = [0.0, 0.0]\nend = [47.0, 0.0]',
                                           'kind = "waypoints"\nfile = "nowhere.csv"'), "path.file", "not found"),
    "unknown field": (BASE.replace("a_lat_max = 2.0", "a_lat_max = 2.0\nmax_speed = 3"), "speed.max_speed",
                      "unknown field"),
    "wrong shape for platform": (BASE.replace('shape = "circle"\nradius = 1.0', 'shape = "sphere"\nradius = 1.0', 1),
                                 "obstacles[0].shape", "expected one of"),
    "negative size": (BASE.replace("radius = 1.0", "radius = -1.0", 1), "obstacles[0].radius", "positive"),
    "duplicate id": (BASE.replace('id = "b1"', 'id = "c1"'), "obstacles[1].id", "duplicate"),
    "R not positive definite": (BASE.replace("R = [[0.1, 0.0], [0.0, 1.0]]", "R = [[0.1, 0.0], [0.0, -1.0]]"),
                                "metrics.R", "positive definite"),
    "trigger without distance": (BASE.replace('yaw = 0.3\n', 'yaw = 0.3\ntrigger = "move"\n', 1),
                                 "obstacles[1].trigger_distance", "missing"),
    "bad TOML": (BASE + "\n[[[", "<syntax>", "not valid TOML"),
    "goal stop not a boolean": (BASE.replace("[goal]", '[goal]\nstop = "yes"'), "goal.stop", "expected"),
    "goal stop on a closed path": (BASE.replace('kind = "line"\nstart = [0.0, 0.0]\nend = [47.0, 0.0]',
                                                'kind = "waypoints"\npoints = [[0.0, 0.0], [47.0, 0.0], [47.0, 30.0]]\n'
                                                'closed = true').replace("[goal]", "[goal]\nstop = false"),
                                   "goal.stop", "closed path has no end"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_scenario_is_a_config_error_naming_file_and_field(tmp_path, case):
    text, field, words = CASES[case]
    assert text != BASE or case == "bad TOML"
    f = write(tmp_path, text)
    with pytest.raises(ConfigError) as err:
        load_scenario(f)
    assert err.value.file == str(f)
    assert err.value.field == field
    assert words in err.value.message


@pytest.mark.parametrize("case", ["missing field", "wrong type", "negative speed", "obstacle covers start",
                                  "missing waypoint file"])
def test_cli_exits_2_with_one_line(tmp_path, capsys, case):
    text, field, _ = CASES[case]
    f = write(tmp_path, text)
    code = main(["sim", str(f), "--out", str(tmp_path / "out"), "--no-plot"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1
    assert re.match(rf"vflpcd: error: {re.escape(str(f))}: {re.escape(field)}: ", err[0])
    assert not (tmp_path / "out").exists()


def test_unknown_scenario_and_controller(tmp_path, capsys):
    assert main(["sim", "no_such_scenario", "--no-plot"]) == 2
    assert "no such scenario" in capsys.readouterr().err
    assert main(["sim", "uav_3d", "--controller", "pure_pursuit", "--no-plot", "--out", str(tmp_path)]) == 2
    assert "--controller" in capsys.readouterr().err
    assert main(["sim", "dense_static", "--controller", "mpc9000", "--no-plot", "--out", str(tmp_path)]) == 2
    assert "unknown controller" in capsys.readouterr().err


def test_waypoint_file_is_read_relative_to_the_scenario(tmp_path):
    (tmp_path / "wp.csv").write_text("# x,y\n0,0\n20,0\n47,0\n")
    f = write(tmp_path, BASE.replace('kind = "line"\nstart = [0.0, 0.0]\nend = [47.0, 0.0]',
                                     'kind = "waypoints"\nfile = "wp.csv"'))
    s = load_scenario(f)
    assert s.goal_at == pytest.approx(47.0, rel=1e-6)
    (tmp_path / "wp.csv").write_text("0,0,0\n1,1,1\n")
    with pytest.raises(ConfigError, match="path.file"):
        load_scenario(f)


def test_obstacle_triggers():
    carsim = load_scenario("carsim_avoidance")
    uav = load_scenario("uav_3d")
    ped = next(o for o in carsim.obstacles if o.id == "pedestrian")
    world = ObstacleWorld([ped])
    world.update(0.0, ped.center + [40.0, 0.0])
    assert np.allclose(world.center(0, 5.0), ped.center)           # waits while the robot is far
    world.update(6.0, ped.center + [20.0, 0.0])                      # within 25 m at t = 6
    assert np.allclose(world.center(0, 8.0), ped.center + 2.0 * ped.velocity)
    drone = next(o for o in uav.obstacles if o.trigger == "appear")
    world = ObstacleWorld([drone])
    assert world.snapshot(0.0) == [] and not world.present(0)
    world.update(3.0, drone.center + [drone.trigger_distance - 0.1, 0, 0])
    snap = world.snapshot(4.0)
    assert len(snap) == 1 and np.allclose(snap[0].center, drone.center + drone.velocity)
    assert snap[0].center_at(5.0) == pytest.approx(drone.center + 2 * drone.velocity)


def test_an_open_road_runs_on_past_its_goal_unless_the_goal_is_a_stop(tmp_path):
    from vflpcd.config.scenarios import line_scenario_toml, run_on_length

    passed = load_scenario(write(tmp_path, line_scenario_toml("through", length=40.0, speed=5.0), "through.toml"))
    a_decel = passed.guidance.a_decel
    assert not passed.stop_at_goal and passed.goal_at == pytest.approx(40.0, abs=1e-9)
    assert run_on_length(5.0, a_decel) == pytest.approx(25.0 / (2 * a_decel) + 3.0 * 5.0)
    assert passed.path.length == pytest.approx(40.0 + run_on_length(5.0, a_decel), abs=1e-9)
    assert passed.goal_progress == pytest.approx(39.0, abs=1e-9)          # the goal's place, not the road's end
    stop = load_scenario(write(tmp_path, line_scenario_toml("stop", length=40.0, speed=5.0, stop=True), "stop.toml"))
    assert stop.stop_at_goal and stop.path.length == pytest.approx(40.0, abs=1e-9) and stop.goal_progress == 39.0
    assert load_scenario(tmp_path / "through.toml", stop_at_goal=True).path.length == pytest.approx(40.0, abs=1e-9)
    track = load_scenario("racing_track")                                  # a closed path has no end
    assert track.path.closed and track.goal_progress == pytest.approx(track.path.length)


def test_a_mission_ends_at_rest_on_its_route_s_goal():
    from vflpcd.config.mission import load_mission

    mission = load_mission(config_dir() / "missions" / "vehicle_inproc.toml")
    assert mission.scenario.stop_at_goal
    assert mission.scenario.path.length == pytest.approx(mission.scenario.goal_at, abs=1e-9)
    assert load_scenario(mission.scenario.file).path.length > mission.scenario.goal_at + 10.0
