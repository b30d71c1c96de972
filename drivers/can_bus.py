"""Which CAN bus to open, from a mission's ``[platform]`` table or the ECU mock's options.

``interface`` and ``channel`` are python-can's:

- ``socketcan`` on ``vcan0`` (or ``can0`` on the vehicle): the kernel's SocketCAN, for the
  bench and hardware in the loop (``systemd/README.md`` brings vcan0 up);
- ``remote`` on ``ws://127.0.0.1:PORT/``: python-can-remote's WebSocket hub
  (``python -m can_remote -H 127.0.0.1 --interface virtual --channel vcan0 --port PORT``), for
  processes on a host whose kernel has no SocketCAN;
- ``virtual`` on any name: python-can's bus inside one process (tests).
"""

from __future__ import annotations

import socket
from dataclasses import dataclass

import can

INTERFACES = ("socketcan", "remote", "virtual")


def af_can_available() -> bool:
    """Whether this kernel offers SocketCAN (AF_CAN raw sockets)."""
    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return False
    try:
        socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError:
        return False
    return True


@dataclass(frozen=True)
class BusConfig:
    interface: str = "socketcan"
    channel: str = "vcan0"

    def __post_init__(self) -> None:
        if self.interface not in INTERFACES:
            raise ValueError(f"interface must be one of {', '.join(INTERFACES)}, got {self.interface!r}")
        if not isinstance(self.channel, str) or not self.channel:
            raise ValueError(f"channel must be a non-empty string, got {self.channel!r}")
        if self.interface == "remote" and not self.channel.startswith(("ws://", "wss://")):
            raise ValueError(f"a remote bus's channel is the hub's URL ws://HOST:PORT/, got {self.channel!r}")

    def describe(self) -> str:
        return f"{self.interface}:{self.channel}"


def open_bus(cfg: BusConfig) -> can.BusABC:
    """The bus (OSError naming the bus when it cannot be opened, e.g. no SocketCAN or no hub)."""
    if cfg.interface == "socketcan" and not af_can_available():
        raise OSError(f"cannot open {cfg.describe()}: this kernel has no SocketCAN (AF_CAN); "
                      "use interface = \"remote\" with a python-can-remote hub")
    try:
        if cfg.interface == "virtual":
            return can.Bus(interface="virtual", channel=cfg.channel, receive_own_messages=False)
        return can.Bus(interface=cfg.interface, channel=cfg.channel)
    except Exception as exc:                # python-can and the remote hub raise their own types
        raise OSError(f"cannot open {cfg.describe()}: {type(exc).__name__}: {exc}") from None


def bus_config(t) -> BusConfig:
    """The bus named by a ``[platform]`` table (``vflpcd.base.tomlread.Table``): ``interface`` and ``channel``
    (ConfigError naming the field)."""
    interface = t.string("interface", "socketcan", choices=INTERFACES)
    channel = t.string("channel", "vcan0")
    try:
        return BusConfig(interface, channel)
    except ValueError as exc:
        raise t.error("channel", str(exc)) from None
