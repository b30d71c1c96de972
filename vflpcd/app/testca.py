"""``vflpcd security make-test-ca DIR``: a test CA and certificates for a bench set-up.

FOR BENCH SET-UPS ONLY: the private keys are written unencrypted next to the CA's own key, which
signs whatever it is given; nothing here rotates or revokes anything (``docs/security.md``).

Writes, with the ``openssl`` command (EC P-256 keys, SHA-256 signatures, ``days`` of validity):

* ``ca.pem`` / ``ca.key``: the CA;
* ``daemon.pem`` / ``daemon.key``: the daemon's certificate, CN ``daemon_name`` (e.g. the vehicle
  id), with the ``hosts`` it is reached at as subject alternative names (TLS clients check them);
* ``gcs.pem`` / ``gcs.key`` (CN ``gcs``) and ``perception.pem`` / ``perception.key`` (CN
  ``perception``): a ground station's and a perception publisher's;
* ``gcs.toml`` / ``perception.toml``: their identity files (``vflpcd watch --identity``), which
  accept telemetry from ``daemon_name`` only.

Every certificate is good for TLS servers and clients alike. Keys are readable by their owner only.
"""

from __future__ import annotations

import ipaddress
import os
import re
import secrets
import shutil
import subprocess
import tempfile
from pathlib import Path

from vflpcd.base.errors import ConfigError

DEFAULT_HOSTS = ("localhost", "127.0.0.1")
CLIENTS = ("gcs", "perception")
CA_NAME = "vflpcd test CA (bench set-ups only)"
_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,63}")
_HOST = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9.-]{0,251}[A-Za-z0-9])?")
_LEAF_EXTENSIONS = ("basicConstraints = critical, CA:FALSE\nkeyUsage = critical, digitalSignature\n"
                    "extendedKeyUsage = serverAuth, clientAuth\nsubjectAltName = {san}\n")
OUTPUTS = ("ca.pem", "ca.key") + tuple(f"{who}.{ext}" for who in ("daemon",) + CLIENTS for ext in ("pem", "key")) \
    + tuple(f"{who}.toml" for who in CLIENTS)


def make_test_ca(folder: str | Path, daemon_name: str = "vflpcd", hosts=DEFAULT_HOSTS, days: int = 30) -> Path:
    """Write the CA, the certificates and the identity files into ``folder`` (created); returns it.
    Bad arguments, files already there or a missing ``openssl`` raise ConfigError."""
    folder = Path(folder)
    if not _NAME.fullmatch(daemon_name):
        raise ConfigError("command line", "--daemon-name", f"expected 1 to 64 letters, digits, '.', '_' or '-' "
                                                           f"(starting with a letter or digit), got {daemon_name!r}")
    san = ", ".join(_san(h) for h in hosts)
    if not san:
        raise ConfigError("command line", "--host", "expected at least one host")
    if not isinstance(days, int) or not 1 <= days <= 3650:
        raise ConfigError("command line", "--days", f"expected 1 to 3650 days, got {days!r}")
    openssl = shutil.which("openssl")
    if openssl is None:
        raise ConfigError("command line", "make-test-ca", "needs the openssl command on the PATH")
    there = [name for name in OUTPUTS if (folder / name).exists()]
    if there:
        raise ConfigError(folder, there[0], "exists already: make-test-ca writes into a folder without its files")
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(folder, "<folder>", f"cannot create ({exc.strerror or exc})") from None
    curve = ["-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:prime256v1", "-nodes", "-sha256"]
    _openssl(openssl, "req", "-x509", *curve, "-keyout", folder / "ca.key", "-out", folder / "ca.pem",
             "-days", str(days), "-subj", f"/CN={CA_NAME}", "-addext", "basicConstraints=critical,CA:TRUE",
             "-addext", "keyUsage=critical,keyCertSign,cRLSign")
    with tempfile.TemporaryDirectory() as tmp:
        ext = Path(tmp) / "leaf.ext"
        ext.write_text(_LEAF_EXTENSIONS.format(san=san))
        for who, cn in (("daemon", daemon_name),) + tuple((c, c) for c in CLIENTS):
            csr = Path(tmp) / f"{who}.csr"
            _openssl(openssl, "req", "-new", *curve, "-keyout", folder / f"{who}.key", "-out", csr,
                     "-subj", f"/CN={cn}")
            _openssl(openssl, "x509", "-req", "-in", csr, "-CA", folder / "ca.pem", "-CAkey", folder / "ca.key",
                     "-set_serial", str(secrets.randbits(63)), "-days", str(days), "-sha256", "-extfile", ext,
                     "-out", folder / f"{who}.pem")
    for who in ("ca", "daemon") + CLIENTS:
        os.chmod(folder / f"{who}.key", 0o600)
    for who in CLIENTS:
        (folder / f"{who}.toml").write_text(
            f"# {who}'s identity for `vflpcd watch --identity` (a bench set-up only; docs/security.md)\n"
            f'ca = "ca.pem"\ncertificate = "{who}.pem"\nprivate_key = "{who}.key"\n'
            f'daemon = "{daemon_name}"        # telemetry is taken from this certificate common name only\n')
    return folder


def mission_snippet(folder: Path, daemon_name: str = "vflpcd", hosts: tuple[str, ...] = DEFAULT_HOSTS) -> str:
    """The mission tables and the watch command line that use the files of ``folder``, on the first
    address among the certificate's ``hosts`` (the first host when none is an address): a client
    checks the daemon's certificate against the host it connects to."""
    d = Path(folder).resolve()
    host = next((h for h in hosts if _is_address(h)), hosts[0])
    endpoint = f"tls/[{host}]:7447" if ":" in host else f"tls/{host}:7447"
    return (f'[telemetry]\nlisten = ["{endpoint}"]\n\n'
            f'[telemetry.tls]\nca = "{d / "ca.pem"}"\ncertificate = "{d / "daemon.pem"}"\n'
            f'private_key = "{d / "daemon.key"}"\nmutual = true\n\n'
            f'[telemetry.access]\ntelemetry = ["gcs"]\nperception = ["perception"]\n\n'
            f"vflpcd watch VEHICLE_ID --connect {endpoint} --identity {d / 'gcs.toml'}"
            f"   # the daemon's certificate: CN {daemon_name}")


def _is_address(host) -> bool:
    try:
        ipaddress.ip_address(host)
    except ValueError:
        return False
    return True


def _san(host: str) -> str:
    if _is_address(host):
        return f"IP:{ipaddress.ip_address(host)}"
    if not isinstance(host, str) or not _HOST.fullmatch(host):
        raise ConfigError("command line", "--host", f"expected a host name or an IP address, got {host!r}")
    return f"DNS:{host}"


def _openssl(openssl: str, *args) -> None:
    proc = subprocess.run([openssl, *map(str, args)], capture_output=True, text=True, timeout=60)
    if proc.returncode != 0:
        lines = [line for line in proc.stderr.splitlines() if line.strip()] or [f"exit code {proc.returncode}"]
        raise ConfigError("command line", "make-test-ca", f"openssl {args[0]} failed: {lines[-1][:200]}")
