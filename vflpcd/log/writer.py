"""The flight log: every tick and event of a run in one MCAP file, written off the control thread.

Layout: an unchunked MCAP file (profile "", no compression). Each record is one MCAP message
record written straight after the previous one, so the file is at every moment a valid MCAP
prefix; the writer thread flushes the file object every ``flush_period_s``, handing the bytes
to the kernel. A process killed with SIGKILL therefore loses only what was still in the queue
or in the user-space buffer: at most ``flush_period_s`` plus one write pass. (``os.fsync`` is
not called: the kernel keeps what it was given when the process dies; only a power cut loses
more.) ``vflpcd.log.reader.read_flight_log`` reads such a truncated file up to its last complete
message. ``close()`` writes the summary and footer.

Channels (message encoding "json", schema encoding "jsonschema"): ``/header`` (one
``MissionHeader``, log time = the open time), ``/tick`` (``TickRecord``), ``/event``
(``Event``); log_time = publish_time = the record's ``stamp_ns`` (``time.monotonic_ns()``).

The caller never waits on the disk: ``record_tick``/``record_event`` append to a queue and
return; the thread "flight-recorder" encodes and writes. A write error is logged once at ERROR
and the recorder stops writing; it never raises into the caller.
"""

from __future__ import annotations

import json
import logging
import queue
import threading
import time
import typing
from dataclasses import fields, is_dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from mcap.writer import CompressionType, IndexType, Writer

from vflpcd.log.records import Event, MissionHeader, TickRecord, json_bytes
from vflpcd.base.errors import ConfigError

log = logging.getLogger("vflpcd.log.writer")

TOPIC_HEADER = "/header"
TOPIC_TICK = "/tick"
TOPIC_EVENT = "/event"

_STOP = object()


def log_path(directory: str | Path, vehicle_id: str, now: datetime | None = None) -> Path:
    """``DIR/VEHICLE-YYYYmmdd-HHMMSS.mcap`` (local time ``now``, default: the current time);
    creates DIR. Raises ``ConfigError(DIR, "log.dir", ...)`` when DIR cannot be created."""
    directory = Path(directory)
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise ConfigError(directory, "log.dir", f"cannot create the log directory ({exc.strerror or exc})") from exc
    now = now or datetime.now()
    return directory / f"{vehicle_id}-{now:%Y%m%d-%H%M%S}.mcap"


