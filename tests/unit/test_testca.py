"""``vflpcd security make-test-ca``: a CA and certificates that openssl verifies, with the CNs and
host names asked for; identity files that load; no file overwritten; bad arguments named."""

from __future__ import annotations

import shutil
import stat
import subprocess

import pytest

from vflpcd.app.cli import main
from vflpcd.app.testca import OUTPUTS, make_test_ca
from vflpcd.base.errors import ConfigError
from vflpcd.daemon.zenoh_security import IdentityFile, TrustedDaemon

pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="needs the openssl command")


def openssl(*args) -> str:
    return subprocess.run(["openssl", *map(str, args)], capture_output=True, text=True, check=True).stdout


def test_certificates_chain_to_the_ca_with_the_names_asked_for(tmp_path, capsys):
    folder = tmp_path / "pki"
    assert main(["security", "make-test-ca", str(folder), "--daemon-name", "car-7", "--host", "rover.local",
                 "--host", "10.0.0.2"]) == 0
    out = capsys.readouterr().out
    assert "for bench set-ups only" in out and f'ca = "{folder / "ca.pem"}"' in out
    # the printed set-up uses the certificate's address: a client checks the daemon's host name
    assert 'listen = ["tls/10.0.0.2:7447"]' in out and "--connect tls/10.0.0.2:7447" in out
    assert sorted(p.name for p in folder.iterdir()) == sorted(OUTPUTS)
    for who, cn in (("daemon", "car-7"), ("gcs", "gcs"), ("perception", "perception")):
        assert openssl("verify", "-CAfile", folder / "ca.pem", folder / f"{who}.pem").strip().endswith("OK")
        text = openssl("x509", "-in", folder / f"{who}.pem", "-noout", "-subject", "-ext", "subjectAltName")
        assert f"CN = {cn}" in text and "DNS:rover.local" in text and "IP Address:10.0.0.2" in text
        assert stat.S_IMODE((folder / f"{who}.key").stat().st_mode) == 0o600
    assert "bench set-ups only" in openssl("x509", "-in", folder / "ca.pem", "-noout", "-subject")
    ident = IdentityFile.load(folder / "gcs.toml")
    assert ident.tls.certificate == (folder / "gcs.pem").resolve() and ident.policy() == TrustedDaemon("car-7")


def test_other_cas_certificates_do_not_verify(tmp_path):
    a, b = make_test_ca(tmp_path / "a"), make_test_ca(tmp_path / "b")
    proc = subprocess.run(["openssl", "verify", "-CAfile", a / "ca.pem", b / "gcs.pem"], capture_output=True)
    assert proc.returncode != 0


def test_files_are_never_overwritten(tmp_path, capsys):
    make_test_ca(tmp_path)
    before = (tmp_path / "ca.key").read_bytes()
    assert main(["security", "make-test-ca", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "ca.pem: exists already" in err
    assert (tmp_path / "ca.key").read_bytes() == before


@pytest.mark.parametrize("options, field", [
    ({"daemon_name": "a/b"}, "--daemon-name"), ({"daemon_name": ""}, "--daemon-name"),
    ({"hosts": ("bad host",)}, "--host"), ({"hosts": ()}, "--host"), ({"days": 0}, "--days"),
])
def test_bad_arguments_are_named(tmp_path, options, field):
    with pytest.raises(ConfigError) as err:
        make_test_ca(tmp_path / "x", **options)
    assert err.value.field == field
    assert not (tmp_path / "x").exists()
