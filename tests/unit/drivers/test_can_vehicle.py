"""The CAN vehicle driver against a scripted node on python-can's in-process virtual bus."""

import asyncio
import time

import can
import cantools
import numpy as np
import pytest

from canhub import receive_for
from drivers.can_bus import BusConfig
from drivers.can_codec import FRAME_ERRORS, CounterSource, VehicleCan, checksum
from drivers.can_secoc import AUTH_ERRORS, PENDING, AuthConfig, Sender
from drivers.can_vehicle import CanVehicle, can_vehicle_from_scenario
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.config.scenarios import load_scenario
from vflpcd.base.errors import ConfigError

LIMITS = BicycleConfig.load("nominal").limits
KEY = bytes(range(100, 132))


class Node:
    """The vehicle side, scripted: sends INS and status frames, records the commands it receives."""

    def __init__(self, channel: str, key: bytes | None = None) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.codec = VehicleCan()
        self.counter = CounterSource()
        self.auth = Sender(key) if key is not None else None

    def send(self, frame: can.Message) -> None:
        self.bus.send(frame)
        if self.auth is not None:
            self.bus.send(self.auth.protect(frame))

    def publish(self, x=(1.0, 2.0, 0.3, 5.0, 0.1, 0.05), mode=2, speed=None, faults=None, steer=0.02) -> None:
        c = self.codec
        self.send(c.encode("InsPosition", {"PosX": x[0], "PosY": x[1]}))
        self.send(c.encode("VehicleStatus", {"Speed": x[3] if speed is None else speed, "YawRate": x[5],
                                             "SteerAngle": steer, "Mode": mode,
                                             **(faults or dict.fromkeys(("FaultCmdTimeout", "FaultBadCounter",
                                                                         "FaultBadChecksum", "FaultOutOfRange"), 0))}))
        self.send(c.encode("InsHeadingVelocity", {"Heading": x[2], "VelX": x[3], "VelY": x[4],
                                                  "AliveCounter": self.counter.take()}))

    def commands(self, timeout=0.3) -> list[dict]:
        out, deadline = [], time.monotonic() + timeout
        while time.monotonic() < deadline:
            msg = self.bus.recv(0.01)
            if msg is not None and msg.arbitration_id == 0x100:
                out.append(self.codec.decode(msg).signals)
        return out

    def close(self) -> None:
        self.bus.shutdown()


@pytest.fixture
def channel(request):
    return f"vflpcd-test-{request.node.name}"


def driver(channel, **kw) -> CanVehicle:
    return CanVehicle(BusConfig("virtual", channel), LIMITS, **kw)


async def _settle(s=0.05):
    await asyncio.sleep(s)


def test_state_is_assembled_in_plant_order_from_ins_and_status(channel):
    async def main():
        node, d = Node(channel), driver(channel)
        await d.connect()
        assert d.latest_state() is None and d.fault() is not None
        node.publish()
        await _settle()
        s = d.latest_state()
        np.testing.assert_allclose(s.state, [1.0, 2.0, 0.3, 5.0, 0.1, 0.05], atol=1e-3)
        assert d.state_names == ("X", "Y", "psi", "vx", "vy", "omega")
        assert d.fault() is None and d.ecu_mode == "automatic"
        await d.close()
        node.close()
    asyncio.run(main())


def test_commands_are_encoded_clipped_counted_and_repeated_only_while_fresh(channel):
    async def main():
        node, d = Node(channel), driver(channel, command_hold=0.1)
        await d.connect()
        node.publish()
        await _settle()
        await d.send(np.array([1.5, -0.2]))
        await d.enable()
        await d.send(np.array([1.5, -0.2]))
        await d.send(np.array([99.0, 9.0]))            # clipped to a_max, delta_max
        got = await asyncio.get_running_loop().run_in_executor(None, node.commands, 0.3)
        await d.close()
        node.close()
        return got
    got = asyncio.run(main())
    assert got[0]["AccelCmd"] == pytest.approx(1.5) and got[0]["SteerAngleCmd"] == pytest.approx(-0.2)
    assert got[1]["AccelCmd"] == pytest.approx(LIMITS.a_max) and got[1]["SteerAngleCmd"] == pytest.approx(LIMITS.delta_max)
    assert all(c["Enable"] == 1 for c in got)
    counters = [c["AliveCounter"] for c in got]
    assert all((b - a) % 16 == 1 for a, b in zip(counters, counters[1:]))
    # 2 sent at once, then repeats every 20 ms while the newest is younger than 0.1 s: 3 to 5 more, then silence
    assert 4 <= len(got) <= 8, len(got)


