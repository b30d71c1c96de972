"""TelemetryPublisher against a real Zenoh subscriber session on loopback (multicast scouting off)."""

from __future__ import annotations

import json
import logging
import socket
import threading
import time

import pytest
import zenoh

from vflpcd.log.records import Event, MissionHeader, ObstacleRecord, TickRecord
from vflpcd.daemon.telemetry import (
    PUBLISHED_TOPICS, TelemetryConfig, TelemetryPublisher, check_endpoint, check_vehicle_id, json_bytes,
    key_expressions, open_session,
)
from vflpcd.base.errors import ConfigError
from vflpcd.base.tomlread import Table
from loopback import free_port, wait_for

VID = "car-7"
STATE_NAMES = ("X", "Y", "psi", "v")
CONTROL_NAMES = ("delta", "a")


def tick(k: int, t: float | None = None) -> TickRecord:
    return TickRecord(k=k, t=0.01 * k if t is None else t, stamp_ns=1_000_000 * k, mode="running",
                      state=(1.0, 2.0, 0.1, 3.0), state_age_s=0.002, reference=(1.5, 2.0), command=(0.05, 0.3),
                      lateness_s=1e-4, compute_s=2e-3, overrun=False, threats=("ob1",), plan_version=2,
                      model_version=1,
                      obstacles=(ObstacleRecord("ob1", (5.0, 1.0), (0.0, -1.0), 0.8, "mission"),))


class Collector:
    """A subscriber session on ``vflpc/<VID>/**``: (topic, decoded JSON, encoding string) per message."""

    def __init__(self, session: zenoh.Session) -> None:
        self.messages: list[tuple[str, dict, str]] = []
        self.sub = session.declare_subscriber(f"vflpc/{VID}/**", self._on)

    def _on(self, sample) -> None:
        topic = str(sample.key_expr)[len(f"vflpc/{VID}/"):]
        self.messages.append((topic, json.loads(sample.payload.to_bytes()), str(sample.encoding)))

    def of(self, topic: str) -> list[dict]:
        return [m for t, m, _ in list(self.messages) if t == topic]


