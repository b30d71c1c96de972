"""The PX4-like quadrotor autopilot against a pymavlink ground station on loopback."""

import math
import socket
import struct
import time

import numpy as np
import pytest

from gcs import RTL, Gcs, mav
from loopback import free_port
from sim.sitl.quad import PARAMS, QuadSitl, check_param

FAST = {"MIS_TAKEOFF_ALT": 1.0, "MPC_TKO_SPEED": 3.0, "COM_OF_LOSS_T": 0.3, "NAV_OBL_HOLD_T": 0.5,
        "MPC_LAND_SPEED": 2.0}
OFFBOARD_MODE = 6 << 16


@pytest.fixture
def rig():
    port = free_port()
    gcs = Gcs(port)
    sitl = QuadSitl("127.0.0.1", port, params=FAST)
    sitl.start()
    gcs.recv("HEARTBEAT")
    yield sitl, gcs, port
    sitl.stop()
    gcs.close()


def test_heartbeat_is_a_px4_quadrotor_and_acks_go_to_the_sender(rig):
    sitl, gcs, _ = rig
    hb = gcs.recv("HEARTBEAT")
    assert (hb.type, hb.autopilot, hb.base_mode, hb.custom_mode) == (2, 12, 1, (3 << 24) | (4 << 16))
    assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1 and hb.get_msgbuf()[0] == 0xFD   # MAVLink 2
    ack = gcs.command(400, 1)
    assert (ack.result, ack.target_system, ack.target_component) == (0, 245, 190)
    assert gcs.recv("HEARTBEAT", cond=lambda m: m.base_mode & 128).base_mode == 129
    assert gcs.command(400, 0).result == 0 and not sitl.armed          # on the ground: disarm accepted


def test_refusals_are_acked_and_each_says_why_in_a_statustext(rig):
    sitl, gcs, _ = rig
    denied, unsupported = mav.MAV_RESULT_DENIED, mav.MAV_RESULT_UNSUPPORTED

    def refused(ack, result, text):
        assert ack.result == result
        assert gcs.recv("STATUSTEXT", cond=lambda m: m.text == text).severity == mav.MAV_SEVERITY_WARNING

    refused(gcs.command(22, *[math.nan] * 7), denied, "take-off denied: not armed")
    refused(gcs.command(20), denied, "RTL denied: not in the air")
    assert gcs.command(400, 1).result == 0
    refused(gcs.command(176, 129, 6), denied, "OFFBOARD denied: no fresh setpoint")
    refused(gcs.set_mode(4, 5), denied, "RTL denied: not in the air")                   # armed, on the ground
    refused(gcs.set_mode(4, 4), unsupported, "AUTO.MISSION: missions not supported by this SITL")
    refused(gcs.set_mode(7), unsupported, "STABILIZED: stick mode, unsupported by this SITL")
    refused(gcs.command(176, 0, 4, 5), unsupported, "only PX4 custom modes are supported by this SITL")
    refused(gcs.command(31000), unsupported, "command 31000 not supported by this SITL")
    refused(gcs.command(511, 32, math.nan), denied, "request denied: a parameter is not a number")
    gcs.c.mav.set_mode_send(1, 1, (4 << 24) | (4 << 16))                                 # SET_MODE: AUTO.MISSION
    ack = gcs.recv("COMMAND_ACK")
    assert (ack.command, ack.target_system) == (mav.MAV_CMD_DO_SET_MODE, 245)
    refused(ack, unsupported, "AUTO.MISSION: missions not supported by this SITL")
    gcs.c.mav.mission_request_list_send(1, 1)                                           # no mission
    assert gcs.recv("MISSION_COUNT").count == 0
    gcs.c.mav.mission_count_send(1, 1, 3)                                               # an upload
    assert gcs.recv("MISSION_ACK").type == mav.MAV_MISSION_UNSUPPORTED
    assert gcs.recv("STATUSTEXT").text == "upload: missions not supported by this SITL"
    gcs.takeoff()
    refused(gcs.command(400, 0), denied, "disarm denied: in the air")
    assert sitl.armed and sitl.mode == "AUTO.LOITER" and sitl.stats()["rejected_commands"] == 11


