"""Helpers shared by the tests that talk over loopback (on the test path via pyproject's
``pythonpath``)."""

from __future__ import annotations

import json
import socket
import time


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def free_udp_port() -> int:
    """A UDP port on 127.0.0.1 that nothing is bound to now (e.g. for MAVSDK to listen on)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_for(pred, timeout: float = 3.0) -> bool:
    """Poll ``pred`` every 5 ms until it is true or ``timeout`` s have passed; its last value."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if pred():
            return True
        time.sleep(0.005)
    return pred()


def zenoh_peer(port: int, identity=None, vehicle_id: str = "t1"):
    """A Zenoh peer session that connects to 127.0.0.1:``port`` (multicast scouting off): over TCP,
    or with ``identity`` (an identity file, ``vflpcd.daemon.zenoh_security.IdentityFile``) over TLS,
    taking ``vehicle_id``'s key space from the identity's daemon only when the file names one."""
    import zenoh

    if identity is not None:
        from vflpcd.daemon.telemetry import TelemetryConfig, open_session
        from vflpcd.daemon.zenoh_security import IdentityFile

        ident = IdentityFile.load(identity)
        return open_session(TelemetryConfig(connect=(f"tls/127.0.0.1:{port}",), tls=ident.tls, access=ident.policy()),
                            vehicle_id=vehicle_id)
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)
