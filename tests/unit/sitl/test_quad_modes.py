"""PX4's flight modes in the quadrotor SITL: which it flies, the reasons it gives for the others,
and the path of its return to home."""

import numpy as np
import pytest

from sim.sitl.quad_modes import (NOT_CUSTOM, STATUSTEXT_LEN, Return, custom_mode, mode_name, requested_mode,
                                 split_custom_mode)

CUSTOM = 1 | 128                                # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | SAFETY_ARMED, as MAVSDK sends


@pytest.mark.parametrize("main, sub, name", [(3, 0, "POSCTL"), (2, 0, "ALTCTL"), (4, 5, "AUTO.RTL"),
                                             (4, 3, "AUTO.LOITER"), (4, 6, "AUTO.LAND"), (6, 0, "OFFBOARD")])
def test_the_modes_a_station_may_set(main, sub, name):
    assert requested_mode(CUSTOM, main, sub) == (name, "")
    assert split_custom_mode(custom_mode(name)) == (main, sub)


@pytest.mark.parametrize("base, main, sub, why", [
    (CUSTOM, 4, 4, "AUTO.MISSION: missions not supported by this SITL"),
    (CUSTOM, 7, 0, "STABILIZED: stick mode, unsupported by this SITL"),
    (CUSTOM, 1, 0, "MANUAL: stick mode"), (CUSTOM, 5, 0, "ACRO: stick mode"),
    (CUSTOM, 4, 2, "AUTO.TAKEOFF by mode unsupported: use NAV_TAKEOFF"),
    (CUSTOM, 4, 1, "AUTO.READY: not supported"), (CUSTOM, 3, 1, "main 3 sub 1: not supported"),
    (CUSTOM, 4, 8, "main 4 sub 8: not supported"), (CUSTOM, 255, 255, "main 255 sub 255: not supported"),
    (0, 4, 5, NOT_CUSTOM)])
def test_every_refused_mode_has_a_reason_that_fits_one_statustext(base, main, sub, why):
    name, reason = requested_mode(base, main, sub)
    assert name is None and reason.startswith(why) and len(reason.encode()) <= STATUSTEXT_LEN


def test_px4_encoding_of_custom_mode():
    assert custom_mode("AUTO.RTL") == (5 << 24) | (4 << 16) == 84148224
    assert custom_mode("POSCTL") == 3 << 16 and custom_mode("ALTCTL") == 2 << 16
    assert mode_name(4, 4) == "AUTO.MISSION" and mode_name(7, 0) == "STABILIZED" and mode_name(7, 2) == "main 7 sub 2"


def test_return_climbs_where_it_is_then_flies_home_then_descends_onto_it():
    home = np.array([2.0, 1.0, 0.0])
    ret = Return(np.array([8.0, -3.0, 5.0]), home, return_alt=6.0, alt_radius=0.5, xy_radius=0.3)
    assert ret.phase == Return.CLIMB and ret.target() == pytest.approx([8.0, -3.0, 6.0])
    assert not ret.advance(np.array([8.0, -3.0, 5.4]))                          # 0.6 m short
    assert ret.advance(np.array([8.1, -3.0, 5.6])) and ret.phase == Return.BACK
    assert ret.target() == pytest.approx([2.0, 1.0, 6.0])                      # level, at the return altitude
    assert not ret.advance(np.array([2.3, 1.2, 6.0]))                          # 0.36 m off
    assert ret.advance(np.array([2.2, 1.1, 6.0])) and ret.phase == Return.DESCEND
    assert ret.target() == pytest.approx(home)
    assert not ret.advance(np.array([2.0, 1.0, 3.0]))                          # the last phase


def test_return_above_the_return_altitude_keeps_its_altitude_and_over_home_descends_at_once():
    ret = Return(np.array([5.0, 0.0, 12.0]), np.zeros(3), return_alt=6.0, alt_radius=0.5, xy_radius=0.3)
    assert ret.altitude == 12.0 and ret.advance(np.array([5.0, 0.0, 12.0])) and ret.phase == Return.BACK
    over_home = Return(np.array([0.1, 0.0, 7.0]), np.zeros(3), return_alt=6.0, alt_radius=0.5, xy_radius=0.3)
    assert over_home.advance(np.array([0.1, 0.0, 7.0])) and over_home.phase == Return.DESCEND
