"""The authentication of CAN frames (drivers/can_secoc.py): MAC, freshness reconstruction, the
receiver's verdicts, the key file and the DBC layout of the authentication PDUs."""

import struct

import can
import cantools
import pytest

from drivers.can_codec import LINK_MESSAGES, VehicleCan
from drivers.can_secoc import (AUTH_ID_OFFSET, FRESHNESS_BITS, MIN_KEY_BYTES, PENDING, Receiver, Sender, auth_pdu,
                               load_key, mac, reconstruct, secured_ids)
from drivers.can_vehicle import can_vehicle_from_scenario
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.config.scenarios import load_scenario

KEY = bytes(range(32))
CODEC = VehicleCan()
POS = CODEC.message("InsPosition").frame_id
SPAN = 1 << FRESHNESS_BITS


class Clock:
    def __init__(self, ms: int) -> None:
        self.ms = ms

    def __call__(self) -> int:
        return self.ms


def position(x: float, y: float = 0.0) -> can.Message:
    return CODEC.encode("InsPosition", {"PosX": x, "PosY": y})


def rig(now_ms: int = 10_000_000, skew_s: float = 2.0):
    clock, rejected = Clock(now_ms), []
    rx = Receiver(KEY, [POS], rejected.append, clock_skew_s=skew_s, clock_ms=clock)
    return Sender(KEY, clock_ms=clock), rx, clock, rejected


def feed(rx: Receiver, *frames: can.Message) -> list[can.Message]:
    return [out for f in frames if (out := rx.feed(f)) is not None]


def kinds(rejected) -> list[str]:
    return [e.kind for e in rejected]


def test_mac_round_trip_and_layout():
    tx, rx, _, rejected = rig()
    frame = position(12.5, -3.0)
    auth = tx.protect(frame)
    assert auth.arbitration_id == POS + AUTH_ID_OFFSET and len(auth.data) == 8
    low, tag = struct.unpack("<I4s", bytes(auth.data))
    assert low == tx.freshness(POS) % SPAN and tag == mac(KEY, POS, bytes(frame.data), tx.freshness(POS))
    assert rx.feed(frame) is None                     # held until its authentication PDU comes
    (out,) = feed(rx, auth)
    assert out is frame and rejected == [] and rx.newest(POS) == tx.freshness(POS)
    assert mac(KEY, POS, bytes(frame.data), 5) != mac(KEY, POS + 1, bytes(frame.data), 5)     # the id counts
    assert mac(KEY, POS, bytes(frame.data), 5) != mac(bytes(32), POS, bytes(frame.data), 5)   # and the key


def test_freshness_follows_the_clock_and_advances_by_one_at_least():
    tx, _, clock, _ = rig(now_ms=1000)
    values = [tx.freshness(POS) for _ in range(3) if tx.protect(position(0.0))]
    assert values == [1000, 1001, 1002]               # faster than the clock: one per frame
    clock.ms = 5000
    tx.protect(position(0.0))
    assert tx.freshness(POS) == 5000                  # a restarted sender would start here too


@pytest.mark.parametrize("reference, low, expected", [
    (SPAN - 3, 2, SPAN + 2),                          # forward over the wrap of the low bits
    (5 * SPAN + 1, SPAN - 2, 5 * SPAN - 2),           # backward over it: a stale value stays stale
    (7 * SPAN + 100, 150, 7 * SPAN + 150),
    (7 * SPAN + 100, 50, 7 * SPAN + 50),
    (3, SPAN - 1, SPAN - 1),                          # never below 0
])
def test_reconstruction_takes_the_nearest_value(reference, low, expected):
    assert reconstruct(low, reference) == expected


def test_frames_across_the_wrap_of_the_low_bits_are_accepted_in_order():
    start = 9 * SPAN - 4
    tx, rx, clock, rejected = rig(now_ms=start)
    got = []
    for k in range(8):
        clock.ms = start + 2 * k
        frame = position(float(k))
        got += feed(rx, frame, tx.protect(frame))
    assert [CODEC.decode(f).signals["PosX"] for f in got] == [float(k) for k in range(8)] and rejected == []
    assert rx.newest(POS) == 9 * SPAN + 10 and rx.newest(POS) % SPAN == 10


