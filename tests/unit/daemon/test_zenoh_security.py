"""[telemetry.tls] / [telemetry.access] validation and the Zenoh configuration built from them."""

from __future__ import annotations

import json

import pytest

from vflpcd.base.errors import ConfigError
from vflpcd.base.tomlread import Table
from vflpcd.daemon.telemetry import TelemetryConfig, key_expressions, key_space, open_session, zenoh_config
from vflpcd.daemon.zenoh_security import AccessConfig, IdentityFile, TrustedDaemon
from loopback import free_port

CERT = "-----BEGIN CERTIFICATE-----\nMIIB\n-----END CERTIFICATE-----\n"
KEY = "-----BEGIN PRIVATE KEY-----\nMIIB\n-----END PRIVATE KEY-----\n"


@pytest.fixture
def folder(tmp_path):
    """tmp/mission.toml's folder with certs/ca.pem, certs/d.pem, certs/d.key (PEM-shaped, not usable)."""
    (tmp_path / "certs").mkdir()
    for name, text in (("ca.pem", CERT), ("d.pem", CERT), ("d.key", KEY)):
        (tmp_path / "certs" / name).write_text(text)
    return tmp_path


def secured(**changes) -> dict:
    data = {"listen": ["tls/127.0.0.1:7447"], "perception": True,
            "tls": {"ca": "certs/ca.pem", "certificate": "certs/d.pem", "private_key": "certs/d.key"},
            "access": {"telemetry": ["gcs"], "perception": ["perception"]}}
    for path, value in changes.items():
        *outer, key = path.split("__")
        d = data
        for k in outer:
            d = d[k]
        if value is None:
            d.pop(key)
        else:
            d[key] = value
    return data


def parse(folder, data) -> TelemetryConfig:
    return TelemetryConfig.from_table(Table(data, folder / "mission.toml", "telemetry"))


def test_tls_files_resolve_against_the_mission_file(folder, monkeypatch):
    monkeypatch.chdir("/")
    cfg = parse(folder, secured())
    assert cfg.tls.ca == (folder / "certs" / "ca.pem").resolve() and cfg.tls.mutual is True
    assert cfg.tls.private_key == (folder / "certs" / "d.key").resolve()
    assert cfg.access == AccessConfig(telemetry=("gcs",), perception=("perception",))
    absolute = parse(folder, secured(tls__ca=str(folder / "certs" / "ca.pem")))
    assert absolute.tls.ca == cfg.tls.ca


@pytest.mark.parametrize("changes, field, words", [
    ({"tls": None, "access": None}, "telemetry.tls", "tls/127.0.0.1:7447 needs TLS settings"),
    ({"tls": None, "access": None, "listen": [], "connect": ["quic/10.0.0.2:7447"]}, "telemetry.tls",
     "quic/10.0.0.2:7447 needs TLS settings"),
    ({"tls__private_key": None}, "telemetry.tls.private_key", "missing required field"),
    ({"tls__ca": "certs/nope.pem"}, "telemetry.tls.ca", "file not found"),
    ({"tls__certificate": "certs/d.key"}, "telemetry.tls.certificate", "not a PEM file holding a certificate"),
    ({"tls__private_key": "certs"}, "telemetry.tls.private_key", "not a regular file (a directory)"),
    ({"tls__cert": "x.pem"}, "telemetry.tls.cert", "unknown field"),
    ({"tls__mutual": "yes"}, "telemetry.tls.mutual", "true or false"),
    ({"listen": ["tls/127.0.0.1:7447", "tcp/127.0.0.1:7448"]}, "telemetry.listen", "unencrypted"),
    ({"connect": ["udp/127.0.0.1:7448"]}, "telemetry.connect", "unencrypted"),
    ({"tls": None}, "telemetry.tls", "needs TLS settings"),
    ({"listen": [], "tls": None}, "telemetry.access", "needs [telemetry.tls] with mutual = true"),
    ({"tls__mutual": False}, "telemetry.access", "needs [telemetry.tls] with mutual = true"),
    ({"access__perception": None}, "telemetry.access.perception", "no identity may publish it"),
    ({"access__telemetry": [""]}, "telemetry.access.telemetry", "certificate common name"),
    ({"access__telemetry": ["gcs\n"]}, "telemetry.access.telemetry", "certificate common name"),
    ({"access__telemetry": "gcs"}, "telemetry.access.telemetry", "list of strings"),
    ({"access__readers": ["gcs"]}, "telemetry.access.readers", "unknown field"),
])
def test_security_problems_are_named(folder, changes, field, words):
    with pytest.raises(ConfigError) as err:
        parse(folder, secured(**changes))
    assert err.value.field == field and words in err.value.message, err.value
    assert "\n" not in str(err.value)


