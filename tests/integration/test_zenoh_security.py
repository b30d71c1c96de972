"""Zenoh security from the mission, on loopback: with [telemetry.tls] (mutual TLS) and
[telemetry.access], peers without a certificate of the mission's CA get no telemetry and cannot
publish perception or on the daemon's keys; a permitted identity reads telemetry and publishes
perception; an identity not permitted to publish perception is refused. Certificates come from
``vflpcd security make-test-ca`` (openssl) in a temporary folder."""

from __future__ import annotations

import io
import json
import shutil
import socket
import threading
import time

import numpy as np
import pytest
import zenoh

from loopback import wait_for, zenoh_peer
from vflpcd.app.run import run_mission
from vflpcd.app.testca import make_test_ca
from vflpcd.app.watch import watch
from vflpcd.base.errors import ConfigError
from vflpcd.config.mission import load_mission
from vflpcd.daemon.perception import PerceptionInput, PerceptionLimits
from vflpcd.daemon.telemetry import TelemetryPublisher, key_expressions, open_session
from vflpcd.log.reader import read_flight_log
from vflpcd.log.records import TickRecord

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")

VID = "t1"
KEYS = key_expressions(VID)


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    """(the mission's CA folder, another CA's folder), both with the CNs vflpcd, gcs, perception."""
    return (make_test_ca(tmp_path_factory.mktemp("ca")), make_test_ca(tmp_path_factory.mktemp("other-ca")))


def secure_mission(mission_file, port, folder, telemetry=("gcs",), perception=("perception",)):
    path = mission_file(rate_hz=20.0, telemetry_port=port,
                        telemetry_extra="perception = true\nperception_max_age_s = 0.5",
                        extra=f"""
[telemetry.tls]
ca = "{folder / 'ca.pem'}"
certificate = "{folder / 'daemon.pem'}"
private_key = "{folder / 'daemon.key'}"
mutual = true
[telemetry.access]
telemetry = {json.dumps(list(telemetry))}
perception = {json.dumps(list(perception))}
""")
    path.write_text(path.read_text().replace('"tcp/127.0.0.1:', '"tls/127.0.0.1:'))
    return path


def uncertified_peer(port, folder):
    """A TLS peer that trusts the mission's CA but has no certificate of its own."""
    cfg = zenoh.Config()
    for key, value in (("mode", "peer"), ("connect/endpoints", [f"tls/127.0.0.1:{port}"]),
                       ("scouting/multicast/enabled", False),
                       ("transport/link/tls/root_ca_certificate", str(folder / "ca.pem"))):
        cfg.insert_json5(key, json.dumps(value))
    return zenoh.open(cfg)


class Peer:
    """A peer session that records the daemon's telemetry it receives (state payloads in mode
    "running"), the other peers' spoofs it receives (their names) and every key it receives on."""

    def __init__(self, name: str, session) -> None:
        self.name, self.session = name, session
        self.running: list[dict] = []
        self.spoofed: set[str] = set()
        self.keys: set[str] = set()
        self.sub = session.declare_subscriber(f"vflpc/{VID}/**", self._on)

    def _on(self, sample) -> None:
        key, payload = str(sample.key_expr), sample.payload.to_bytes()
        self.keys.add(key)
        if b"SPOOFED" in payload:
            by = json.loads(payload)["by"]
            if by != self.name:                 # its own puts come back to it locally
                self.spoofed.add(by)
            return
        if key == KEYS["state"] and json.loads(payload).get("mode") == "running":
            self.running.append(json.loads(payload))

    def send(self, perception: bool = True) -> None:
        """Put a perception message naming this peer (beside the road), then a spoofed state and
        failsafe event."""
        if perception:
            msg = {"stamp": time.time(), "obstacles": [{"id": f"from-{self.name}", "center": [10.0, 30.0],
                                                        "shape": {"kind": "circle", "radius": 0.5},
                                                        "velocity": [0.0, 0.0]}]}
            self.session.put(KEYS["perception"], json.dumps(msg))
        self.session.put(KEYS["state"], json.dumps({"mode": "SPOOFED", "k": 0, "by": self.name}))
        self.session.put(KEYS["events"], json.dumps({"kind": "failsafe", "detail": {"SPOOFED": True}, "by": self.name}))

    def close(self) -> None:
        self.sub.undeclare()
        self.session.close()


