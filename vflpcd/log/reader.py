"""Reading a flight log (the MCAP file of ``vflpcd.log.writer``) into numpy arrays.

A log that stopped early (the daemon was killed, or a write error stopped the recorder) ends in
a footer without a summary (``vflpcd.log.mcapfile``), or, written another way, without any footer
and possibly inside a record; ``read_flight_log`` reads it record by record, keeps every complete
message and reports ``truncated=True``.
"""

from __future__ import annotations

import json
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np
from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, Footer, Message
from mcap.stream_reader import StreamReader

from vflpcd.log.records import Event, MissionHeader
from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import DATA_MAX_BYTES, FILE_FIELD, open_binary

MAGIC_SIZE = 8


@dataclass
class FlightLog:
    """A flight log as arrays over its M ticks (file order, i.e. tick order).

    header: the mission header; events: every event, in order. Per tick: k, t (s) (M,);
    stamp_ns (M,) int64; mode (M,) str; state (M, n_x) in ``header.state_names`` order, NaN rows
    where the tick had no state; state_age_s (M,); reference (M, d), NaN rows without a plan;
    command (M, n_u) in ``header.control_names`` order, NaN rows where none was sent;
    lateness_s, compute_s (M,) s; overrun (M,) bool; plan_version, model_version (M,) int;
    threats: M tuples of obstacle ids. obstacles: id -> (M, d) centres, NaN rows where that
    obstacle was absent from the tick; obstacle_radius: id -> radius (m) as last recorded.
    truncated: the log stopped before the recorder finished it (no summary and final footer);
    stop_reason: why, when the recorder could say so (its ``log_stopped`` event, e.g. "disk full
    (ENOSPC)"), else None (the writer was killed or the process died).
    """

    path: Path
    header: MissionHeader
    events: list[Event]
    k: np.ndarray
    t: np.ndarray
    stamp_ns: np.ndarray
    mode: np.ndarray
    state: np.ndarray
    state_age_s: np.ndarray
    reference: np.ndarray
    command: np.ndarray
    lateness_s: np.ndarray
    compute_s: np.ndarray
    overrun: np.ndarray
    plan_version: np.ndarray
    model_version: np.ndarray
    threats: list[tuple[str, ...]]
    obstacles: dict[str, np.ndarray] = field(default_factory=dict)
    obstacle_radius: dict[str, float] = field(default_factory=dict)
    truncated: bool = False

    @property
    def stop_reason(self) -> str | None:
        return next((str(e.detail.get("reason", "")) for e in self.events if e.kind == "log_stopped"), None)

    @property
    def logged_s(self) -> float:
        """Mission time of the last tick in the log (s), 0 without ticks."""
        return float(self.t[-1]) if len(self) else 0.0

    def __len__(self) -> int:
        return len(self.k)


class _WholeReads:
    """A binary file whose ``read(n)`` returns n bytes or raises ``EndOfFile``: a record cut by
    the end of the file is never handed on half-read."""

    def __init__(self, f: BinaryIO) -> None:
        self._f = f
        self.count = 0

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        self.count += len(data)
        if n > 0 and len(data) < n:
            raise EndOfFile()
        return data


