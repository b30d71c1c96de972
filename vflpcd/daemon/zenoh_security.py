"""Zenoh link security: TLS settings, access control, and the identity file of a client.

``TlsConfig`` is the ``[telemetry.tls]`` table of a mission (or the keys of an identity file):
the CA that signs every certificate of the set-up, this end's certificate and private key (PEM
files; relative paths resolve against the file that names them) and ``mutual`` (the listening
side asks the connecting side for a certificate too: mutual TLS). ``zenoh_json`` is Zenoh's
``transport/link/tls`` section; the same certificate and key serve the listen and the connect
endpoints, ``tls/`` and ``quic/`` alike.

Access control is Zenoh's (``access_control``, default deny), keyed by certificate common names
(CN). ``AccessConfig`` (``[telemetry.access]``) is the daemon's: remote identities named in
``telemetry`` may subscribe within ``vflpc/<id>/`` and are sent the published topics; those named
in ``perception`` may put on the perception input and learn of its subscriber. No remote identity
may put on the published topics or anywhere else, so only the daemon publishes under its keys.
``TrustedDaemon`` is a client's (``vflpcd watch``, a perception publisher): only the named
identity may exchange puts and subscriptions with it, within ``vflpc/<id>/``. Both implement
``AccessPolicy``.

``IdentityFile`` reads a client's identity file (TOML): ``ca``, ``certificate``, ``private_key``
(``mutual`` as above, for a client that listens) and optionally ``daemon``, the daemon
certificate's CN that alone may serve it telemetry.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Mapping, Protocol

from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import read_bytes
from vflpcd.base.tomlread import Table, load_table

SECURE_PROTOCOLS = ("tls", "quic")
TLS_KEYS = frozenset({"ca", "certificate", "private_key", "mutual"})
MAX_NAME_CHARS = 64                     # the longest X.509 common name
_PEM = {"ca": "CERTIFICATE", "certificate": "CERTIFICATE", "private_key": "PRIVATE KEY"}


# --------------------------------------------------------------------------- TLS
@dataclass(frozen=True)
class TlsConfig:
    """ca: the CA certificate that every peer's certificate must chain to; certificate,
    private_key: this end's (PEM); mutual: a listening end asks connecting ends for a
    certificate signed by ``ca`` (mutual TLS; needed to tell identities apart)."""

    ca: Path
    certificate: Path
    private_key: Path
    mutual: bool = True

    @classmethod
    def from_table(cls, table: Table, known: frozenset[str] = frozenset()) -> TlsConfig:
        """Validate ``table`` (keys ``TLS_KEYS`` and ``known``): the three files must exist and be
        PEM; relative paths resolve against ``table.file``'s folder. ConfigError naming the field."""
        table.check_known(set(TLS_KEYS | known))
        base = Path(table.file).parent if table.file is not None else Path.cwd()
        files = {key: _pem_file(table, key, base) for key in ("ca", "certificate", "private_key")}
        return cls(mutual=table.boolean("mutual", True), **files)

    def zenoh_json(self) -> dict:
        """Zenoh's ``transport/link/tls`` section."""
        return {"root_ca_certificate": str(self.ca), "listen_certificate": str(self.certificate),
                "listen_private_key": str(self.private_key), "connect_certificate": str(self.certificate),
                "connect_private_key": str(self.private_key), "enable_mtls": self.mutual}


def _pem_file(table: Table, key: str, base: Path) -> Path:
    try:
        path = Path(table.string(key)).expanduser()
    except RuntimeError as exc:             # ~user of an unknown user
        raise table.error(key, str(exc)) from None
    path = path if path.is_absolute() else base / path
    try:
        head = read_bytes(path)
    except ConfigError as exc:
        raise table.error(key, f"{str(path)!r}: {exc.message}") from None
    label = _PEM[key]
    if not any(line.startswith(b"-----BEGIN ") and line.rstrip().endswith(f"{label}-----".encode())
               for line in head.splitlines()):
        raise table.error(key, f"{str(path)!r} is not a PEM file holding a {label.lower()} "
                               f"(no '-----BEGIN ...{label}-----' line)")
    return path.resolve()