def tick(k: int) -> TickRecord:
    return TickRecord(k=k, t=0.05 * k, stamp_ns=k, mode="running", state=(1.0, 2.0, 0.0, 3.0), state_age_s=0.001,
                      reference=(1.0, 2.0), command=(0.0, 0.1), lateness_s=1e-4, compute_s=1e-3, overrun=False)


def test_session_from_the_mission_serves_only_its_identities(certs, mission_file, port):
    """The daemon's session as ``vflpcd run`` opens it, from the mission's [telemetry]: the GCS
    identity reads telemetry, the perception identity publishes perception; the GCS is refused
    perception; nobody else (no certificate, another CA's, plain TCP) reads or publishes."""
    ours, theirs = certs
    mission = load_mission(secure_mission(mission_file, port, ours))
    session = open_session(mission.telemetry, vehicle_id=mission.vehicle_id)
    tc = mission.telemetry
    pub = TelemetryPublisher(session, VID, tc)
    limits = PerceptionLimits(lo=np.array([-100.0, -100.0]), hi=np.array([100.0, 100.0]), max_speed=40.0,
                              max_radius=10.0)
    inp = PerceptionInput(session, VID, 2, 5.0, limits, 200.0)
    perceived: list[str] = []
    spy = session.declare_subscriber(f"vflpc/{VID}/**", lambda s: perceived.append(s.payload.to_bytes().decode()))
    peers: list[Peer] = []
    try:
        peers = [Peer("gcs", zenoh_peer(port, ours / "gcs.toml")),
                 Peer("perception", zenoh_peer(port, ours / "perception.toml")),
                 Peer("other-ca-gcs", zenoh_peer(port, theirs / "gcs.toml")),
                 Peer("other-ca-perception", zenoh_peer(port, theirs / "perception.toml")),
                 Peer("no-certificate", uncertified_peer(port, ours)),
                 Peer("plain-tcp", zenoh_peer(port))]
        gcs, per, *strangers = peers
        k = 0

        def step():
            nonlocal k
            pub.offer_tick(tick(k))
            k += 1
            for p in peers:
                p.send()
            time.sleep(0.02)
            return bool(gcs.running) and inp.accepted > 0

        assert wait_for(step, timeout=5.0), (len(gcs.running), inp.received)
        for _ in range(25):                               # 0.5 s more for anything refused to show up
            step()
    finally:
        for p in peers:
            p.close()
        spy.undeclare()
        inp.close()
        pub.close()
        session.close()
    # the permitted reader gets the daemon's telemetry and nobody's spoof
    assert gcs.running and gcs.running[-1]["k"] > 0 and gcs.spoofed == set()
    # only the perception identity's messages reached the daemon, and no spoofed state or event
    ids = {o["id"] for m in perceived if m.startswith('{"stamp"') for o in json.loads(m)["obstacles"]}
    assert ids == {"from-perception"}, ids
    assert inp.rejected == 0 and inp.accepted == inp.received
    assert not any("SPOOFED" in m for m in perceived)
    # the perception identity may not read telemetry; the strangers get nothing but their own puts
    assert per.running == [] and per.spoofed == set()
    for p in strangers:
        assert p.running == [] and p.spoofed == set(), (p.name, len(p.running), p.spoofed)
        assert p.keys == {KEYS["perception"], KEYS["state"], KEYS["events"]}, (p.name, p.keys)


