"""The vehicle's CAN database loads cleanly and fits the vehicle it describes."""

import cantools
import numpy as np
import pytest

from vflpcd.config.vehicles import BicycleConfig
from vflpcd.base.paths import config_dir

DBC = config_dir() / "can" / "vehicle.dbc"


@pytest.fixture(scope="module")
def db():
    return cantools.database.load_file(DBC, strict=True)


def test_messages_ids_and_cycle_times(db):
    got = {m.name: (m.frame_id, m.length, m.cycle_time) for m in db.messages}
    assert got == {"VehicleCmd": (0x100, 8, 20), "VehicleStatus": (0x200, 8, 20),
                   "InsPosition": (0x300, 8, 10), "InsHeadingVelocity": (0x301, 8, 10),
                   "VehicleCmdAuth": (0x180, 8, 20), "VehicleStatusAuth": (0x280, 8, 20),
                   "InsPositionAuth": (0x380, 8, 10), "InsHeadingVelocityAuth": (0x381, 8, 10)}


@pytest.mark.parametrize("params", ["nominal", "exact"])
def test_command_ranges_cover_the_vehicle_limits(db, params):
    lim = BicycleConfig.load(params).limits
    cmd = db.get_message_by_name("VehicleCmd")
    accel, steer = cmd.get_signal_by_name("AccelCmd"), cmd.get_signal_by_name("SteerAngleCmd")
    assert accel.minimum <= lim.a_min and accel.maximum >= lim.a_max
    assert steer.minimum <= -lim.delta_max and steer.maximum >= lim.delta_max
    status = db.get_message_by_name("VehicleStatus").get_signal_by_name("SteerAngle")
    assert status.minimum <= -lim.delta_max and status.maximum >= lim.delta_max


def test_round_trip_within_the_signal_resolution(db):
    rng = np.random.default_rng(0)
    for _ in range(200):
        for msg in db.messages:
            values = {s.name: (int(rng.integers(s.minimum, s.maximum + 1)) if s.scale == 1
                               else float(rng.uniform(s.minimum, s.maximum))) for s in msg.signals}
            back = msg.decode(msg.encode(values), decode_choices=False)
            for s in msg.signals:
                assert back[s.name] == pytest.approx(values[s.name], abs=s.scale / 2 + 1e-12), (msg.name, s.name)


def test_heading_covers_a_full_turn(db):
    heading = db.get_message_by_name("InsHeadingVelocity").get_signal_by_name("Heading")
    assert heading.minimum <= -np.pi and heading.maximum >= np.pi
