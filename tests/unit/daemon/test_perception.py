"""PerceptionInput fed by a real Zenoh publisher session on loopback (multicast scouting off):
validation, the magnitudes of the mission's world, the message budget and the aggregated reports."""

from __future__ import annotations

import json
import time

import numpy as np
import pytest
import zenoh

import vflpcd.daemon.perception as perception_mod
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Circle, Sphere
from vflpcd.daemon.perception import (
    DROPPED, REJECTED, MessageBudget, PerceptionError, PerceptionInput, PerceptionLimits, parse_message,
)
from vflpcd.daemon.telemetry import TelemetryConfig, open_session
from vflpcd.base.errors import ConfigError
from vflpcd.base.tomlread import Table
from loopback import free_port, wait_for

VID = "car-7"
KEY = f"vflpc/{VID}/perception/obstacles"
ROAD = ReferencePath.line([0.0, 0.0], [100.0, 0.0])
LIMITS = PerceptionLimits.around(ROAD, margin=50.0, max_speed=40.0, max_radius=10.0)   # x -50..150, y -50..50
UNLIMITED_HZ = 1e9        # a budget no test reaches: every message is parsed


def obstacle(oid="ped-1", center=(10.0, 2.0), velocity=(1.0, -0.5), radius=0.6, kind="circle") -> dict:
    return {"id": oid, "shape": {"kind": kind, "radius": radius}, "center": list(center), "velocity": list(velocity)}


def message(obstacles, stamp=None) -> dict:
    return {"stamp": time.time() if stamp is None else stamp, "obstacles": obstacles}


def encode(msg: dict) -> bytes:
    return json.dumps(msg).encode()


class Rig:
    """The daemon's session (listening) with a PerceptionInput, and a source session publishing."""

    def __init__(self, dim=2, max_age_s=0.5, limits=LIMITS, rate_hz=UNLIMITED_HZ) -> None:
        ep = f"tcp/127.0.0.1:{free_port()}"
        self.daemon = open_session(TelemetryConfig(listen=(ep,)))
        self.source = open_session(TelemetryConfig(connect=(ep,)))
        self.events: list[tuple[str, dict]] = []
        self.inp = PerceptionInput(self.daemon, VID, dim, max_age_s, limits, rate_hz,
                                   on_event=lambda kind, detail: self.events.append((kind, detail)))
        # BLOCK: a burst must reach the input whole (Zenoh's default drops under congestion)
        self.pub = self.source.declare_publisher(KEY, encoding=zenoh.Encoding.APPLICATION_JSON,
                                                 congestion_control=zenoh.CongestionControl.BLOCK)
        assert wait_for(lambda: self.pub.matching_status.matching), "perception input never matched"

    def send(self, payload) -> None:
        """Put ``payload`` (dict -> JSON, or bytes as is) and wait until the input has handled it."""
        n = self.handled()
        self.pub.put(payload if isinstance(payload, bytes) else encode(payload))
        assert wait_for(lambda: self.handled() > n), "message not handled"

    def burst(self, payloads: list[bytes]) -> None:
        """Put all ``payloads`` at once and wait until the input has seen them all."""
        n = self.handled()
        for p in payloads:
            self.pub.put(p)
        assert wait_for(lambda: self.handled() >= n + len(payloads), timeout=10.0), (self.handled(), n)

    def handled(self) -> int:
        """Messages dropped, accepted or rejected so far (``received`` counts them on arrival)."""
        return self.inp.dropped + self.inp.accepted + self.inp.rejected

    def of(self, kind: str) -> list[dict]:
        return [d for k, d in self.events if k == kind]

    def close(self) -> None:
        """Close the input (it reports what is left), then both sessions (idempotent)."""
        if self.pub is None:
            return
        self.inp.close()
        pub, self.pub = self.pub, None
        pub.undeclare()
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
    assert rig.inp.accepted == 1 and rig.inp.rejected == 0 and rig.inp.dropped == 0
    obs = rig.inp.snapshot(stamp + 0.3, t_mission=12.5)
    assert [o.id for o in obs] == ["perception:ped-1", "perception:car-2"]
    np.testing.assert_allclose(obs[0].center, [10.0 + 0.3, 2.0 - 0.15])
    np.testing.assert_allclose(obs[0].velocity, [1.0, -0.5])
    np.testing.assert_allclose(obs[1].center, [0.0, 0.0])
    assert obs[0].shape == Circle(0.6) and obs[1].shape == Circle(2.0)
    assert all(o.stamp == 12.5 and o.yaw == 0.0 for o in obs)
    assert obs[0].moving and not obs[1].moving
    np.testing.assert_allclose(obs[0].center_at(13.5), [11.3, 1.35])  # mission time propagates on
    assert rig.events == []                                            # nothing to report