def test_silence_bad_frames_and_an_ecu_takeover_are_faults(channel):
    async def main():
        node, d = Node(channel), driver(channel, state_timeout=0.1)
        await d.connect()
        node.publish()
        await _settle()
        await d.enable()
        assert d.fault() is None
        await _settle(0.15)
        assert "no INS frames" in d.fault()
        node.publish()
        await _settle()
        assert d.fault() is None
        node.publish(mode=3, faults={"FaultCmdTimeout": 1, "FaultBadCounter": 0, "FaultBadChecksum": 0,
                                     "FaultOutOfRange": 0})
        await _settle()
        assert "took over" in d.fault()
        bad = [can.Message(arbitration_id=0x300, data=bytes(5), is_extended_id=False),           # dlc
               can.Message(arbitration_id=0x7FF, data=bytes(8), is_extended_id=False),           # unknown id
               can.Message(arbitration_id=0x200, data=bytes(8), is_extended_id=False)]           # checksum
        data = bytearray(node.codec.encode("InsHeadingVelocity", {"Heading": 0.0, "VelX": 0.0, "VelY": 0.0,
                                                                  "AliveCounter": 0}).data)
        data[0:2] = (32000).to_bytes(2, "little", signed=True)                                  # heading 3.2 rad
        bad.append(can.Message(arbitration_id=0x301, data=bytes(data), is_extended_id=False))   # range
        status = bytearray(node.codec.encode("VehicleStatus", {"Speed": 1, "YawRate": 0, "SteerAngle": 0, "Mode": 2,
                                                               "FaultCmdTimeout": 0, "FaultBadCounter": 0,
                                                               "FaultBadChecksum": 0, "FaultOutOfRange": 0}).data)
        status[7] = (checksum(0x200, status) + 1) & 0xFF
        bad.append(can.Message(arbitration_id=0x200, data=bytes(status), is_extended_id=False))  # checksum
        for m in bad:
            node.bus.send(m)
        node.counter.take()                                                                      # skip one: counter
        node.publish()
        await _settle()
        stats = d.link_stats()
        await d.close()
        node.close()
        return stats
    stats = asyncio.run(main())
    assert stats["bad_frames"] == {"unknown_id": 1, "dlc": 1, "checksum": 2, "range": 1, "counter": 1,
                                   "replayed": 0, "forged": 0, "unauthenticated": 0}


def test_another_senders_commands_and_an_ecu_counter_takeover_are_faults(channel):
    async def main():
        node, d = Node(channel), driver(channel, state_timeout=0.5)
        await d.connect()
        node.publish()
        await _settle()
        await d.enable()
        await d.send(np.array([0.5, 0.0]))
        await _settle()
        assert d.fault() is None and d.foreign_commands == 0           # its own frames do not come back
        replayed = node.codec.encode("VehicleCmd", {"AccelCmd": 2.0, "SteerAngleCmd": 0.3, "Enable": 1,
                                                    "AliveCounter": 3})
        node.bus.send(replayed)
        node.publish()
        await _settle()
        assert "another sender's VehicleCmd frames on the bus (1" in d.fault()
        assert d.link_stats()["foreign_commands"] == 1
        await d.close()
        node.close()

        node, d = Node(channel), driver(channel, state_timeout=0.5)
        await d.connect()
        node.publish()
        await _settle()
        await d.enable()
        node.publish(mode=3, faults={"FaultCmdTimeout": 0, "FaultBadCounter": 1, "FaultBadChecksum": 0,
                                     "FaultOutOfRange": 0})
        await _settle()
        assert "alive-counter errors" in d.fault()
        await d.close()
        node.close()
    asyncio.run(main())


def test_failsafe_brakes_with_the_steering_held_then_hands_back_at_standstill(channel):
    async def main():
        node, d = Node(channel), driver(channel)
        await d.connect()
        node.publish(steer=0.07)
        await _settle()
        await d.enable()
        await d.failsafe("link_lost")
        await d.send(np.array([2.0, 0.0]))              # ignored after the failsafe
        moving = await asyncio.get_running_loop().run_in_executor(None, node.commands, 0.1)
        node.publish(x=(1.0, 2.0, 0.3, 0.0, 0.0, 0.0), speed=0.0, mode=1)
        await _settle()
        node.commands(0.05)
        stopped = await asyncio.get_running_loop().run_in_executor(None, node.commands, 0.1)
        assert d.at_rest
        await d.close()
        node.close()
        return moving, stopped
    moving, stopped = asyncio.run(main())
    assert moving and all(c["AccelCmd"] == pytest.approx(LIMITS.a_min) and c["Enable"] == 1
                          and c["SteerAngleCmd"] == pytest.approx(0.07) for c in moving)
    assert stopped and all(c["Enable"] == 0 for c in stopped)