def json_schema(cls: type) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a record dataclass's ``to_json()`` object."""
    schema = _object_schema(cls)
    schema["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    schema["title"] = cls.__name__
    return schema


def _object_schema(cls: type) -> dict[str, Any]:
    hints = typing.get_type_hints(cls)
    props = {f.name: _type_schema(hints[f.name]) for f in fields(cls)}
    return {"type": "object", "properties": props, "required": [f.name for f in fields(cls)]}


def _type_schema(tp: Any) -> dict[str, Any]:
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if tp is bool:
        return {"type": "boolean"}
    if tp is int:
        return {"type": "integer"}
    if tp is float:
        return {"type": "number"}
    if tp is str:
        return {"type": "string"}
    if tp is dict or origin is dict:
        return {"type": "object"}
    if origin is tuple:
        items = args[0] if args else Any
        return {"type": "array", "items": _type_schema(items)}
    if is_dataclass(tp):
        return _object_schema(tp)
    return {}


class FlightRecorder:
    """Writes ``TickRecord``s and ``Event``s to the MCAP file ``path`` from its own thread.

    The file is created (and ``header`` written) at construction; an unusable path raises
    ``ConfigError(path, "log.dir", ...)``. ``record_tick``/``record_event`` only enqueue (a few
    microseconds) and never raise. ``written``: records (ticks and events) written; ``dropped``:
    records refused after ``close()`` or lost after a write error; ``failed``: a write error
    stopped the recorder.
    """

    def __init__(self, path: str | Path, header: MissionHeader, flush_period_s: float = 0.5) -> None:
        self.path = Path(path)
        self.flush_period_s = float(flush_period_s)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise ConfigError(self.path, "log.dir", f"cannot open the flight log for writing "
                                                    f"({exc.strerror or exc})") from exc
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._accepting = True
        self._failed = False
        self._closed = False
        self._close_lock = threading.Lock()
        self._refused_lock = threading.Lock()
        self._refused = 0
        self._lost = 0
        self._written = 0
        self._bad_record_logged = False
        try:
            self._writer = Writer(self._file, use_chunking=False, compression=CompressionType.NONE,
                                  index_types=IndexType.NONE)
            self._writer.start(profile="", library="vflpcd")
            self._channels = {}
            for topic, cls in ((TOPIC_HEADER, MissionHeader), (TOPIC_TICK, TickRecord), (TOPIC_EVENT, Event)):
                schema_id = self._writer.register_schema(
                    cls.__name__, "jsonschema", json.dumps(json_schema(cls)).encode())
                self._channels[cls] = self._writer.register_channel(topic, "json", schema_id)
            now = time.monotonic_ns()
            self._writer.add_message(self._channels[MissionHeader], now, _encode(header), now)
            self._file.flush()
        except OSError as exc:
            self._file.close()
            raise ConfigError(self.path, "log.dir", f"cannot write the flight log ({exc.strerror or exc})") from exc
        self._thread = threading.Thread(target=self._run, name="flight-recorder", daemon=False)
        self._thread.start()

    # -- caller side -------------------------------------------------------------------------

    def record_tick(self, rec: TickRecord) -> None:
        """Queue one tick for writing; returns at once."""
        if self._accepting:
            self._queue.put(rec)
        else:
            self._refuse()

    def record_event(self, ev: Event) -> None:
        """Queue one event for writing; returns at once."""
        if self._accepting:
            self._queue.put(ev)
        else:
            self._refuse()

    def _refuse(self) -> None:
        with self._refused_lock:
            self._refused += 1

    @property
    def written(self) -> int:
        return self._written

    @property
    def dropped(self) -> int:
        return self._refused + self._lost

    @property
    def failed(self) -> bool:
        return self._failed

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, timeout_s: float = 1.0) -> None:
        """Stop accepting records, write what is queued, the summary and footer, close the file and
        join the thread (at most ``timeout_s``). Idempotent; never raises."""
        with self._close_lock:
            if self._closed:
                return
            self._closed = True
            self._accepting = False
            self._queue.put(_STOP)
        self._thread.join(timeout_s)
        if self._thread.is_alive():
            log.warning("event=flight_log_close_timeout path=%s timeout_s=%.2f queued=%d",
                        self.path, timeout_s, self._queue.qsize())
            return
        self._lost += self._discard_queue()  # put between the check in record_* and close()

    def __enter__(self) -> FlightRecorder:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- writer thread -----------------------------------------------------------------------

    def _run(self) -> None:
        try:
            self._loop()
        except Exception:  # a bug here must not leave the queue growing behind a dead thread
            self._failed = self._closed = True
            self._accepting = False
            log.exception("event=flight_log_writer_crashed path=%s written=%d later=dropped", self.path, self._written)
            try:
                self._file.close()
            except (OSError, ValueError):
                pass

    def _loop(self) -> None:
        next_flush = time.monotonic() + self.flush_period_s
        while True:
            try:
                item = self._queue.get(timeout=max(0.0, next_flush - time.monotonic()))
            except queue.Empty:
                item = None
            if item is _STOP:
                break
            if item is None and not threading.main_thread().is_alive():
                self._accepting = False  # the program ended without close(): finish the file
                self._closed = True
                break
            if item is not None:
                self._write(item)
            if time.monotonic() >= next_flush:
                next_flush = time.monotonic() + self.flush_period_s
                self._guard(self._file.flush)
        self._guard(self._finish)
        try:
            self._file.close()
        except OSError:
            pass

    def _write(self, rec: TickRecord | Event) -> None:
        if self._failed:
            self._lost += 1
            return
        try:
            if not (isinstance(rec.stamp_ns, int) and 0 <= rec.stamp_ns < 1 << 64):
                raise ValueError(f"stamp_ns {rec.stamp_ns!r} is not a uint64 time")
            data = _encode(rec)
        except (TypeError, ValueError) as exc:  # a record the log cannot hold: skip it only
            self._lost += 1
            if not self._bad_record_logged:
                self._bad_record_logged = True
                log.error("event=flight_log_bad_record type=%s error=%r later_bad_records=unlogged",
                          type(rec).__name__, exc)
            return
        if self._guard(self._writer.add_message, self._channels[type(rec)], rec.stamp_ns, data, rec.stamp_ns):
            self._written += 1
        else:
            self._lost += 1

    def _finish(self) -> None:
        self._writer.finish()
        self._file.flush()

    def _guard(self, fn, *args) -> bool:
        if self._failed:
            return False
        try:
            fn(*args)
            return True
        except (OSError, ValueError) as exc:
            self._failed = True
            self._accepting = False
            log.error("event=flight_log_write_failed path=%s error=%r written=%d later=dropped",
                      self.path, exc, self._written)
            return False

    def _discard_queue(self) -> int:
        n = 0
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return n
            if item is not _STOP:
                n += 1


def _encode(rec: Any) -> bytes:
    return json_bytes(rec.to_json())