def test_sphere_for_dim_3():
    climb = ReferencePath.line([0.0, 0.0, 0.0], [10.0, 0.0, 5.0])
    r = Rig(dim=3, limits=PerceptionLimits.around(climb, 5.0, 10.0, 2.0))
    try:
        stamp = time.time()
        r.send(message([obstacle(center=(1.0, 2.0, 3.0), velocity=(0.0, 0.0, 1.0), kind="sphere")], stamp=stamp))
        (o,) = r.inp.snapshot(stamp + 0.2, 1.0)
        assert o.shape == Sphere(0.6)
        np.testing.assert_allclose(o.center, [1.0, 2.0, 3.2])
        r.send(message([obstacle(center=(1.0, 2.0, 10.5), velocity=(0.0, 0.0, 0.0), kind="sphere")]))
        assert r.inp.rejected == 1 and "z in [-5, 10]" in r.inp.last_reject    # above the climb + 5 m
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
    (message([obstacle(radius=15.0)]), "obstacles[0].shape.radius must be > 0 and < 10 m (perception_max_radius"),
    (message([obstacle(radius=1e308)]), "obstacles[0].shape.radius must be > 0 and < 10 m"),
    (message([obstacle("a"), obstacle("b", center=(1.7e308, 0.0))]),
     "obstacles[1].center [1.7e+308, 0] lies outside the perception area x in [-50, 150], y in [-50, 50] m"),
    (message([obstacle(center=(-1.7e308, -1.7e308))]), "obstacles[0].center [-1.7e+308, -1.7e+308] lies outside"),
    (message([obstacle(center=(151.0, 0.0))]), "obstacles[0].center [151, 0] lies outside the perception area"),
    (message([obstacle(center=(20.0, -50.5))]), "obstacles[0].center [20, -50.5] lies outside the perception area"),
    (message([obstacle(velocity=(1e308, 1e308))]), "obstacles[0].velocity [1e+308, 1e+308] is faster than 40 m/s"),
    (message([obstacle(velocity=(0.0, -41.0))]), "obstacles[0].velocity [0, -41] is faster than 40 m/s"),
    (message([obstacle(velocity=(30.0, 30.0))]), "obstacles[0].velocity [30, 30] is faster than 40 m/s"),  # 42.4
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
    (b"[" * 30000 + b"]" * 30000, "JSON nested too deeply"),          # within the size limit
]


def test_invalid_messages_rejected(rig):
    good = message([obstacle("keep")], stamp=time.time() + 0.5)  # fresh for the whole test
    rig.send(good)
    for i, (payload, reason) in enumerate(INVALID):
        rig.send(payload() if callable(payload) else payload)
        assert rig.inp.rejected == i + 1, (reason, rig.inp.last_reject)
        assert reason in rig.inp.last_reject, (reason, rig.inp.last_reject)
    assert rig.inp.accepted == 1
    assert [o.id for o in rig.inp.snapshot(time.time(), 1.0)] == ["perception:keep"]


def test_limit_edges_accepted(rig):
    """The area's border, the top speed and radii just below the largest are valid."""
    rig.send(message([obstacle("a", center=(-50.0, 50.0), velocity=(40.0, 0.0), radius=9.99),
                      obstacle("b", center=(150.0, -50.0), velocity=(24.0, -32.0))]))    # |v| = 40
    assert rig.inp.accepted == 1, rig.inp.last_reject


def test_huge_values_never_reach_the_snapshot(rig):
    """The values that used to overflow when propagated are rejected; the last good message stays."""
    stamp = time.time()
    rig.send(message([obstacle("ok")], stamp=stamp))
    rig.send(message([obstacle("big", center=(1.7e308, 1.7e308), velocity=(1e308, 1e308))], stamp=stamp))
    assert rig.inp.rejected == 1 and "outside the perception area" in rig.inp.last_reject
    with np.errstate(over="raise", invalid="raise"):
        (o,) = rig.inp.snapshot(stamp + 0.4, 3.0)
        o.center_at(1e6)
    assert o.id == "perception:ok"