def test_bus_log_decodes_with_cantools(channel, tmp_path):
    async def main():
        node, d = Node(channel), driver(channel, bus_log=tmp_path / "run.asc")
        await d.connect()
        for _ in range(5):
            node.publish()
            await _settle(0.01)
        await d.enable()
        await d.send(np.array([0.5, 0.01]))
        await _settle()
        await d.close()
        node.close()
    asyncio.run(main())
    db = cantools.database.load_file("config/can/vehicle.dbc")
    names = []
    with can.ASCReader(tmp_path / "run.asc") as reader:
        for msg in reader:
            names.append(db.decode_message(msg.arbitration_id, msg.data) and db.get_message_by_frame_id(msg.arbitration_id).name)
    assert names.count("InsPosition") == 5 and names.count("VehicleStatus") == 5
    assert names.count("VehicleCmd") >= 1


def test_mission_options_are_checked():
    sc = load_scenario("carsim_avoidance")
    v = can_vehicle_from_scenario(sc, {"interface": "remote", "channel": "ws://127.0.0.1:5/"}, "m.toml")
    assert v.bus_cfg.describe() == "remote:ws://127.0.0.1:5/"
    for options, field in [({"interface": "pcan"}, "platform.interface"),
                           ({"interface": "remote", "channel": "vcan0"}, "platform.channel"),
                           ({"state_timeout": 0.0}, "platform.state_timeout"),
                           ({"bus_log": "csv"}, "platform.bus_log"),
                           ({"dbc": "/nonexistent.dbc"}, "platform.dbc"),
                           ({"bitrate": 500000}, "platform")]:
        with pytest.raises(ConfigError) as err:
            can_vehicle_from_scenario(sc, options, "m.toml")
        assert field in str(err.value)


def test_frame_error_kinds_are_the_counted_ones():
    assert set(FRAME_ERRORS) == {"unknown_id", "dlc", "checksum", "range", "counter"}
    assert set(AUTH_ERRORS) == {"replayed", "forged", "unauthenticated"}


def test_fuzz_thousands_of_malformed_frames_are_counted_and_the_state_stays_right(channel):
    """3000 malformed frames among the vehicle's valid ones: every one counted by kind, none used."""
    rng = np.random.default_rng(11)

    async def main():
        node, d = Node(channel), driver(channel, state_timeout=1.0)
        await d.connect()
        sent = dict.fromkeys(("dlc", "checksum", "range", "unknown_id"), 0)
        codec = node.codec
        status = bytearray(codec.encode("VehicleStatus", {"Speed": 1, "YawRate": 0, "SteerAngle": 0, "Mode": 2,
                                                          "FaultCmdTimeout": 0, "FaultBadCounter": 0,
                                                          "FaultBadChecksum": 0, "FaultOutOfRange": 0}).data)
        for i in range(3000):
            kind = tuple(sent)[i % 4]
            if kind == "dlc":
                frame_id = int(rng.choice([0x200, 0x300, 0x301]))
                data = bytes(rng.integers(0, 256, int(rng.integers(0, 8)), dtype=np.uint8))
            elif kind == "checksum":
                frame_id, data = 0x200, bytearray(status)
                data[7] = (checksum(0x200, data) + 1 + int(rng.integers(0, 254))) & 0xFF
            elif kind == "range":                               # heading beyond pi, no checksum on 0x301
                frame_id = 0x301
                data = bytearray(codec.encode("InsHeadingVelocity", {"Heading": 0.0, "VelX": 0.0, "VelY": 0.0,
                                                                     "AliveCounter": 0}).data)
                data[0:2] = int(rng.integers(31500, 32767)).to_bytes(2, "little", signed=True)
            else:
                frame_id, data = int(rng.integers(0x400, 0x7FF)), bytes(8)
            sent[kind] += 1
            node.bus.send(can.Message(arbitration_id=frame_id, data=bytes(data), is_extended_id=False))
            if i % 100 == 0:
                node.publish()
                await asyncio.sleep(0.002)
        node.publish()
        await _settle(0.2)
        stats, state = d.link_stats(), d.latest_state()
        await d.close()
        node.close()
        return sent, stats, state
    sent, stats, state = asyncio.run(main())
    bad = stats["bad_frames"]
    for kind, n in sent.items():
        assert bad[kind] == n, (kind, bad)
    assert bad["counter"] == 0 and stats["frames_ok"] == 3 * 31
    np.testing.assert_allclose(state.state, [1.0, 2.0, 0.3, 5.0, 0.1, 0.05], atol=1e-3)


