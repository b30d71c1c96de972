"""The MAVLink quadrotor end to end with real processes on loopback: the PX4-like autopilot
(``vflpcd sitl quad``) and the daemon (``vflpcd run``) talking MAVLink 2 over UDP through MAVSDK."""

import json
import os
import time
from pathlib import Path

import numpy as np
import pytest

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

from loopback import free_udp_port  # noqa: E402
from processes import Proc  # noqa: E402

LOITER, LAND = (3 << 24) | (4 << 16), (6 << 24) | (4 << 16)


def quad_mission(folder: Path, port: int, *, hold: float = 3.0, state_max_age: float = 0.5,
                 telemetry_timeout: float = 1.0) -> Path:
    """The uav_3d mission over MAVLink on ``port``; ``state_max_age`` 0.5 s, ``telemetry_timeout``
    1 s and an overrun streak of 25 ticks (0.5 s) before the failsafe: the test machine's other
    tests share its two cores, and with the default 5 (0.1 s) the control thread, kept from the CPU
    for five periods in a row, failed the mission in some full-suite runs, as did a SITL state 265
    ms old at 0.25 s and a SITL that sent no position for 0.3 s (the overrun and stale-state
    failsafes have their own tests, ``test_daemon_failsafes.py``; the other integration missions
    allow a 0.5 s old state too, ``conftest.mission_file``, and the shutdown test 1 s without a
    position; the link-loss test below keeps 0.25 and 0.3 s, as all three had before)."""
    path = folder / "quad_sitl.toml"
    path.write_text(f"""vehicle_id = "quad1"
[platform]
kind = "mavlink"
url = "udpin://127.0.0.1:{port}"
telemetry_timeout = {telemetry_timeout}
hold_s = 1.0
[route]
scenario = "uav_3d"
[controller]
name = "vflpc"
model = "quadrotor.npz"
[loop]
rate_hz = 50
[workers]
executor = "process"
[telemetry]
enabled = false
[failsafe]
state_max_age = {state_max_age}
overrun_streak = 25
connect_timeout = 30.0
hold = {hold}
[log]
dir = "{folder / 'logs'}"
""")
    return path


def sitl(port: int, *params: str) -> Proc:
    args = ["sitl", "quad", "--port", str(port)]
    for p in params:
        args += ["--param", p]
    proc = Proc(*args)
    proc.wait_line("event=sitl_started", 20)
    return proc


def sitl_stats(proc: Proc) -> dict:
    return next(json.loads(line)["sitl_stats"] for line in proc.out if line.startswith('{"sitl_stats"'))


def test_quadrotor_mission_through_mavsdk_takes_off_flies_the_course_and_lands(tmp_path):
    port = free_udp_port()
    mission = quad_mission(tmp_path, port)
    autopilot = sitl(port)
    daemon = Proc("run", str(mission))
    try:
        assert daemon.wait(150) == 0, daemon.text()[-3000:]
    finally:
        daemon.stop()
        autopilot.stop()
    out = "\n".join(daemon.out)
    assert "mission_complete (exit code 0)" in out and "0 obstacles touched" in out, out
    for step in ("event=takeoff", "event=offboard_started", "action=hold_then_land", "mode=LAND",
                 "event=land_commanded", "event=at_rest"):
        daemon.wait_line(step, 0.1)
    # the landing outlasts failsafe.hold (3 s): the daemon waited for it, not for the hold
    complete, rest = daemon.wait_line("event=mission_complete", 0.1), daemon.wait_line("event=at_rest", 0.1)
    assert rest - complete > 3.0 + 1.0
    stats = sitl_stats(autopilot)                      # stopped after the daemon exited
    assert stats["landed_state"] == 1 and stats["armed"] is False and stats["offboard_losses"] == 0
    assert stats["rejected_setpoints"] == 0 and stats["malformed"] == 0 and stats["setpoints"] > 1500


def test_autopilot_killed_trips_the_failsafe_and_a_restarted_one_is_reconnected(tmp_path):
    port = free_udp_port()
    mission = quad_mission(tmp_path, port, hold=6.0, state_max_age=0.25, telemetry_timeout=0.3)
    autopilot = sitl(port)
    daemon = Proc("run", str(mission))
    autopilot2 = None
    try:
        daemon.wait_line("event=ready", 90)
        time.sleep(2.0)
        autopilot.p.kill()
        t_kill = time.monotonic()
        t_failsafe = daemon.wait_line("event=failsafe", 5)
        reason = daemon.lines_with("event=failsafe")[0][1]
        assert "reason=stale_state" in reason or "reason=link_lost" in reason   # whichever sees it first
        assert t_failsafe - t_kill < 0.6
        daemon.wait_line("event=link_lost", 3, after=t_kill)      # the driver saw it go before it comes back
        autopilot2 = sitl(port)
        daemon.wait_line("event=link_restored", 10, after=t_failsafe)
        assert daemon.wait(30) == 3, daemon.text()[-2000:]
    finally:
        daemon.stop()
        autopilot.stop()
        if autopilot2 is not None:
            autopilot2.stop()
    # the restarted autopilot stands on the ground and was told to land (its safe state)
    stats = sitl_stats(autopilot2)
    assert stats["landed_state"] == 1 and stats["mode"] in ("AUTO.LAND", "AUTO.LOITER")


def test_daemon_killed_the_autopilot_holds_then_lands(tmp_path):
    port = free_udp_port()
    mission = quad_mission(tmp_path, port)
    autopilot = sitl(port, "COM_OF_LOSS_T=0.5", "NAV_OBL_HOLD_T=1.0", "MPC_LAND_SPEED=1.5")
    daemon = Proc("run", str(mission))
    try:
        daemon.wait_line("event=ready", 90)
        time.sleep(2.0)
        daemon.p.kill()
        t_kill = time.monotonic()
        daemon.p.wait(5)                                   # the port is free once the process is gone
        gcs = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=245, source_component=190,
                                         dialect="common")
        seen, z = [], []
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline:
            m = gcs.recv_match(type=["HEARTBEAT", "LOCAL_POSITION_NED"], blocking=True, timeout=0.2)
            if m is None:
                continue
            if m.get_type() == "LOCAL_POSITION_NED":
                z.append(-m.z)
            elif not seen or seen[-1][1:] != (m.custom_mode, m.base_mode & 128):
                seen.append((time.monotonic(), m.custom_mode, m.base_mode & 128))
            if seen and seen[-1][2] == 0:                  # disarmed after touchdown
                break
        gcs.close()
    finally:
        daemon.stop()
        autopilot.stop()
    modes = [mode for _, mode, _ in seen]
    assert LOITER in modes and LAND in modes and modes.index(LOITER) < modes.index(LAND), seen
    assert seen[-1][2] == 0 and z[-1] == pytest.approx(0.0, abs=0.01)
    assert max(np.diff(z[::10]), default=0.0) < 0.05        # it came down, never climbed
    stats = sitl_stats(autopilot)
    assert stats["offboard_losses"] == 1 and stats["landed_state"] == 1
    autopilot.wait_line("event=offboard_lost", 0.1, after=t_kill)