def test_area_is_the_route_bounding_box_grown_by_the_margin():
    quarter = ReferencePath.arc([0.0, 0.0], 20.0, 0.0, np.pi / 2)            # (20, 0) round to (0, 20)
    lim = PerceptionLimits.around(quarter, 5.0, 12.0, 3.0)
    pts = quarter.point_at(np.linspace(0.0, quarter.length, 2000))
    np.testing.assert_allclose(lim.lo, pts.min(axis=0) - 5.0, atol=1e-9)
    np.testing.assert_allclose(lim.hi, pts.max(axis=0) + 5.0, atol=1e-9)
    np.testing.assert_allclose(lim.hi, [25.0, 25.0], atol=1e-6)
    assert (lim.max_speed, lim.max_radius, lim.dim) == (12.0, 3.0, 2)
    ok = message([obstacle(center=(-4.9, 24.9), velocity=(0.0, 0.0), radius=1.0)], stamp=0.0)
    assert parse_message(encode(ok), 2, 0.0, lim).ids == ("ped-1",)
    with pytest.raises(PerceptionError, match="outside the perception area x in"):
        parse_message(encode(message([obstacle(center=(25.1, 0.0), velocity=(0.0, 0.0), radius=1.0)], 0.0)),
                      2, 0.0, lim)


def test_message_budget_token_bucket():
    b = MessageBudget(10.0)                       # 10 a second, bursts of 2
    assert b.capacity == 2.0
    assert [b.take(0.0), b.take(0.0), b.take(0.0)] == [True, True, False]
    assert not b.take(0.05)                       # half a token
    assert b.take(0.1)                            # one token back after 0.1 s
    taken = sum(b.take(0.1 + k * 0.001) for k in range(1, 1001))     # 1 kHz for 1 s
    assert taken == 10
    assert b.take(100.0) and b.take(100.0) and not b.take(100.0)     # refills only up to the burst
    assert MessageBudget(200.0).capacity == 20.0
    with pytest.raises(ValueError):
        MessageBudget(0.0)


def test_budget_drops_are_counted_and_not_parsed(monkeypatch):
    parsed = []
    real = perception_mod.parse_message
    monkeypatch.setattr(perception_mod, "parse_message", lambda *a: parsed.append(1) or real(*a))
    r = Rig(rate_hz=20.0)
    try:
        payload = encode(message([obstacle(f"o{i}", center=(i, 5.0)) for i in range(64)], stamp=time.time() + 0.5))
        t0 = time.monotonic()
        r.burst([payload] * 400)
        elapsed = time.monotonic() - t0
        inp = r.inp
        assert inp.received == 400 and inp.rejected == 0
        assert inp.dropped + inp.accepted == 400
        assert len(parsed) == inp.accepted                          # the drops were never parsed
        assert inp.accepted <= inp.budget.capacity + 20.0 * elapsed + 1
        assert inp.dropped >= 400 - (inp.budget.capacity + 20.0 * elapsed + 1)
        assert len(inp.snapshot(time.time(), 0.0)) == 64            # the accepted ones are used
        assert r.of(DROPPED)[0] == {"count": 1, "total": 1, "budget_hz": 20.0}   # the first, at once
    finally:
        r.close()


def test_flood_of_bad_messages_gives_one_event_per_second():
    """Up to 1 kHz of invalid messages for 2.5 s beyond a 50 Hz budget (what a loaded machine's
    publisher manages: each is counted): per kind at most one event a second (plus the first and
    the last), counts that add up to the counters."""
    r = Rig(rate_hz=50.0)
    try:
        bad = encode(message([obstacle(center=(1e300, 0.0))]))
        sent = 0
        t0 = time.monotonic()
        while time.monotonic() - t0 < 2.5:
            for _ in range(10):
                r.pub.put(bad)
                sent += 1
            time.sleep(0.01)
        elapsed = time.monotonic() - t0
        assert sent > 5 * 50.0 * elapsed, sent                      # a flood: five times the budget at least
        assert wait_for(lambda: r.handled() >= sent, timeout=5.0), (r.handled(), sent)
        r.close()                                                   # reports what is left
        inp = r.inp
        assert inp.received == sent and inp.accepted == 0 and inp.rejected >= 100
        assert inp.rejected <= inp.budget.capacity + 50.0 * elapsed + 1 and inp.dropped == sent - inp.rejected
        for kind, total in ((DROPPED, inp.dropped), (REJECTED, inp.rejected)):
            events = r.of(kind)
            assert 2 <= len(events) <= elapsed / inp.report_period_s + 3, (kind, len(events))
            assert sum(e["count"] for e in events) == total
            assert events[-1]["total"] == total
        assert all("outside the perception area" in e["reason"] for e in r.of(REJECTED))
        assert len(r.events) == inp.reported
    finally:
        r.close()