@pytest.fixture
def link():
    """(daemon session listening on loopback, subscriber session connected to it, endpoint)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    a = open_session(TelemetryConfig(listen=(ep,)))
    b = open_session(TelemetryConfig(connect=(ep,)))
    yield a, b, ep
    b.close()
    a.close()


def publisher(session, **cfg) -> TelemetryPublisher:
    return TelemetryPublisher(session, VID, TelemetryConfig(**cfg), state_names=STATE_NAMES,
                              control_names=CONTROL_NAMES)


def connected(pub: TelemetryPublisher) -> None:
    assert wait_for(lambda: all(pub.matched(t) for t in PUBLISHED_TOPICS)), "subscriber never matched"


# --------------------------------------------------------------------------- delivery
def test_every_topic_delivered_as_json(link):
    a, b, _ = link
    col = Collector(b)
    pub = publisher(a, rate_hz=50.0, health_rate_hz=50.0)
    try:
        connected(pub)
        header = MissionHeader(vehicle_id=VID, platform="inproc", controller="vflpc", dim=2, rate_hz=100.0,
                               state_names=STATE_NAMES, control_names=CONTROL_NAMES,
                               path=((0.0, 0.0), (10.0, 0.0)), obstacles=(), mission_file="m.toml")
        pub.offer_header(header)
        pub.offer_tick(tick(42, t=0.42))
        pub.offer_event(Event(t=0.4, stamp_ns=5, kind="ready", detail={"x": float("nan")}))
        pub.offer_health({"mode": "running", "ticks": 42, "lateness_p99_ms": 0.2})
        assert wait_for(lambda: {t for t, _, _ in col.messages} >= set(PUBLISHED_TOPICS)
                        and len(col.of("events")) == 2)
    finally:
        pub.close()
    assert all(enc == "application/json" for _, _, enc in col.messages)
    state, = col.of("state")
    assert state == {"k": 42, "t": 0.42, "stamp_ns": 42_000_000, "mode": "running", "state_names": list(STATE_NAMES),
                     "state": [1.0, 2.0, 0.1, 3.0], "age_s": 0.002}
    command, = col.of("command")
    assert command["control_names"] == list(CONTROL_NAMES) and command["command"] == [0.05, 0.3]
    ref, = col.of("reference")
    assert ref["reference"] == [1.5, 2.0] and ref["plan_version"] == 2 and ref["model_version"] == 1
    obs, = col.of("obstacles")
    assert obs["threats"] == ["ob1"]
    assert obs["obstacles"] == [{"id": "ob1", "center": [5.0, 1.0], "velocity": [0.0, -1.0], "radius": 0.8,
                                 "source": "mission"}]
    timing, = col.of("timing")
    assert timing == {"k": 42, "t": 0.42, "stamp_ns": 42_000_000, "lateness_s": 1e-4, "compute_s": 2e-3,
                      "overrun": False}
    assert col.of("health")[0] == {"mode": "running", "ticks": 42, "lateness_p99_ms": 0.2}
    head, ev = col.of("events")
    assert head["kind"] == "header" and head["vehicle_id"] == VID and head["path"] == [[0.0, 0.0], [10.0, 0.0]]
    assert ev == {"t": 0.4, "stamp_ns": 5, "kind": "ready", "detail": {"x": None}}  # NaN -> null
    assert pub.published >= 8 and pub.errors == 0


def test_rate_limited_to_latest_tick(link):
    a, b, _ = link
    col = Collector(b)
    pub = publisher(a, rate_hz=10.0)
    try:
        connected(pub)
        t0 = time.monotonic()
        for k in range(500):
            pub.offer_tick(tick(k))
            time.sleep(max(0.0, t0 + (k + 1) * 0.002 - time.monotonic()))
        assert wait_for(lambda: col.of("state") and col.of("state")[-1]["k"] == 499, 1.0)
    finally:
        pub.close()
    states = col.of("state")
    assert 5 <= len(states) <= 12, len(states)
    ks = [m["k"] for m in states]
    assert ks == sorted(ks) and len(set(ks)) == len(ks)
    assert len(col.of("timing")) == len(states)


def test_event_burst_all_delivered_in_order(link):
    a, b, _ = link
    col = Collector(b)
    pub = publisher(a, rate_hz=1.0)
    try:
        connected(pub)
        for i in range(50):
            pub.offer_event(Event(t=i * 0.01, stamp_ns=i, kind="worker_error", detail={"job": "replan", "i": i}))
        assert wait_for(lambda: len(col.of("events")) == 50, 2.0)
    finally:
        pub.close()
    assert [m["detail"]["i"] for m in col.of("events")] == list(range(50))
    assert pub.events_dropped == 0


def test_event_queue_bounded(link):
    a, _, _ = link
    pub = publisher(a)
    pub._stop = True  # stop the publishing thread so that nothing drains the queue
    pub._wake.set()
    pub._thread.join(1.0)
    try:
        for i in range(1100):
            pub.offer_event(Event(t=0.0, stamp_ns=i, kind="ready"))
        assert pub.events_dropped == 100
    finally:
        pub.close()


def test_offer_tick_never_blocks(link):
    a, _, _ = link
    pub = publisher(a, rate_hz=200.0)
    rec = tick(1)
    result = {}

    def producer():
        t0 = time.perf_counter()
        for _ in range(10_000):
            pub.offer_tick(rec)
        result["mean"] = (time.perf_counter() - t0) / 10_000

    th = threading.Thread(target=producer)
    th.start()
    th.join(5.0)
    pub.close()
    assert result["mean"] < 50e-6, result


def test_put_errors_logged_not_raised(caplog):
    ep = f"tcp/127.0.0.1:{free_port()}"
    s = open_session(TelemetryConfig(listen=(ep,)))
    pub = publisher(s, rate_hz=100.0)
    for p in pub._pubs.values():
        p.undeclare()
    with caplog.at_level(logging.WARNING, logger="vflpcd.daemon.telemetry"):
        pub.offer_tick(tick(1))
        pub.offer_event(Event(t=0.0, stamp_ns=0, kind="ready"))
        assert wait_for(lambda: pub.errors >= 2)
        pub.close()
    s.close()
    assert any("event=telemetry_put_failed" in r.getMessage() for r in caplog.records)
    assert not pub._thread.is_alive()
    pub.close()  # idempotent
    pub.offer_tick(tick(2))  # harmless after close


def test_json_bytes_sanitizes():
    import numpy as np

    assert json.loads(json_bytes({"a": float("inf"), "b": [np.float32(1.5), np.int64(3)], "c": (1, 2)})) == {
        "a": None, "b": [1.5, 3], "c": [1, 2]}


# --------------------------------------------------------------------------- configuration
def table(data: dict) -> Table:
    return Table(data, "m.toml", "telemetry")


def test_config_defaults_and_values():
    assert TelemetryConfig.from_table(table({})) == TelemetryConfig()
    cfg = TelemetryConfig.from_table(table({"mode": "client", "connect": ["tcp/10.0.0.2:7447"],
                                            "listen": ["udp/[::1]:7000"], "rate_hz": 20, "perception": True}))
    assert cfg.mode == "client" and cfg.connect == ("tcp/10.0.0.2:7447",) and cfg.rate_hz == 20.0
    assert cfg.listen == ("udp/[::1]:7000",) and cfg.perception


@pytest.mark.parametrize("data, field", [
    ({"connect": ["tcp/127.0.0.1"]}, "telemetry.connect"),
    ({"connect": ["127.0.0.1:7447"]}, "telemetry.connect"),
    ({"listen": ["http/127.0.0.1:80"]}, "telemetry.listen"),
    ({"listen": ["tcp/300.1.1.1:7447"]}, "telemetry.listen"),
    ({"listen": ["tcp/127.0.0.1:70000"]}, "telemetry.listen"),
    ({"listen": "tcp/127.0.0.1:7447"}, "telemetry.listen"),
    ({"rate": 10}, "telemetry.rate"),
    ({"rate_hz": 0}, "telemetry.rate_hz"),
    ({"rate_hz": 500}, "telemetry.rate_hz"),
    ({"health_rate_hz": -1}, "telemetry.health_rate_hz"),
    ({"mode": "router"}, "telemetry.mode"),
    ({"mode": "client"}, "telemetry.connect"),
    ({"perception_max_age_s": 0}, "telemetry.perception_max_age_s"),
])
def test_config_errors(data, field):
    with pytest.raises(ConfigError) as err:
        TelemetryConfig.from_table(table(data))
    assert err.value.field == field and err.value.file == "m.toml"


def test_listen_endpoint_in_use():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
        with pytest.raises(ConfigError) as err:
            open_session(TelemetryConfig(listen=(ep,)))
    assert err.value.field == "telemetry.listen" and "in use" in err.value.message and ep in err.value.message


def test_endpoints_and_vehicle_ids():
    assert check_endpoint("tcp/127.0.0.1:7447") is None and check_endpoint("quic/host.local:1") is None
    assert check_endpoint("tcp/127.0.0.1:0") is not None and check_endpoint("tcp/127.0.0.1:0", listen=True) is None
    assert check_vehicle_id("car-7_B") == "car-7_B"
    for bad in ("", "a/b", "a*", "$x", "a#1", "a?", "a b", None):
        with pytest.raises(ValueError, match="vehicle id"):
            check_vehicle_id(bad)
    keys = key_expressions("uav1")
    assert keys["state"] == "vflpc/uav1/state" and keys["perception"] == "vflpc/uav1/perception/obstacles"
    assert set(keys) == set(PUBLISHED_TOPICS) | {"perception"}
