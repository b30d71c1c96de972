"""A ground station against the quadrotor SITL process (``vflpcd sitl quad``) on loopback, with
pymavlink's own calls (``set_mode``, ``set_mode_rtl``, ``mode_string_v10``: what MAVProxy's
``mode POSCTL`` and ``rtl`` send and show): take off, fly away, hold in POSCTL, a refused mission,
then return to launch: back to home, landed and disarmed."""

import math
import time

import numpy as np
import pytest

from pymavlink import mavutil

from gcs import LAND, POSCTL, RTL, Gcs, mav
from loopback import free_udp_port
from processes import Proc

TAKEOFF_ALT, RETURN_ALT = 3.0, 4.0


def positions(gcs, seconds):
    """LOCAL_POSITION_NED (n, e, d) for ``seconds`` from now."""
    out, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline:
        m = gcs.recv("LOCAL_POSITION_NED")
        out.append((m.x, m.y, m.z))
    return np.array(out)


def test_takeoff_fly_away_hold_refused_mission_and_return_to_launch():
    port = free_udp_port()
    gcs = Gcs(port)
    autopilot = Proc("sitl", "quad", "--port", str(port), "--telemetry-rate", "50",
                     "--param", f"MIS_TAKEOFF_ALT={TAKEOFF_ALT}", "--param", "MPC_TKO_SPEED=3",
                     "--param", "MPC_LAND_SPEED=3", "--param", f"RTL_RETURN_ALT={RETURN_ALT}")
    try:
        autopilot.wait_line("event=sitl_started", 20)
        gcs.recv("HEARTBEAT", 5)
        gcs.takeoff()
        hover = gcs.latest("LOCAL_POSITION_NED")
        assert (hover.x, hover.y, -hover.z) == pytest.approx((0.0, 0.0, TAKEOFF_ALT), abs=0.1)
        home = gcs.last["GLOBAL_POSITION_INT"]                             # hovering over home

        # fly 2 m/s east in OFFBOARD, then stop
        gcs.velocity(0.0, 0.0, 0.0, math.pi / 2)
        assert gcs.mode("OFFBOARD").result == mav.MAV_RESULT_ACCEPTED
        for vel, steps in ((2.0, 40), (0.0, 25)):
            for _ in range(steps):
                gcs.velocity(0.0, vel, 0.0, math.pi / 2)
                time.sleep(0.02)

        # POSCTL: answered, shown, and the vehicle holds where it was
        assert gcs.mode("POSCTL").result == mav.MAV_RESULT_ACCEPTED
        gcs.shown(POSCTL)
        assert mavutil.mode_string_v10(gcs.heartbeats[-1]) == "POSCTL"
        at_switch = gcs.latest("LOCAL_POSITION_NED")
        away = np.array([at_switch.x, at_switch.y, at_switch.z])
        held = positions(gcs, 1.5)
        assert away[1] > 1.2 and -away[2] == pytest.approx(TAKEOFF_ALT, abs=0.2)     # east of home, aloft
        assert np.max(np.linalg.norm(held - away, axis=1)) < 0.1
        assert abs(gcs.latest("LOCAL_POSITION_NED").vy) < 0.1

        # a mission: refused, with a STATUSTEXT saying why
        ack = gcs.mode("MISSION")
        assert ack.result in (mav.MAV_RESULT_UNSUPPORTED, mav.MAV_RESULT_DENIED)
        assert "missions not supported" in gcs.recv("STATUSTEXT", 2, lambda m: "MISSION" in m.text).text

        # return to launch: climb to RTL_RETURN_ALT, fly home, land, disarm
        t_rtl = time.monotonic()
        gcs.c.set_mode_rtl()                                               # MAV_CMD_NAV_RETURN_TO_LAUNCH
        assert gcs.recv("COMMAND_ACK", cond=lambda m: m.command == 20).result == mav.MAV_RESULT_ACCEPTED
        gcs.shown(RTL)
        assert mavutil.mode_string_v10(gcs.heartbeats[-1]) == "RTL"
        track, landed_states = [], set()
        while True:
            m = gcs.recv("LOCAL_POSITION_NED", 1)
            track.append((m.x, m.y, m.z))
            landed_states.add(gcs.last["EXTENDED_SYS_STATE"].landed_state)
            if gcs.heartbeats[-1].base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED == 0:
                break
            assert time.monotonic() - t_rtl < 12.0, "not disarmed 12 s after RTL"
        t_disarmed = time.monotonic()
        track = np.array(track)
        final = gcs.latest("LOCAL_POSITION_NED")
        landed, state = gcs.last["GLOBAL_POSITION_INT"], gcs.last["EXTENDED_SYS_STATE"]
    finally:
        rc = autopilot.stop()
        gcs.close()
    assert rc == 0
    assert -track[:, 2].min() == pytest.approx(RETURN_ALT, abs=0.3)            # it climbed to the return altitude
    left = int(np.argmax(np.linalg.norm(track[:, :2] - away[:2], axis=1) > 0.3))
    assert -track[left, 2] >= RETURN_ALT - 0.8                                  # within NAV_MC_ALT_RAD before it left
    assert math.hypot(final.x, final.y) < 0.1 and final.z == 0.0                # on home, on the ground
    north = (landed.lat - home.lat) * 1e-7 * math.pi / 180 * 6378137.0
    east = (landed.lon - home.lon) * 1e-7 * math.pi / 180 * 6378137.0 * math.cos(math.radians(home.lat * 1e-7))
    assert math.hypot(north, east) < 0.2 and landed.relative_alt == 0
    assert state.landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    assert mav.MAV_LANDED_STATE_LANDING in landed_states
    assert gcs.heartbeats[-1].custom_mode == RTL and LAND not in [m.custom_mode for m in gcs.heartbeats]
    assert any("RTL: landing" in t for t in gcs.texts)
    assert t_disarmed - t_rtl < 8.0
