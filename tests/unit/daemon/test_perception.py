"""PerceptionInput fed by a real Zenoh publisher session on loopback (multicast scouting off)."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh

from vflpcd.core.shapes import Circle, Sphere
from vflpcd.daemon.perception import PerceptionInput, parse_message
from vflpcd.daemon.telemetry import TelemetryConfig, open_session
from loopback import free_port, wait_for

VID = "car-7"
KEY = f"vflpc/{VID}/perception/obstacles"


def obstacle(oid="ped-1", center=(10.0, 2.0), velocity=(1.0, -0.5), radius=0.6, kind="circle") -> dict:
    return {"id": oid, "shape": {"kind": kind, "radius": radius}, "center": list(center), "velocity": list(velocity)}


def message(obstacles, stamp=None) -> dict:
    return {"stamp": time.time() if stamp is None else stamp, "obstacles": obstacles}


class Rig:
    """The daemon's session (listening) with a PerceptionInput, and a source session publishing."""

    def __init__(self, dim=2, max_age_s=0.5) -> None:
        ep = f"tcp/127.0.0.1:{free_port()}"
        self.daemon = open_session(TelemetryConfig(listen=(ep,)))
        self.source = open_session(TelemetryConfig(connect=(ep,)))
        self.reasons: list[str] = []
        self.inp = PerceptionInput(self.daemon, VID, dim, max_age_s, on_reject=self.reasons.append)
        self.pub = self.source.declare_publisher(KEY, encoding=zenoh.Encoding.APPLICATION_JSON)
        assert wait_for(lambda: self.pub.matching_status.matching), "perception input never matched"

    def send(self, payload) -> None:
        """Put ``payload`` (dict -> JSON, or bytes as is) and wait until the input has handled it."""
        n = self.inp.received
        self.pub.put(payload if isinstance(payload, bytes) else json.dumps(payload).encode())
        assert wait_for(lambda: self.inp.received > n), "message not received"

    def close(self) -> None:
        self.inp.close()
        self.pub.undeclare()
        self.source.close()
        self.daemon.close()


@pytest.fixture
def rig():
    r = Rig()
    yield r
    r.close()


def test_valid_message_propagated(rig):
    stamp = time.time() - 0.1
    rig.send(message([obstacle(), obstacle("car-2", (0.0, 0.0), (0.0, 0.0), 2.0)], stamp=stamp))
    assert rig.inp.accepted == 1 and rig.inp.rejected == 0
    obs = rig.inp.snapshot(stamp + 0.3, t_mission=12.5)
    assert [o.id for o in obs] == ["perception:ped-1", "perception:car-2"]
    np.testing.assert_allclose(obs[0].center, [10.0 + 0.3, 2.0 - 0.15])
    np.testing.assert_allclose(obs[0].velocity, [1.0, -0.5])
    np.testing.assert_allclose(obs[1].center, [0.0, 0.0])
    assert obs[0].shape == Circle(0.6) and obs[1].shape == Circle(2.0)
    assert all(o.stamp == 12.5 and o.yaw == 0.0 for o in obs)
    assert obs[0].moving and not obs[1].moving
    np.testing.assert_allclose(obs[0].center_at(13.5), [11.3, 1.35])  # mission time propagates on


def test_sphere_for_dim_3():
    r = Rig(dim=3)
    try:
        stamp = time.time()
        r.send(message([obstacle(center=(1.0, 2.0, 3.0), velocity=(0.0, 0.0, 1.0), kind="sphere")], stamp=stamp))
        (o,) = r.inp.snapshot(stamp + 0.2, 1.0)
        assert o.shape == Sphere(0.6)
        np.testing.assert_allclose(o.center, [1.0, 2.0, 3.2])
    finally:
        r.close()


