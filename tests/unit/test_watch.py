"""``watch`` against a live TelemetryPublisher on loopback (multicast scouting off)."""

from __future__ import annotations

import io
import threading
import time

import pytest

from vflpcd.log.records import Event, TickRecord
from vflpcd.daemon.telemetry import TelemetryConfig, TelemetryPublisher, open_session
from vflpcd.base.errors import ConfigError
from vflpcd.app.watch import watch
from loopback import free_port

VID = "rover-3"


def test_watch_renders_live_telemetry():
    ep = f"tcp/127.0.0.1:{free_port()}"
    session = open_session(TelemetryConfig(listen=(ep,)))
    pub = TelemetryPublisher(session, VID, TelemetryConfig(rate_hz=20.0, health_rate_hz=20.0),
                             state_names=("X", "Y", "psi", "v"), control_names=("delta", "a"))
    stop = threading.Event()

    def daemon():
        k = 0
        while not stop.is_set():
            pub.offer_tick(TickRecord(k=k, t=0.01 * k, stamp_ns=k, mode="running", state=(1.2345, -6.5, 0.25, 3.0),
                                      state_age_s=0.001, reference=(1.0, 2.0), command=(0.1, 0.5),
                                      lateness_s=2e-4, compute_s=1.5e-3, overrun=False))
            pub.offer_health({"mode": "running", "ticks": k, "overruns": 0})
            if k % 20 == 0:
                pub.offer_event(Event(t=0.01 * k, stamp_ns=k, kind="ready", detail={"n": k}))
            k += 1
            stop.wait(0.01)

    th = threading.Thread(target=daemon)
    th.start()
    out = io.StringIO()
    try:
        t0 = time.monotonic()
        assert watch(VID, connect=(ep,), duration_s=1.5, out=out, refresh_s=0.25) == 0
        assert time.monotonic() - t0 < 4.0
    finally:
        stop.set()
        th.join(2.0)
        pub.close()
        session.close()
    text = out.getvalue()
    assert "\x1b[" not in text  # not a terminal: plain blocks
    last = text.strip().split("\n\n")[-1]
    assert VID in last and "mode=running" in last and "X=1.234" in last and "Y=-6.500" in last
    assert "delta=0.100" in last and "compute 1.50 ms" in last and "ticks=" in last
    assert "ready n=" in last


def test_watch_rejects_bad_arguments():
    with pytest.raises(ConfigError) as err:
        watch("bad/id", duration_s=0.0, out=io.StringIO())
    assert err.value.field == "vehicle_id"
    with pytest.raises(ConfigError) as err:
        watch(VID, connect=("localhost:7447",), duration_s=0.0, out=io.StringIO())
    assert err.value.field == "--connect"


def test_watch_without_publisher_returns():
    out = io.StringIO()
    assert watch(VID, duration_s=0.2, out=out, refresh_s=0.1) == 0
    assert "0 messages" in out.getvalue() and "(none yet)" in out.getvalue()


def test_watch_needs_an_identity_for_tls_and_tls_with_one(tmp_path):
    with pytest.raises(ConfigError) as err:
        watch(VID, connect=("tls/127.0.0.1:7447",), duration_s=0.0)
    assert err.value.field == "--identity" and "needs TLS settings" in err.value.message
    for name, text in (("ca.pem", "CERTIFICATE"), ("c.pem", "CERTIFICATE"), ("c.key", "PRIVATE KEY")):
        (tmp_path / name).write_text(f"-----BEGIN {text}-----\nMIIB\n-----END {text}-----\n")
    ident = tmp_path / "gcs.toml"
    ident.write_text('ca = "ca.pem"\ncertificate = "c.pem"\nprivate_key = "c.key"\n')
    with pytest.raises(ConfigError) as err:
        watch(VID, connect=("tcp/127.0.0.1:7447",), duration_s=0.0, identity=ident)
    assert err.value.field == "--connect" and "unencrypted" in err.value.message
    ident.write_text('ca = "ca.pem"\ncertificate = "nope.pem"\nprivate_key = "c.key"\n')
    with pytest.raises(ConfigError) as err:
        watch(VID, connect=("tls/127.0.0.1:7447",), duration_s=0.0, identity=ident)
    assert err.value.file == str(ident) and err.value.field == "certificate"