def test_an_authenticated_link_uses_authenticated_frames_only_and_counts_the_others_by_kind(channel):
    """Spoofed positions (plain, forged PDU, replayed) are dropped and counted; a run of them is a stale
    state; a replayed copy of the driver's own command is counted, a freshly authenticated foreign one
    is the foreign-command fault."""
    async def main():
        node, d = Node(channel, KEY), driver(channel, state_timeout=0.15, auth=AuthConfig(KEY))
        attacker = Node(channel)                               # no key
        await d.connect()
        node.publish()
        await _settle()
        assert d.fault() is None and d.latest_state() is not None
        recorded = can.Message(arbitration_id=0x300, data=bytes(node.codec.encode(
            "InsPosition", {"PosX": 1.0, "PosY": 2.0}).data), is_extended_id=False)
        recorded_auth = node.auth.protect(recorded)            # recorded, never delivered: replayed below
        node.publish()
        await _settle()
        spoof = attacker.codec.encode("InsPosition", {"PosX": 40.0, "PosY": -7.0})
        for _ in range(3):
            attacker.bus.send(spoof)                           # unauthenticated
        attacker.bus.send(can.Message(arbitration_id=0x380, data=bytes(8), is_extended_id=False))     # forged
        attacker.bus.send(recorded)
        attacker.bus.send(recorded_auth)                       # older than what was accepted: replayed
        node.publish()
        await _settle()
        np.testing.assert_allclose(d.latest_state().state[:2], [1.0, 2.0], atol=1e-3)
        assert d.fault() is None
        counts = dict(d.bad_frames)

        await d.enable()
        await d.send(np.array([0.5, 0.0]))
        got = await asyncio.get_running_loop().run_in_executor(None, lambda: receive_for(node.bus, 0.1))
        got = [m for m in got if m.arbitration_id in (0x100, 0x180)]       # the attacker's frames reached it too
        assert got[0].arbitration_id == 0x100 and [m.arbitration_id for m in got] == [0x100, 0x180] * (len(got) // 2)
        node.publish()
        node.bus.send(got[0])
        node.bus.send(got[1])                                  # the driver's own command, replayed
        await _settle()
        assert d.fault() is None and d.foreign_commands == 0

        for _ in range(20):                                    # only spoofed INS for 0.2 s
            attacker.bus.send(spoof)
            attacker.bus.send(can.Message(arbitration_id=0x380, data=bytes(8), is_extended_id=False))
            await _settle(0.01)
        fault = d.fault()
        stats = d.link_stats()
        node.publish()
        await _settle()
        healthy = d.fault()
        second = Node(channel, KEY)                            # a second commander with the key
        second.send(second.codec.encode("VehicleCmd", {"AccelCmd": 2.0, "SteerAngleCmd": 0.3, "Enable": 1,
                                                       "AliveCounter": 0}))
        node.publish()
        await _settle()
        foreign = d.fault()
        await d.close()
        for n in (node, attacker, second):
            n.close()
        return counts, fault, stats, healthy, foreign

    counts, fault, stats, healthy, foreign = asyncio.run(main())
    # the forged PDU and the replay at once; the 3 spoofed positions wait for a PDU, and are pushed out
    # (unauthenticated) by the frames that come after them
    assert (counts["unauthenticated"], counts["forged"], counts["replayed"]) == (0, 1, 1), counts
    assert stats["bad_frames"]["unauthenticated"] == 3 + 20 - PENDING and stats["bad_frames"]["forged"] == 21
    assert "no authenticated INS frames" in fault and "rejected" in fault, fault
    assert stats["authenticated"] and stats["auth_rejected"]["InsPosition"] >= 20
    assert stats["auth_rejected"]["VehicleCmd"] == 1 and stats["bad_frames"]["replayed"] == 2
    assert healthy is None
    assert "another sender's VehicleCmd" in foreign