INVALID = [
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "not a JSON object"),
    (message([obstacle(center=(float("nan"), 1.0))]), "obstacles[0].center[0] must be a finite number"),
    (message([obstacle(center=(1.0, 2.0, 3.0))]), "obstacles[0].center must be a list of 2 numbers"),
    (message([obstacle(velocity=(1.0,))]), "obstacles[0].velocity must be a list of 2 numbers"),
    (message([obstacle(kind="sphere")]), "obstacles[0].shape.kind must be 'circle'"),
    (message([obstacle(radius=-1.0)]), "obstacles[0].shape.radius must be > 0"),
    (message([obstacle(radius=150.0)]), "obstacles[0].shape.radius must be > 0 and < 100 m"),
    (message([obstacle("a"), obstacle("a")]), "obstacles[1].id 'a' is a duplicate"),
    (message([obstacle("")]), "obstacles[0].id must be a non-empty string"),
    (message([obstacle(str(i)) for i in range(65)]), "too many obstacles (65 > 64)"),
    (lambda: message([obstacle()], stamp=time.time() + 30.0), "in the future"),   # stamped when sent
    ({"stamp": float("inf"), "obstacles": []}, "stamp must be a finite number"),
    ({"obstacles": []}, "missing field stamp"),
    ({"stamp": 1.0}, "missing field obstacles"),
    (message([{"id": "x", "center": [0, 0], "velocity": [0, 0]}]), "missing field obstacles[0].shape"),
    (message({"id": "x"}), "obstacles must be a list"),
    (message(["x"]), "obstacles[0] must be an object"),
    (message([obstacle(center=(True, 1.0))]), "obstacles[0].center[0] must be a finite number"),
    (b" " * (64 * 1024 + 1), "payload too large"),
]


def test_invalid_messages_rejected(rig):
    good = message([obstacle("keep")], stamp=time.time() + 0.5)  # fresh for the whole test
    rig.send(good)
    for i, (payload, reason) in enumerate(INVALID):
        rig.send(payload() if callable(payload) else payload)
        assert rig.inp.rejected == i + 1, (reason, rig.reasons)
        assert reason in rig.reasons[-1], (reason, rig.reasons[-1])
        assert rig.inp.last_reject == rig.reasons[-1]
    assert rig.inp.accepted == 1
    assert [o.id for o in rig.inp.snapshot(time.time(), 1.0)] == ["perception:keep"]


def test_on_reject_set_later_and_failing_callback(rig):
    rig.inp.on_reject = None
    rig.send(b"nope")
    assert rig.inp.rejected == 1

    def boom(reason):
        raise RuntimeError("callback failed")

    rig.inp.on_reject = boom
    rig.send(b"nope")
    assert rig.inp.rejected == 2
    rig.send(message([obstacle()]))
    assert rig.inp.accepted == 1  # the subscriber survived the failing callback


def test_stale_or_missing_gives_nothing(rig):
    assert rig.inp.snapshot(time.time(), 0.0) == [] and rig.inp.stale == 1
    stamp = time.time() - 1.0
    rig.send(message([obstacle()], stamp=stamp))
    assert rig.inp.accepted == 1
    assert rig.inp.snapshot(time.time(), 0.0) == [] and rig.inp.stale == 2
    assert len(rig.inp.snapshot(stamp + 0.4, 0.0)) == 1


def test_parse_message_direct():
    msg = parse_message(json.dumps(message([obstacle()], stamp=100.0)).encode(), 2, now_unix=100.0)
    assert msg.ids == ("ped-1",) and msg.centers.shape == (1, 2) and not msg.centers.flags.writeable
    with pytest.raises(ValueError, match="dim 2 or 3"):
        parse_message(b"{}", 4, 0.0)
    with pytest.raises(ValueError, match="stamp must be a finite number"):
        parse_message(b'{"stamp": 1e999999, "obstacles": []}', 2, 0.0)
    with pytest.raises(ValueError, match="radius must be a finite number"):
        parse_message(json.dumps(message([obstacle(radius=10**400)], stamp=0.0)).encode(), 2, 0.0)