def test_reports_are_aggregated_per_period(rig):
    """A burst of rejections: the first is reported at once, the rest in one event once the period
    has passed (here made by the control thread's snapshot), with the last reason."""
    rig.burst([encode(message([obstacle(str(k), velocity=(50.0 + k, 0.0))])) for k in range(100)])
    assert rig.inp.rejected == 100
    first = rig.of(REJECTED)
    assert first == [{"count": 1, "total": 1, "reason": first[0]["reason"]}]
    assert "[50, 0] is faster than 40 m/s" in first[0]["reason"]
    time.sleep(rig.inp.report_period_s + 0.05)
    rig.inp.snapshot(time.time(), 0.0)
    rig.inp.snapshot(time.time(), 0.0)                           # nothing new: no second report
    (_, later) = rig.of(REJECTED)
    assert later["count"] == 99 and later["total"] == 100
    assert "[149, 0] is faster than 40 m/s" in later["reason"]     # the last one's reason
    assert rig.of(DROPPED) == []


def test_on_event_set_later_and_failing_callback(rig):
    rig.inp.on_event = None
    rig.send(b"nope")                                             # reported to the log only
    assert rig.inp.rejected == 1 and rig.inp.reported == 1

    def boom(kind, detail):
        raise RuntimeError("callback failed")

    rig.inp.on_event = boom
    time.sleep(rig.inp.report_period_s + 0.05)
    rig.send(b"nope")
    assert rig.inp.rejected == 2 and rig.inp.reported == 2
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
    msg = parse_message(encode(message([obstacle()], stamp=100.0)), 2, 100.0, LIMITS)
    assert msg.ids == ("ped-1",) and msg.centers.shape == (1, 2) and not msg.centers.flags.writeable
    with pytest.raises(ValueError, match="dim 2 or 3"):
        parse_message(b"{}", 4, 0.0, LIMITS)
    with pytest.raises(ValueError, match="limits of dim 2 for a dim 3"):
        parse_message(b"{}", 3, 0.0, LIMITS)
    with pytest.raises(ValueError, match="stamp must be a finite number"):
        parse_message(b'{"stamp": 1e999999, "obstacles": []}', 2, 0.0, LIMITS)
    with pytest.raises(ValueError, match="radius must be a finite number"):
        parse_message(encode(message([obstacle(radius=10**400)], stamp=0.0)), 2, 0.0, LIMITS)


# --------------------------------------------------------------------------- the mission's settings
def table(data: dict) -> Table:
    return Table(data, "m.toml", "telemetry")


def test_settings_defaults_and_values():
    d = TelemetryConfig.from_table(table({}))
    assert (d.perception_area_margin_m, d.perception_max_speed, d.perception_max_radius,
            d.perception_rate_hz) == (50.0, 40.0, 10.0, 50.0)
    c = TelemetryConfig.from_table(table({"perception": True, "perception_area_margin_m": 0,
                                          "perception_max_speed": 12.5, "perception_max_radius": 3,
                                          "perception_rate_hz": 30}))
    assert (c.perception_area_margin_m, c.perception_max_speed, c.perception_max_radius,
            c.perception_rate_hz) == (0.0, 12.5, 3.0, 30.0)


@pytest.mark.parametrize("data, field", [
    ({"perception_area_margin_m": -1.0}, "telemetry.perception_area_margin_m"),
    ({"perception_area_margin_m": "far"}, "telemetry.perception_area_margin_m"),
    ({"perception_max_speed": 0}, "telemetry.perception_max_speed"),
    ({"perception_max_speed": float("inf")}, "telemetry.perception_max_speed"),
    ({"perception_max_radius": 0}, "telemetry.perception_max_radius"),
    ({"perception_max_radius": 150.0}, "telemetry.perception_max_radius"),
    ({"perception_rate_hz": 0}, "telemetry.perception_rate_hz"),
    ({"perception_rate_hz": 1000}, "telemetry.perception_rate_hz"),
    ({"perception_rate": 10}, "telemetry.perception_rate"),
])
def test_settings_errors(data, field):
    with pytest.raises(ConfigError) as err:
        TelemetryConfig.from_table(table(data))
    assert err.value.field == field and err.value.file == "m.toml"