def test_set_mode_message_starts_the_return_and_altctl_holds_where_it_was_set(rig):
    sitl, gcs, _ = rig
    gcs.takeoff()
    gcs.c.mav.set_mode_send(1, 1, RTL)                                                   # as older stations do
    ack = gcs.recv("COMMAND_ACK")
    assert (ack.command, ack.result) == (mav.MAV_CMD_DO_SET_MODE, mav.MAV_RESULT_ACCEPTED)
    gcs.shown(RTL)
    assert "RTL: climb to 60.0 m" in gcs.texts                                          # PX4's RTL_RETURN_ALT
    time.sleep(0.3)
    assert gcs.set_mode(2).result == mav.MAV_RESULT_ACCEPTED                            # ALTCTL, climbing
    at_switch = sitl.position.copy()
    gcs.shown(2 << 16)
    assert at_switch[2] > 1.2 and sitl.landed_state == 2                                 # climbed, in the air
    time.sleep(1.5)
    assert np.linalg.norm(sitl.position - at_switch) < 0.1
    assert np.linalg.norm(sitl.plant.velocity_world()) < 0.1


def test_home_is_where_it_was_armed(rig):
    sitl, gcs, _ = rig
    sitl.plant.reset(np.array([2.0, -1.0, 0.0, 0.0, 0.0, 0.0, 0.0]))                     # on the ground elsewhere
    assert gcs.command(400, 1).result == 0
    home = gcs.last["HOME_POSITION"]                                                     # sent on arming
    assert (home.x, home.y, home.z) == pytest.approx((-1.0, 2.0, 0.0))                   # NED: north -1, east 2
    assert home.latitude < 473977420 and home.longitude > 85455940


def test_takeoff_then_offboard_acceleration_and_velocity_setpoints(rig):
    sitl, gcs, _ = rig
    gcs.takeoff()
    pos = gcs.latest("LOCAL_POSITION_NED")
    assert pos.z == pytest.approx(-1.0, abs=0.1)
    assert gcs.recv("EXTENDED_SYS_STATE").landed_state == mav.MAV_LANDED_STATE_IN_AIR
    gcs.accel(0, 0, 0)
    assert gcs.command(176, 129, 6).result == 0
    assert any(m.custom_mode == OFFBOARD_MODE == 393216 for m in gcs.heartbeats)   # sent at once on the switch
    x0 = gcs.latest("LOCAL_POSITION_NED").x
    for _ in range(50):                                   # 1 s of 1 m/s^2 north
        gcs.accel(1.0, 0.0, 0.0)
        time.sleep(0.02)
    p = gcs.latest("LOCAL_POSITION_NED")
    assert p.x - x0 > 0.2 and p.vx > 0.5 and abs(p.y) < 0.05
    for _ in range(100):                                  # 2 s of 1 m/s east
        gcs.velocity(0.0, 1.0, 0.0, math.pi / 2)
        time.sleep(0.02)
    p = gcs.latest("LOCAL_POSITION_NED")
    assert p.vy == pytest.approx(1.0, abs=0.15) and abs(p.vx) < 0.2
    att = gcs.latest("ATTITUDE")
    assert att.yaw == pytest.approx(math.pi / 2, abs=0.1)


def test_offboard_loss_holds_then_lands_and_disarms(rig):
    sitl, gcs, _ = rig
    gcs.takeoff()
    gcs.accel(0, 0, 0)
    assert gcs.command(176, 129, 6).result == 0
    t_last = time.monotonic()                             # no more setpoints
    gcs.recv("STATUSTEXT", 2, lambda m: "Offboard lost" in m.text)
    t_hold = time.monotonic()
    gcs.recv("HEARTBEAT", 2, lambda m: m.custom_mode == (3 << 24) | (4 << 16))
    gcs.recv("HEARTBEAT", 3, lambda m: m.custom_mode == (6 << 24) | (4 << 16))                # AUTO.LAND
    t_land = time.monotonic()
    gcs.recv("EXTENDED_SYS_STATE", 5, lambda m: m.landed_state == mav.MAV_LANDED_STATE_ON_GROUND)
    gcs.recv("HEARTBEAT", 3, lambda m: not m.base_mode & 128)                                 # auto-disarm
    assert 0.25 <= t_hold - t_last <= 0.6 and 0.4 <= t_land - t_hold <= 0.9
    assert sitl.stats()["offboard_losses"] == 1 and sitl.position[2] == 0.0