def test_tls_without_access_control_and_without_perception_identities(folder):
    cfg = parse(folder, secured(access=None, perception=False, tls__mutual=False))
    assert cfg.access is None and cfg.tls.mutual is False
    assert parse(folder, secured(access__perception=None, perception=False)).access.perception == ()


def test_default_config_is_the_open_profile(folder):
    assert parse(folder, {}) == TelemetryConfig()
    zc = zenoh_config(TelemetryConfig(listen=("tcp/127.0.0.1:7447",)))
    assert zc.get_json("access_control/enabled") == "false"
    assert zc.get_json("transport/link/tls/root_ca_certificate") == "null"
    assert zc.get_json("scouting/gossip/enabled") == "null"          # Zenoh's default, as before


def test_secured_config_builds_mtls_access_control_and_no_gossip(folder):
    cfg = parse(folder, secured())
    zc = zenoh_config(cfg, vehicle_id="car-7")
    assert json.loads(zc.get_json("transport/link/tls/enable_mtls")) is True
    assert json.loads(zc.get_json("transport/link/tls/listen_private_key")) == str(cfg.tls.private_key)
    assert json.loads(zc.get_json("transport/link/tls/connect_certificate")) == str(cfg.tls.certificate)
    assert json.loads(zc.get_json("scouting/gossip/enabled")) is False
    acl = json.loads(zc.get_json("access_control"))
    assert acl["enabled"] is True and acl["default_permission"] == "deny"
    allowed_in = {k for r in acl["rules"] if "ingress" in r["flows"] and "put" in r["messages"] for k in r["key_exprs"]}
    assert allowed_in == {"vflpc/car-7/perception/obstacles"}          # no remote put on the published topics
    assert {s["id"]: s["cert_common_names"] for s in acl["subjects"]} == {"readers": ["gcs"],
                                                                          "perception": ["perception"]}
    with pytest.raises(ValueError, match="vehicle id"):
        zenoh_config(cfg)


def test_access_control_leaves_out_empty_identity_lists():
    acl = AccessConfig(telemetry=("gcs",)).access_control(key_expressions("v"), key_space("v"))
    assert [s["id"] for s in acl["subjects"]] == ["readers"] and [p["id"] for p in acl["policies"]] == ["readers"]
    pin = TrustedDaemon("vflpcd").access_control(key_expressions("v"), key_space("v"))
    assert pin["subjects"] == [{"id": "daemon", "cert_common_names": ["vflpcd"]}]
    assert pin["rules"][0]["key_exprs"] == ["vflpc/v/**"]


def test_certificates_zenoh_cannot_use_are_named_when_opening(folder):
    cfg = parse(folder, secured(listen=[f"tls/127.0.0.1:{free_port()}"]))
    with pytest.raises(ConfigError) as err:
        open_session(cfg, vehicle_id="car-7", file="m.toml")
    assert err.value.field == "telemetry.tls" and "certificates" in err.value.message
    assert "\n" not in str(err.value) and " at /" not in str(err.value)


def test_identity_file(folder):
    path = folder / "gcs.toml"
    files = 'ca = "certs/ca.pem"\ncertificate = "certs/d.pem"\nprivate_key = "certs/d.key"\n'
    path.write_text(files + 'daemon = "vflpcd"\n')
    ident = IdentityFile.load(path)
    assert ident.tls.ca == (folder / "certs" / "ca.pem").resolve() and ident.policy() == TrustedDaemon("vflpcd")
    path.write_text(files)
    assert IdentityFile.load(path).policy() is None
    path.write_text(files + 'daemon = ""\n')
    with pytest.raises(ConfigError) as err:
        IdentityFile.load(path)
    assert err.value.file == str(path) and err.value.field == "daemon"
    with pytest.raises(ConfigError) as err:
        IdentityFile.load(folder / "missing.toml")
    assert err.value.field == "<file>"