def test_every_single_bit_flip_is_rejected_as_forged():
    tx, _, clock, _ = rig()
    frame = position(1.0, 2.0)
    auth = tx.protect(frame)
    for which in ("data", "auth"):
        for bit in range(64):
            rejected = []
            rx = Receiver(KEY, [POS], rejected.append, clock_ms=clock)
            data, pdu = bytearray(frame.data), bytearray(auth.data)
            (data if which == "data" else pdu)[bit // 8] ^= 1 << (bit % 8)
            out = feed(rx, can.Message(arbitration_id=POS, data=bytes(data), is_extended_id=False),
                       can.Message(arbitration_id=POS + AUTH_ID_OFFSET, data=bytes(pdu), is_extended_id=False))
            assert out == [] and kinds(rejected) == ["forged"], (which, bit)
            assert len(feed(rx, frame, auth)) == 1    # the frame as sent still passes


def test_replayed_and_reordered_frames_are_stale():
    tx, rx, clock, rejected = rig()
    pairs = []
    for k in range(3):
        clock.ms += 10
        frame = position(float(k))
        pairs.append((frame, tx.protect(frame)))
    assert len(feed(rx, *pairs[0], *pairs[2])) == 2
    assert feed(rx, *pairs[1]) == [] and feed(rx, *pairs[0]) == [] and feed(rx, *pairs[2]) == []
    assert kinds(rejected) == ["replayed"] * 3
    mixed = feed(rx, pairs[1][0], pairs[2][1])         # a frame with another frame's PDU
    assert mixed == [] and kinds(rejected)[-1] == "forged"
    for k in range(PENDING):                          # the frame waits on, then is pushed out
        assert feed(rx, position(50.0 + k)) == []
    assert kinds(rejected)[3:] == ["forged", "unauthenticated"]


def test_a_recording_replayed_to_a_fresh_receiver_is_stale_by_the_clock():
    tx, _, clock, _ = rig()
    frame = position(3.0)
    auth = tx.protect(frame)
    clock.ms += 2500                                  # 2.5 s later; the receiver allows 2 s
    rejected = []
    late = Receiver(KEY, [POS], rejected.append, clock_skew_s=2.0, clock_ms=clock)
    assert feed(late, frame, auth) == [] and kinds(rejected) == ["replayed"]
    fresh = Receiver(KEY, [POS], rejected.append, clock_skew_s=3.0, clock_ms=clock)
    assert len(feed(fresh, frame, auth)) == 1


def test_plain_frames_are_unauthenticated_and_an_injected_frame_does_not_block_ours():
    tx, rx, clock, rejected = rig()
    plain = [position(float(k)) for k in range(5)]
    assert feed(rx, *plain) == []
    assert kinds(rejected) == ["unauthenticated"] * (5 - PENDING)
    rejected.clear()
    ours = position(7.0)
    auth = tx.protect(ours)
    spoofs = [position(-50.0 - k) for k in range(PENDING - 1)]      # slipped in between our frame and its PDU
    (out,) = feed(rx, ours, *spoofs, auth)
    assert out is ours
    orphan = can.Message(arbitration_id=POS + AUTH_ID_OFFSET, data=bytes(8), is_extended_id=False)
    assert feed(rx, orphan) == [] and "forged" in kinds(rejected)


def test_own_frames_raise_the_floor_for_their_copies():
    tx, rx, _, rejected = rig()
    frame = position(1.0)
    auth = tx.protect(frame)
    rx.raise_floor(POS, tx.freshness(POS))
    assert feed(rx, frame, auth) == [] and kinds(rejected) == ["replayed"]


def test_other_ids_pass_unchanged():
    _, rx, _, rejected = rig()
    status = CODEC.message("VehicleStatus").frame_id
    other = can.Message(arbitration_id=status + AUTH_ID_OFFSET, data=bytes(8), is_extended_id=False)
    assert feed(rx, other) == [other] and rejected == []


def test_key_files(tmp_path):
    hexfile = tmp_path / "k.hex"
    hexfile.write_text("# a comment\n" + KEY.hex()[:32] + "\n  " + KEY.hex()[32:] + "\n")
    assert load_key(hexfile) == KEY
    raw = tmp_path / "k.bin"
    raw.write_bytes(b"\xff\x00" * MIN_KEY_BYTES)
    assert load_key(raw) == b"\xff\x00" * MIN_KEY_BYTES
    short = tmp_path / "short.hex"
    short.write_text("00" * (MIN_KEY_BYTES - 1))
    with pytest.raises(ValueError, match="at least 16"):
        load_key(short)
    with pytest.raises(ValueError, match="file not found"):
        load_key(tmp_path / "missing.key")
    assert len(load_key(config_dir() / "can" / "demo_secoc.key")) == 32


def test_mission_key_is_relative_to_the_mission_and_checked(tmp_path):
    sc = load_scenario("carsim_avoidance")
    (tmp_path / "keys").mkdir()
    (tmp_path / "keys" / "can.key").write_text(KEY.hex())
    mission = tmp_path / "m.toml"
    v = can_vehicle_from_scenario(sc, {"interface": "virtual", "channel": "x", "auth_key": "keys/can.key"}, mission)
    assert v.auth.key == KEY and v.link_warnings() == ()
    plain = can_vehicle_from_scenario(sc, {"interface": "virtual", "channel": "x"}, mission)
    assert plain.auth is None and "not authenticated" in plain.link_warnings()[0]
    (tmp_path / "short.key").write_text("00" * 8)
    for options, text in [({"auth_key": "nokey.key"}, "file not found"), ({"auth_key": "short.key"}, "8 bytes"),
                          ({"auth_key": 3}, "expected a string"),
                          ({"auth_key": "keys/can.key", "auth_clock_skew": 0.0}, "auth_clock_skew")]:
        with pytest.raises(ConfigError) as err:
            can_vehicle_from_scenario(sc, options, mission)
        assert "platform.auth" in str(err.value) and text in str(err.value), str(err.value)


def test_the_dbc_declares_the_authentication_pdus_as_sent():
    db = cantools.database.load_file(config_dir() / "can" / "vehicle.dbc", strict=True)
    ids = secured_ids(db, LINK_MESSAGES)
    for name, frame_id in ids.items():
        data_msg, auth_msg = db.get_message_by_name(name), db.get_message_by_name(name + "Auth")
        assert auth_msg.senders == data_msg.senders and auth_msg.cycle_time == data_msg.cycle_time
        pdu = auth_pdu(frame_id, 0x1234_5678_9ABC, KEY, bytes(8))
        signals = auth_msg.decode(pdu.data)
        assert signals["FreshnessLow"] == 0x5678_9ABC
        assert signals["Mac"].to_bytes(4, "little") == mac(KEY, frame_id, bytes(8), 0x1234_5678_9ABC)
    bare = cantools.database.load_string('VERSION ""\nBU_: A\nBO_ 256 VehicleCmd: 8 A\n'
                                         ' SG_ X : 0|8@1+ (1,0) [0|255] "" A\n')
    with pytest.raises(ValueError, match="VehicleCmdAuth"):
        secured_ids(bare, ["VehicleCmd"])