def test_parameter_protocol(rig):
    sitl, gcs, _ = rig
    gcs.c.mav.param_request_list_send(1, 1)
    got = {}
    while len(got) < len(PARAMS):
        m = gcs.recv("PARAM_VALUE")
        got[m.param_id] = m
    assert got["MIS_TAKEOFF_ALT"].param_value == pytest.approx(1.0) and got["MIS_TAKEOFF_ALT"].param_count == 9
    assert got["RTL_RETURN_ALT"].param_value == pytest.approx(60.0)            # PX4's default
    act = got["COM_OBL_ACT"]
    assert act.param_type == mav.MAV_PARAM_TYPE_INT32           # carried bytewise, as PX4 does
    assert struct.unpack("<i", struct.pack("<f", act.param_value))[0] == 1
    gcs.c.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 3.5, mav.MAV_PARAM_TYPE_REAL32)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == pytest.approx(3.5)
    gcs.c.mav.param_set_send(1, 1, b"MIS_TAKEOFF_ALT", 500.0, mav.MAV_PARAM_TYPE_REAL32)   # out of range: echoed
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "MIS_TAKEOFF_ALT").param_value == pytest.approx(3.5)
    gcs.c.mav.param_request_read_send(1, 1, b"NAV_OBL_HOLD_T", -1)
    assert gcs.recv("PARAM_VALUE", cond=lambda m: m.param_id == "NAV_OBL_HOLD_T").param_value == pytest.approx(0.5)
    gcs.c.mav.param_set_send(1, 1, b"NO_SUCH_PARAM", 1.0, mav.MAV_PARAM_TYPE_REAL32)
    time.sleep(0.1)
    assert sitl.stats()["rejected_params"] == 2
    with pytest.raises(ValueError, match="COM_OBL_ACT"):
        check_param("COM_OBL_ACT", 0.5)


def test_home_position_and_autopilot_version_on_request(rig):
    sitl, gcs, _ = rig
    assert gcs.command(512, 242).result == 0
    home = gcs.recv("HOME_POSITION")
    assert home.latitude == 473977420 and (home.x, home.y, home.z) == (0, 0, 0)
    assert gcs.command(512, 148, *[math.nan] * 6).result == 0                # the unused parameters NaN, as MAVSDK
    v = gcs.recv("AUTOPILOT_VERSION")
    assert v.capabilities & mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
    assert gcs.command(511, 32, 20000).result == 0                       # LOCAL_POSITION_NED at 50 Hz
    gcs.recv("LOCAL_POSITION_NED")
    stamps = [time.monotonic() for _ in range(26) if gcs.recv("LOCAL_POSITION_NED")]
    assert np.mean(np.diff(stamps)) == pytest.approx(0.02, rel=0.3)
    status = gcs.recv("SYS_STATUS")
    assert status.onboard_control_sensors_health & 0x10000020 == 0x10000020      # GPS and pre-arm ok


