"""The daemon's shutdown with the in-process platform: a stop request (the path SIGTERM/SIGINT
take: ``Daemon.request_stop``) hands the vehicle to its safe action and the daemon exits only once
the vehicle is at rest (the quadrotor landed, the ground vehicle standing still), or with exit
code 4 when the mission's ``failsafe.land_timeout`` / ``failsafe.brake_timeout`` runs out first."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
import pytest

from vflpcd.config.scenarios import line_scenario_toml
from vflpcd.daemon.service import EXIT_NOT_AT_REST, EXIT_OK
from vflpcd.app.drill import Drill
from vflpcd.base.errors import ConfigError
from vflpcd.log.reader import read_flight_log
from vflpcd.config.mission import load_mission
from vflpcd.app.run import run_mission


def mission(folder: Path, *, aerial: bool, platform: str = "", failsafe: str = "") -> Path:
    """An in-process mission: the uav_3d course (pd_tracker) or a straight 200 m road at 5 m/s
    (pure_pursuit); telemetry off, logs in folder/logs."""
    if aerial:
        route, controller = "uav_3d", "pd_tracker"
    else:
        (folder / "line.toml").write_text(line_scenario_toml("line", length=200.0, speed=5.0, t_max=200.0))
        route, controller = "line.toml", "pure_pursuit"
    path = folder / "mission.toml"
    path.write_text(f"""vehicle_id = "t1"
[platform]
kind = "inproc"
{platform}
[route]
scenario = "{route}"
[controller]
name = "{controller}"
[loop]
rate_hz = 50
[workers]
executor = "thread"
[telemetry]
enabled = false
[failsafe]
state_max_age = 0.1
{failsafe}
[log]
dir = "{folder / 'logs'}"
""")
    return path


def speeds(log) -> np.ndarray:
    names = list(log.header.state_names)
    v = [names.index(n) for n in ("vx", "vy", "vz") if n in names]
    return np.linalg.norm(log.state[:, v], axis=1)


def run_timed(path: Path, stop_after_s: float):
    t0 = time.monotonic()
    result = run_mission(load_mission(path), stop_after_s=stop_after_s)
    return result, time.monotonic() - t0


def test_stop_request_lands_the_quadrotor_before_the_daemon_exits(tmp_path):
    path = mission(tmp_path, aerial=True, platform="hold_s = 0.2\nland_speed = 1.0",
                   failsafe="land_timeout = 30.0")
    result = run_timed(path, 1.0)[0]
    platform, outcome = result.outcome.loop.platform, result.outcome
    assert outcome.code == EXIT_OK and outcome.reason == "ran 1 s"
    assert platform.failsafe_reason == "shutdown: ran 1 s"
    assert platform.landed and platform.at_rest and abs(platform.plant.position()[2]) < 0.1
    log = read_flight_log(result.log_path)
    (rest,) = [e for e in log.events if e.kind == "at_rest"]
    # from about 2 m at 1 m/s after a 0.2 s hold: it took the landing, not a fixed bound
    assert 1.5 < rest.detail["waited_s"] < 10.0 and rest.detail["what"] == "landed"
    assert [e.kind for e in log.events][-1] == "stopping"
    assert log.state[0, 2] > 1.5 and abs(log.state[-1, 2]) < 0.1      # recorded all the way down
    assert set(log.mode[log.t > 1.1]) == {"stopping"}


def test_landing_that_does_not_finish_in_time_exits_4(tmp_path):
    path = mission(tmp_path, aerial=True, platform="hold_s = 0.2\nland_speed = 0.05",
                   failsafe="land_timeout = 1.5")
    result, wall = run_timed(path, 1.0)
    platform, outcome = result.outcome.loop.platform, result.outcome
    assert outcome.code == EXIT_NOT_AT_REST == 4
    assert outcome.reason.startswith("ran 1 s; the vehicle was not landed within failsafe.land_timeout = 1.5 s")
    assert "z=" in outcome.reason
    assert not platform.landed and platform.plant.position()[2] > 1.0
    log = read_flight_log(result.log_path)
    (timeout,) = [e for e in log.events if e.kind == "rest_timeout"]
    assert timeout.detail["setting"] == "land_timeout" and timeout.detail["timeout_s"] == 1.5
    assert timeout.detail["z_m"] == pytest.approx(platform.plant.position()[2], abs=0.1)
    assert not [e for e in log.events if e.kind == "at_rest"]
    stop_t = 1.0
    assert log.t[-1] - stop_t == pytest.approx(1.5, abs=0.2)           # it waited the whole timeout, no longer
    assert "failsafe.land_timeout" in log.events[-1].detail["reason"]


def test_stop_request_brakes_the_vehicle_to_a_standstill_before_the_daemon_exits(tmp_path):
    path = mission(tmp_path, aerial=False, failsafe="brake_timeout = 10.0")
    result = run_timed(path, 3.0)[0]
    platform, outcome = result.outcome.loop.platform, result.outcome
    assert outcome.code == EXIT_OK and platform.failsafe_reason == "shutdown: ran 3 s"
    assert platform.at_rest and np.linalg.norm(platform.plant.velocity_world()) < 0.05
    log = read_flight_log(result.log_path)
    v = speeds(log)
    stopping = log.mode == "stopping"
    assert v[~stopping][-1] > 2.0                    # it was driving when the stop was requested
    assert v[-1] < 0.05                              # and the log ends at a standstill
    (rest,) = [e for e in log.events if e.kind == "at_rest"]
    assert rest.detail["what"] == "standstill" and rest.detail["waited_s"] > 0.2


def test_vehicle_not_at_a_standstill_in_time_exits_4(tmp_path):
    path = mission(tmp_path, aerial=False, failsafe="brake_timeout = 0.05")
    outcome = run_timed(path, 3.0)[0].outcome
    assert outcome.code == 4
    assert "not at a standstill within failsafe.brake_timeout = 0.05 s" in outcome.reason
    speed = float(outcome.reason.rsplit("speed=", 1)[1].split()[0])
    assert speed > 1.0                                   # the speed it still had, in the reason
    assert not outcome.loop.platform.at_rest


@pytest.mark.parametrize("key, value", [("land_timeout", "0"), ("brake_timeout", "-1"), ("land_timeout", '"60"')])
def test_bad_rest_timeouts_name_the_field(tmp_path, key, value):
    path = mission(tmp_path, aerial=key == "land_timeout", failsafe=f"{key} = {value}")
    with pytest.raises(ConfigError) as err:
        load_mission(path)
    assert f"failsafe.{key}" in str(err.value) and str(path) in str(err.value)


def test_stop_request_during_a_failsafe_hold_keeps_exit_3_and_the_wait_for_rest(tmp_path):
    path = mission(tmp_path, aerial=False, failsafe="hold = 30.0\nbrake_timeout = 10.0")
    t0 = time.monotonic()
    result = run_mission(load_mission(path), drill=Drill("link", 2.0), stop_after_s=2.5)
    wall = time.monotonic() - t0
    outcome, platform = result.outcome, result.outcome.loop.platform
    assert outcome.code == 3 and outcome.reason.startswith("link_lost") and outcome.reason.endswith("(then ran 2.5 s)")
    assert platform.failsafe_reason.startswith("link_lost") and platform.at_rest
    assert wall < 25.0                                   # the stop request ended the 30 s hold
    log = read_flight_log(result.log_path)
    assert [e.kind for e in log.events if e.kind in ("failsafe", "at_rest", "stopping")] == \
        ["failsafe", "at_rest", "stopping"]
