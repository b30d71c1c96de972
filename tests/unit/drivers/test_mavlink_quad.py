"""The MAVLink quadrotor driver (MAVSDK) against the SITL autopilot in the same process, on loopback."""

import asyncio
import socket
import time

import numpy as np
import pytest

from loopback import free_udp_port
from drivers.mavlink_quad import MavlinkQuad, mavlink_quad_from_scenario
from vflpcd.config.scenarios import load_scenario
from sim.sitl.quad import QuadSitl
from vflpcd.base.errors import ConfigError


@pytest.fixture
def autopilot():
    port = free_udp_port()
    sitl = QuadSitl("127.0.0.1", port, params={"MPC_TKO_SPEED": 3.0})
    sitl.start()
    yield sitl, port
    sitl.stop()


def test_flight_state_in_enu_setpoints_in_ned_and_the_safe_action(autopilot):
    sitl, port = autopilot

    async def main():
        d = MavlinkQuad(f"udpin://127.0.0.1:{port}", takeoff_altitude=1.5, hold_s=0.5)
        await asyncio.wait_for(d.connect(), 20)
        await d.prepare()
        assert sitl.params["MIS_TAKEOFF_ALT"] == pytest.approx(1.5)          # set through the parameter protocol
        s = d.latest_state().state
        assert s[2] == pytest.approx(1.5, abs=0.15) and sitl.mode == "AUTO.LOITER"
        np.testing.assert_allclose(s[6:10], [1.0, 0.0, 0.0, 0.0], atol=0.05)  # level, facing east (ENU yaw 0)
        await d.enable()
        assert sitl.mode == "OFFBOARD" and d.fault() is None
        for _ in range(50):                                                  # 1 s of 1 m/s^2 north (ENU +Y)
            await d.send(np.array([0.0, 1.0, 0.0]))
            await asyncio.sleep(0.02)
        s = d.latest_state().state
        assert s[4] > 0.5 and abs(s[3]) < 0.1 and sitl.position[1] == pytest.approx(s[1], abs=0.1)
        with pytest.raises(ValueError):
            await d.send(np.array([np.nan, 0.0, 0.0]))
        await d.failsafe("test")
        await asyncio.sleep(0.2)
        assert sitl.mode == "AUTO.LOITER"
        deadline = time.monotonic() + 15
        while not d.at_rest and time.monotonic() < deadline:
            await asyncio.sleep(0.1)
        assert d.at_rest and sitl.position[2] == 0.0
        await d.close()
    asyncio.run(main())


def test_garbage_on_the_station_port_does_not_disturb_the_link(autopilot):
    """3000 malformed datagrams to MAVSDK's port: MAVSDK's parser drops them (it keeps no count
    the driver could read); the state keeps coming and no fault is raised."""
    sitl, port = autopilot
    rng = np.random.default_rng(5)

    async def main():
        d = MavlinkQuad(f"udpin://127.0.0.1:{port}")
        await asyncio.wait_for(d.connect(), 20)
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        stamps = []
        for i in range(3000):
            data = bytes(rng.integers(0, 256, int(rng.integers(1, 280)), dtype=np.uint8))
            if i % 3 == 0:
                data = b"\xfd" + data                                      # looks like a MAVLink 2 start
            sock.sendto(data, ("127.0.0.1", port))
            if i % 100 == 0:                                                 # a new state after each burst
                before, deadline = d.latest_state().stamp_ns, time.monotonic() + 1.0
                while d.latest_state().stamp_ns == before and time.monotonic() < deadline:
                    await asyncio.sleep(0.01)
                stamps.append(d.latest_state().stamp_ns)
        sock.close()
        await asyncio.sleep(0.1)
        fault, fresh = d.fault(), time.monotonic_ns() - d.latest_state().stamp_ns
        await d.close()
        return stamps, fault, fresh
    stamps, fault, fresh = asyncio.run(main())
    assert fault is None and fresh < 0.1e9
    assert len(set(stamps)) == len(stamps)                                  # a new state between every burst


def test_mission_options_are_checked():
    sc = load_scenario("uav_3d")
    q = mavlink_quad_from_scenario(sc, {}, "m.toml")
    assert q.takeoff_altitude == pytest.approx(2.0) and q.url == "udpin://127.0.0.1:14540"
    assert mavlink_quad_from_scenario(sc, {"origin": [0, 0, 0.5]}, "m.toml").takeoff_altitude == pytest.approx(1.5)
    for options, field in [({"url": "14540"}, "platform.url"), ({"origin": [0, 0]}, "platform.origin"),
                           ({"telemetry_timeout": 0}, "platform.telemetry_timeout"), ({"rate": 5}, "platform.rate")]:
        with pytest.raises(ConfigError) as err:
            mavlink_quad_from_scenario(sc, options, "m.toml")
        assert field in str(err.value)