def test_fuzz_thousands_of_malformed_frames_are_counted_and_the_autopilot_still_answers(rig):
    sitl, gcs, port = rig
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    gcs.recv("HEARTBEAT")
    (sitl_addr,) = gcs.c.clients                 # the autopilot's own UDP port
    rng = np.random.default_rng(3)
    enc = gcs.c.mav
    sent = {"random": 0, "bad_crc": 0, "truncated": 0, "setpoint": 0, "wrong_target": 0}
    for i in range(3000):
        kind = tuple(sent)[i % 5]
        if kind == "random":
            data = bytes(rng.integers(0, 256, int(rng.integers(1, 300)), dtype=np.uint8))
            data = data.replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00")     # no frame start: all bad
        elif kind == "bad_crc":
            frame = bytearray(enc.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(enc))
            frame[-1] ^= 0x5A
            data = bytes(frame)
        elif kind == "truncated":
            frame = enc.command_long_encode(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(enc)
            data = frame[: int(rng.integers(2, len(frame) - 1))]
        elif kind == "setpoint":                       # NaN, wrong mask or wrong frame: rejected
            variant = i % 3
            msg = enc.set_position_target_local_ned_encode(
                0, 1, 1, (1, 1, 8)[variant], (3135, 7, 3135)[variant], 0, 0, 0, 0, 0, 0,
                (math.nan, 1.0, 1.0)[variant], 0, 0, 0, 0)
            data = msg.pack(enc)
        else:
            data = enc.command_long_encode(7, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0).pack(enc)
        sent[kind] += 1
        sock.sendto(data, sitl_addr)
        if i % 50 == 0:                                # paced: a loopback socket drops what overflows it
            time.sleep(0.005)
    deadline = time.monotonic() + 3.0                  # the autopilot's thread may lag on a loaded machine
    while time.monotonic() < deadline and (sitl.stats()["rejected_setpoints"] < sent["setpoint"]
                                           or sitl.stats()["wrong_target"] < sent["wrong_target"]):
        time.sleep(0.05)
    s = sitl.stats()
    assert s["rejected_setpoints"] == sent["setpoint"] and s["wrong_target"] == sent["wrong_target"]
    assert s["malformed"] >= sent["random"] + sent["bad_crc"] + sent["truncated"]
    assert not sitl.armed and sitl._thread.is_alive()        # no fuzzed arm got through
    assert gcs.command(400, 1).result == 0                   # still answers
    assert gcs.recv("SYS_STATUS").errors_comm >= min(s["malformed"], 65535)
    sock.close()


def test_a_restarted_ground_station_is_served(rig):
    sitl, gcs, port = rig
    gcs.close()
    time.sleep(0.3)
    gcs2 = Gcs(port)
    try:
        gcs2.recv("HEARTBEAT")
        assert gcs2.command(400, 1).result == 0
    finally:
        gcs2.close()


def test_return_path_in_simulated_time_and_a_station_taking_over_in_the_descent():
    """The autopilot stepped by hand (no thread, no station): the take-off's climb rate, the
    return's phases, where it lands, and POSCTL in the descent stopping it."""
    sitl = QuadSitl("127.0.0.1", free_port(), params={**FAST, "MIS_TAKEOFF_ALT": 4.0, "RTL_RETURN_ALT": 3.0})
    dt = sitl.dt

    def command(cmd, *p):
        p = list(p) + [0.0] * (7 - len(p))
        result, _ = sitl._command_result(cmd, p)
        if result == mav.MAV_RESULT_ACCEPTED:
            sitl._apply(cmd, p)
        return result

    def fly(seconds, until=lambda: False):
        for _ in range(int(seconds / dt)):
            sitl._step(dt)
            if until():
                return True
        return False

    try:
        assert command(400, 1) == 0 and command(22, *[math.nan] * 7) == 0
        climb = []
        assert fly(5, lambda: climb.append(sitl.plant.velocity_world()[2]) or sitl.mode == "AUTO.LOITER")
        assert max(climb) == pytest.approx(FAST["MPC_TKO_SPEED"], abs=0.1)      # past the hold's 2 m/s
        sitl.plant.reset(np.array([4.0, -3.0, 1.0, 0.0, 0.0, 0.0, 0.0]))     # 5 m from home, 1 m up
        assert command(20) == 0 and sitl.mode == "AUTO.RTL" and sitl._return.phase == "climb"
        assert fly(5, lambda: sitl._return.phase == "back")
        p = sitl.position
        assert p[2] >= 3.0 - 0.8 and np.linalg.norm(p[:2] - [4.0, -3.0]) < 0.1     # straight up first
        assert fly(10, lambda: sitl._return.phase == "descend") and sitl.landed_state == 4   # LANDING
        assert fly(5, lambda: sitl.position[2] < 1.5)
        assert command(176, 1, 3) == 0 and sitl.landed_state == 2                       # POSCTL: in the air
        held = sitl.position.copy()
        fly(1.0)
        assert np.linalg.norm(sitl.position - held) < 0.15 and sitl.in_air
        assert command(176, 1, 4, 5) == 0                                               # RTL again: up, then down
        assert fly(20, lambda: not sitl.in_air)
        assert np.linalg.norm(sitl.position[:2]) < 0.05 and sitl.position[2] == 0.0 and sitl.landed_state == 1
        assert sitl.mode == "AUTO.RTL"
    finally:
        sitl.conn.close()