def test_daemon_over_mutual_tls_with_watch_and_perception(certs, mission_file, port):
    """``vflpcd run`` on a secured mission: ``watch`` with the GCS identity file shows the running
    daemon and no spoof; the perception identity's walker is used; the obstacle the GCS identity
    (not permitted to publish perception) sends is not."""
    ours, _ = certs
    mission = load_mission(secure_mission(mission_file, port, ours))
    out = io.StringIO()
    watched: list[int] = []
    stop, listening = threading.Event(), threading.Event()

    def perceive():
        per, gcs = Peer("perception", zenoh_peer(port, ours / "perception.toml")), None
        try:
            gate = per.session.declare_publisher(KEYS["perception"])
            wait_for(lambda: gate.matching_status.matching or stop.is_set(), timeout=15.0)  # the daemon listens
            listening.set()
            gcs = Peer("gcs", zenoh_peer(port, ours / "gcs.toml"))
            for _ in range(60):
                if stop.is_set():
                    break
                gate.put(json.dumps({"stamp": time.time(), "obstacles": [
                    {"id": "walker", "shape": {"kind": "circle", "radius": 0.4}, "center": [60.0, 6.0],
                     "velocity": [0.0, 0.0]}]}))
                gcs.send()                                # an intruding obstacle, a spoofed state and event
                per.send(perception=False)                # a spoofed state and event from a permitted publisher
                time.sleep(0.05)
        finally:
            listening.set()
            if gcs is not None:
                gcs.close()
            per.close()

    def look():
        listening.wait(15.0)
        watched.append(watch(VID, connect=(f"tls/127.0.0.1:{port}",), duration_s=3.0, out=out, refresh_s=0.25,
                             identity=ours / "gcs.toml"))

    sender, viewer = threading.Thread(target=perceive), threading.Thread(target=look)
    sender.start()
    viewer.start()
    try:
        result = run_mission(mission, stop_after_s=4.5)
    finally:
        stop.set()
        sender.join(10.0)
        viewer.join(10.0)
    assert watched == [0]
    text = out.getvalue()
    assert "mode=running" in text and "SPOOFED" not in text and "failsafe" not in text
    log = read_flight_log(result.log_path)
    walker = log.obstacles.get("perception:walker")
    assert walker is not None and np.isfinite(walker).all(axis=1).sum() >= 10, list(log.obstacles)
    assert not any(oid.startswith("perception:from-") for oid in log.obstacles), list(log.obstacles)
    assert [e for e in log.events if e.kind == "failsafe"] == []
    assert result.outcome.loop.perception.rejected == 0


def test_check_refuses_a_tls_endpoint_without_certificates(certs, mission_file, port, capsys):
    """``vflpcd check``: a tls/ endpoint without [telemetry.tls] is exit 2 and one line naming the
    field; with the mission's certificates (relative paths) the same mission is ok."""
    from vflpcd.app.cli import main

    plain = mission_file(telemetry_port=port)
    plain.write_text(plain.read_text().replace('"tcp/127.0.0.1:', '"tls/127.0.0.1:'))
    assert main(["check", str(plain)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{plain}: telemetry.tls: listen: endpoint tls/127.0.0.1:{port} needs TLS" in err
    ours, _ = certs
    (plain.parent / "pki").symlink_to(ours)
    secured = secure_mission(mission_file, port, ours)
    secured.write_text(secured.read_text().replace(f'"{ours}/', '"pki/'))
    assert 'ca = "pki/ca.pem"' in secured.read_text()
    assert main(["check", str(secured)]) == 0
    assert "ok: vehicle t1" in capsys.readouterr().out
    (plain.parent / "pki").unlink()
    assert main(["check", str(secured)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "telemetry.tls.ca: " in err and "file not found" in err and str(plain.parent / "pki") in err


def test_a_key_of_another_certificate_is_named_when_the_session_opens(certs, mission_file, port):
    ours, _ = certs
    path = secure_mission(mission_file, port, ours)
    path.write_text(path.read_text().replace(f'"{ours / "daemon.key"}"', f'"{ours / "gcs.key"}"'))
    mission = load_mission(path)                          # both files are PEM: check cannot tell
    with pytest.raises(ConfigError) as err:
        open_session(mission.telemetry, vehicle_id=mission.vehicle_id, file=mission.file)
    assert err.value.field == "telemetry.tls" and "Zenoh cannot use the certificates" in err.value.message
    assert "\n" not in str(err.value)


def test_a_tls_endpoint_in_use_is_named_as_in_use_not_as_a_certificate_problem(certs, mission_file):
    ours, _ = certs
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        mission = load_mission(secure_mission(mission_file, s.getsockname()[1], ours))
        with pytest.raises(ConfigError) as err:
            open_session(mission.telemetry, vehicle_id=mission.vehicle_id, file=mission.file)
    assert err.value.field == "telemetry.listen" and "already in use" in err.value.message, err.value
