"""The vehicle's CAN messages (``config/can/vehicle.dbc``) with their frame checks.

Both ends of the bus use this: the daemon's driver (``drivers/can_vehicle.py``) and the ECU
mock (``vflpcd sitl can-ecu``). ``encode`` fills the checksum of messages that carry one;
``decode`` rejects, with the reason, every frame a careful receiver would drop:

- ``unknown_id``: an id the database does not define (or an extended/remote/error frame);
- ``dlc``: a data length other than the message's;
- ``checksum``: ``Checksum`` differs from (sum of bytes 0..6 + id low byte) mod 256, inverted;
- ``range``: a signal outside its [minimum, maximum];
- ``counter``: the alive counter did not advance by one (``AliveCounter.accept``).

A rejected frame raises ``FrameError``; its ``kind`` is one of ``FRAME_ERRORS``, which the
receivers count.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import can
import cantools

from vflpcd.base.inputfile import read_text
from vflpcd.base.paths import config_dir

FRAME_ERRORS = ("unknown_id", "dlc", "checksum", "range", "counter")
COUNTER_MODULO = 16
MODES = {0: "manual", 1: "ready", 2: "automatic", 3: "braking", 4: "stopped"}
DBC_ENCODING = "cp1252"         # the DBC format's text encoding (cantools' and the CAN tools' default)
LINK_MESSAGES = ("VehicleCmd", "VehicleStatus", "InsPosition", "InsHeadingVelocity")   # the vehicle link's


def default_dbc() -> Path:
    return config_dir() / "can" / "vehicle.dbc"


class FrameError(ValueError):
    """A frame the receiver drops: ``kind`` (one of FRAME_ERRORS) and a detail for the log."""

    def __init__(self, kind: str, detail: str) -> None:
        super().__init__(f"{kind}: {detail}")
        self.kind = kind


def checksum(frame_id: int, data: bytes) -> int:
    """The DBC's checksum of a frame: (sum of bytes 0..6 + id low byte) mod 256, bitwise not."""
    return ~(sum(data[:7]) + (frame_id & 0xFF)) & 0xFF


@dataclass(frozen=True)
class Frame:
    """A decoded frame: message name, physical signal values, receive time (s, the bus's clock)."""

    name: str
    signals: dict
    timestamp: float


class VehicleCan:
    """The database and its codec. ``dbc``: the file (default ``config/can/vehicle.dbc``), read
    by ``vflpcd.base.inputfile`` (ConfigError on a file that cannot be read); cantools raises its
    own errors on one that does not parse."""

    def __init__(self, dbc: str | Path | None = None) -> None:
        path = Path(dbc) if dbc is not None else default_dbc()
        self.path = path
        self.db = cantools.database.load_string(read_text(path, encoding=DBC_ENCODING), database_format="dbc",
                                                strict=True)
        self._by_id = {m.frame_id: m for m in self.db.messages}

    def message(self, name: str):
        return self.db.get_message_by_name(name)

    def encode(self, name: str, signals: dict) -> can.Message:
        """A frame of message ``name`` from physical values (ValueError naming a value out of range);
        ``Checksum`` is computed here, any value given for it is replaced."""
        msg = self.message(name)
        values = dict(signals)
        has_checksum = "Checksum" in msg.signal_tree
        if has_checksum:
            values["Checksum"] = 0
        data = bytearray(msg.encode(values, strict=True))
        if has_checksum:
            data[7] = checksum(msg.frame_id, data)
        return can.Message(arbitration_id=msg.frame_id, data=bytes(data), is_extended_id=False)

    def decode(self, frame: can.Message) -> Frame:
        """The frame's message and values, or FrameError with the reason it must be dropped."""
        msg = self._by_id.get(frame.arbitration_id)
        if msg is None or frame.is_extended_id or frame.is_remote_frame or frame.is_error_frame:
            raise FrameError("unknown_id", f"id 0x{frame.arbitration_id:X}")
        data = bytes(frame.data)
        if len(data) != msg.length or frame.dlc != msg.length:
            raise FrameError("dlc", f"{msg.name} with {len(data)} bytes (expected {msg.length})")
        if "Checksum" in msg.signal_tree and data[7] != checksum(msg.frame_id, data):
            raise FrameError("checksum", f"{msg.name} checksum {data[7]} (expected {checksum(msg.frame_id, data)})")
        values = msg.decode(data, decode_choices=False, scaling=True)
        for s in msg.signals:
            v = values[s.name]
            if (s.minimum is not None and v < s.minimum - 1e-9) or (s.maximum is not None and v > s.maximum + 1e-9):
                raise FrameError("range", f"{msg.name}.{s.name} = {v} outside [{s.minimum}, {s.maximum}]")
        return Frame(msg.name, values, float(frame.timestamp))


class AliveCounter:
    """Receiver side of an alive counter: the first value is taken as it comes, after that each
    frame must carry the previous value + 1 (mod 16). A frame that breaks the sequence is dropped
    and the counter re-synchronises on it, as drive-by-wire ECUs do."""

    def __init__(self) -> None:
        self._last: int | None = None

    def accept(self, value: int) -> bool:
        value = int(value)
        ok = self._last is None or value == (self._last + 1) % COUNTER_MODULO
        self._last = value
        return ok

    def reset(self) -> None:
        self._last = None


class CounterSource:
    """Sender side: 0, 1, ..., 15, 0, ..."""

    def __init__(self) -> None:
        self._next = 0

    def take(self) -> int:
        value = self._next
        self._next = (self._next + 1) % COUNTER_MODULO
        return value