def read_flight_log(path: str | Path) -> FlightLog:
    """Read the flight log at ``path``; raises ``ConfigError(path, "<file>", ...)`` for a missing
    file, a file that is not MCAP, or one without a ``/header`` message."""
    path = Path(path)
    topics: dict[int, str] = {}
    header: dict | None = None
    ticks: list[dict] = []
    events: list[Event] = []
    truncated = True
    f = open_binary(path, DATA_MAX_BYTES)     # a regular file (a FIFO or a device never blocks the reader)
    with f:
        stream = _WholeReads(f)
        reader = StreamReader(stream, record_size_limit=1 << 30)
        try:
            for record in reader.records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message):
                    topic = topics.get(record.channel_id)
                    if topic == "/tick":
                        ticks.append(_decode(path, record))
                    elif topic == "/event":
                        ev = _decode(path, record)
                        events.append(Event(t=ev["t"], stamp_ns=ev["stamp_ns"], kind=ev["kind"],
                                            detail=_tuples(ev.get("detail", {}))))
                    elif topic == "/header" and header is None:
                        header = _decode(path, record)
                elif isinstance(record, Footer):
                    truncated = record.summary_start == 0     # a commit's trailer, not the final footer
        except InvalidMagic as exc:
            raise ConfigError(path, FILE_FIELD, "not an MCAP file (bad magic bytes)") from exc
        except (EndOfFile, struct.error):
            if stream.count < MAGIC_SIZE:
                raise ConfigError(path, FILE_FIELD, f"not an MCAP file ({stream.count} bytes)") from None
            # cut short: keep every complete message before the cut
        except McapError as exc:
            raise ConfigError(path, FILE_FIELD, f"unreadable MCAP data ({exc})") from exc
    if header is None:
        raise ConfigError(path, FILE_FIELD, "no /header message: not a vflpcd flight log")
    return _assemble(path, _header(path, header), events, ticks, truncated)


def _decode(path: Path, message: Message) -> dict[str, Any]:
    try:
        return json.loads(message.data)
    except ValueError as exc:
        raise ConfigError(path, FILE_FIELD, f"message at log time {message.log_time} is not JSON ({exc})") from exc


def _tuples(value: Any) -> Any:
    """JSON lists back to tuples, recursively (the records hold tuples)."""
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    if isinstance(value, dict):
        return {k: _tuples(v) for k, v in value.items()}
    return value


def _header(path: Path, obj: dict) -> MissionHeader:
    try:
        return MissionHeader(**{k: _tuples(v) for k, v in obj.items()})
    except TypeError as exc:
        raise ConfigError(path, "/header", f"not a mission header ({exc})") from exc


def _rows(path: Path, name: str, values: list[list[float]], width: int) -> np.ndarray:
    """(M, width) float array; empty entries become NaN rows."""
    out = np.full((len(values), width), np.nan)
    for i, row in enumerate(values):
        if len(row) == 0:
            continue
        if len(row) != width:
            raise ConfigError(path, f"/tick.{name}", f"tick {i} has {len(row)} values, expected {width}")
        out[i] = row
    return out


def _width(names: tuple[str, ...], values: list[list[float]]) -> int:
    return len(names) if names else max((len(v) for v in values), default=0)


def _assemble(path: Path, header: MissionHeader, events: list[Event], ticks: list[dict],
              truncated: bool) -> FlightLog:
    def col(key: str, dtype=float, default: Any = 0) -> np.ndarray:
        return np.array([tk.get(key, default) for tk in ticks], dtype=dtype)

    states = [tk["state"] for tk in ticks]
    commands = [tk["command"] for tk in ticks]
    d = header.dim
    obstacles: dict[str, np.ndarray] = {}
    radius: dict[str, float] = {}
    for i, tk in enumerate(ticks):
        for o in tk.get("obstacles", ()):
            centres = obstacles.setdefault(o["id"], np.full((len(ticks), d), np.nan))
            centres[i] = o["center"][:d]
            radius[o["id"]] = float(o["radius"])
    return FlightLog(
        path=path, header=header, events=events,
        k=col("k", np.int64), t=col("t"), stamp_ns=col("stamp_ns", np.int64),
        mode=np.array([tk["mode"] for tk in ticks], dtype=str),
        state=_rows(path, "state", states, _width(header.state_names, states)),
        state_age_s=col("state_age_s"),
        reference=_rows(path, "reference", [tk["reference"] for tk in ticks], d),
        command=_rows(path, "command", commands, _width(header.control_names, commands)),
        lateness_s=col("lateness_s"), compute_s=col("compute_s"), overrun=col("overrun", bool, False),
        plan_version=col("plan_version", np.int64), model_version=col("model_version", np.int64),
        threats=[tuple(tk.get("threats", ())) for tk in ticks],
        obstacles=obstacles, obstacle_radius=radius, truncated=truncated,
    )