def endpoint_problem(endpoints: Mapping[str, tuple[str, ...]], tls: TlsConfig | None) -> tuple[str, str] | None:
    """(name, reason) of the first endpoint list (name -> endpoints) that does not fit ``tls``:
    a ``tls/`` or ``quic/`` endpoint needs TLS settings; with them, every endpoint must be
    ``tls/`` or ``quic/``. None when all fit."""
    for name, eps in endpoints.items():
        for ep in eps:
            secure = ep.split("/", 1)[0] in SECURE_PROTOCOLS
            if secure and tls is None:
                return name, (f"endpoint {ep} needs TLS settings: a CA, a certificate and a private key")
            if not secure and tls is not None:
                return name, (f"endpoint {ep} would carry the link unencrypted: with TLS settings every "
                              f"endpoint must be {' or '.join(p + '/' for p in SECURE_PROTOCOLS)}")
    return None


# --------------------------------------------------------------------------- access control
class AccessPolicy(Protocol):
    def access_control(self, keys: Mapping[str, str], space: str) -> dict:
        """Zenoh's ``access_control`` section for the key expressions ``keys`` (topic -> key, from
        ``telemetry.key_expressions``) of the key space ``space`` (``vflpc/<id>/**``)."""


@dataclass(frozen=True)
class AccessConfig:
    """The daemon's ``[telemetry.access]``: telemetry, the common names that may read the
    telemetry; perception, those that may publish the perception input."""

    telemetry: tuple[str, ...] = ()
    perception: tuple[str, ...] = ()

    @classmethod
    def from_table(cls, table: Table) -> AccessConfig:
        table.check_known({"telemetry", "perception"})
        return cls(telemetry=_names(table, "telemetry"), perception=_names(table, "perception"))

    def access_control(self, keys: Mapping[str, str], space: str) -> dict:
        published = [key for topic, key in keys.items() if topic != "perception"]
        perception = [keys["perception"]]
        rules = [_rule("read-subscribe", ["declare_subscriber"], ["ingress"], [space]),
                 _rule("read-put", ["put"], ["egress"], published),
                 _rule("perception-put", ["put"], ["ingress"], perception),
                 _rule("perception-subscribe", ["declare_subscriber"], ["egress"], perception)]
        subjects, policies = [], []
        for sid, names, rule_ids in (("readers", self.telemetry, ["read-subscribe", "read-put"]),
                                     ("perception", self.perception, ["perception-put", "perception-subscribe"])):
            if names:                       # Zenoh refuses an empty list of names
                subjects.append({"id": sid, "cert_common_names": list(names)})
                policies.append({"id": sid, "rules": rule_ids, "subjects": [sid]})
        return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
                "policies": policies}


@dataclass(frozen=True)
class TrustedDaemon:
    """A client's policy: only the identity ``name`` (the daemon certificate's CN) may exchange
    puts and subscriptions with this session, and only within the vehicle's key space."""

    name: str

    def access_control(self, keys: Mapping[str, str], space: str) -> dict:
        return {"enabled": True, "default_permission": "deny",
                "rules": [_rule("daemon", ["put", "declare_subscriber"], ["ingress", "egress"], [space])],
                "subjects": [{"id": "daemon", "cert_common_names": [self.name]}],
                "policies": [{"id": "daemon", "rules": ["daemon"], "subjects": ["daemon"]}]}


def _rule(rid: str, messages: list[str], flows: list[str], key_exprs: list[str]) -> dict:
    return {"id": rid, "messages": messages, "flows": flows, "permission": "allow", "key_exprs": key_exprs}


def check_name(name: object) -> str | None:
    """None when ``name`` can be a certificate common name (1..64 printable characters), else the reason."""
    if not isinstance(name, str) or not name or len(name) > MAX_NAME_CHARS or not name.isprintable():
        return f"expected a certificate common name of 1 to {MAX_NAME_CHARS} printable characters, got {name!r}"
    return None


def _names(table: Table, key: str) -> tuple[str, ...]:
    if not table.has(key):
        return ()
    names = table.strings(key)
    for name in names:
        problem = check_name(name)
        if problem is not None:
            raise table.error(key, problem)
    return names


# --------------------------------------------------------------------------- a client's identity
@dataclass(frozen=True)
class IdentityFile:
    """A client's identity: its TLS settings and, optionally, the daemon's CN (``daemon``)."""

    tls: TlsConfig
    daemon: str | None = None

    @classmethod
    def load(cls, path: str | Path) -> IdentityFile:
        """Read an identity file; ConfigError naming the file and the field."""
        root = load_table(path)
        tls = TlsConfig.from_table(root, known=frozenset({"daemon"}))
        daemon = root.string("daemon") if root.has("daemon") else None
        problem = check_name(daemon) if daemon is not None else None
        if problem is not None:
            raise root.error("daemon", problem)
        return cls(tls, daemon)

    def policy(self) -> AccessPolicy | None:
        return TrustedDaemon(self.daemon) if self.daemon is not None else None

