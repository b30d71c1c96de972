"""The flight log: every tick and event of a run in one MCAP file, written off the control thread.

Layout: a chunked MCAP file (profile "", no compression, message indexes). The writer thread
closes a chunk every ``flush_period_s`` and commits it through ``vflpcd.log.mcapfile.McapFile``:
after each commit the file is a complete MCAP file, closed by a footer, synced to disk, that
every MCAP reader reads (the ``mcap`` package's seeking and stream readers, Foxglove). A process
killed with SIGKILL, or a power cut, loses only what came after the last commit: at most
``flush_period_s`` plus one write pass. ``close()`` writes the summary (chunk indexes,
statistics) and the final footer; a log without them stopped early (``FlightLog.truncated``).

Channels (message encoding "json", schema encoding "jsonschema"): ``/header`` (one
``MissionHeader``, log time = the open time), ``/tick`` (``TickRecord``), ``/event``
(``Event``); log_time = publish_time = the record's ``stamp_ns`` (``time.monotonic_ns()``).

The caller never waits on the disk: ``record_tick``/``record_event`` append to a queue and
return; the thread "flight-recorder" encodes and writes. A write error (a full disk) is logged
once at ERROR and the recorder stops writing; it never raises into the caller. It keeps the
reason (``stop_reason``, e.g. "disk full (ENOSPC)") and tries to close the log with a
``log_stopped`` event that names it (which fits when the file's last disk block has room).
"""

from __future__ import annotations

import errno
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

from mcap.writer import CompressionType, Writer

from vflpcd.log.mcapfile import McapFile
from vflpcd.log.records import Event, MissionHeader, TickRecord, json_bytes
from vflpcd.base.errors import ConfigError

log = logging.getLogger("vflpcd.log.writer")

TOPIC_HEADER = "/header"
TOPIC_TICK = "/tick"
TOPIC_EVENT = "/event"

CHUNK_SIZE = 4 << 20     # bytes; a chunk is closed at each commit, or when it grows past this

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

    The file is created (and ``header`` committed) at construction; an unusable path raises
    ``ConfigError(path, "log.dir", ...)``. ``record_tick``/``record_event`` only enqueue (a few
    microseconds) and never raise. ``written``: records (ticks and events) committed to the file;
    ``dropped``: records refused after ``close()`` or lost to a write error; ``failed``: a write
    error stopped the recorder; ``stop_reason``: why the log ended before ``close()`` finished it
    (None while it has not).
    """

    def __init__(self, path: str | Path, header: MissionHeader, flush_period_s: float = 0.5) -> None:
        self.path = Path(path)
        self.flush_period_s = float(flush_period_s)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = McapFile(self.path)
        except OSError as exc:
            raise ConfigError(self.path, "log.dir", f"cannot open the flight log for writing "
                                                    f"({exc.strerror or exc})") from exc
        self._queue: queue.SimpleQueue = queue.SimpleQueue()
        self._accepting = True
        self._failed = False
        self._closed = False
        self._stop_reason: str | None = None
        self._close_lock = threading.Lock()
        self._refused_lock = threading.Lock()
        self._refused = 0
        self._lost = 0
        self._written = 0
        self._uncommitted = 0
        self._last_clock: tuple[float, int] | None = None    # (t, stamp_ns) of the last tick added
        self._bad_record_logged = False
        try:
            self._writer = Writer(self._file, chunk_size=CHUNK_SIZE, compression=CompressionType.NONE)
            self._writer.start(profile="", library="vflpcd")
            self._channels = {}
            for topic, cls in ((TOPIC_HEADER, MissionHeader), (TOPIC_TICK, TickRecord), (TOPIC_EVENT, Event)):
                schema_id = self._writer.register_schema(
                    cls.__name__, "jsonschema", json.dumps(json_schema(cls)).encode())
                self._channels[cls] = self._writer.register_channel(topic, "json", schema_id)
            now = time.monotonic_ns()
            self._writer.add_message(self._channels[MissionHeader], now, _encode(header), now)
            self._writer.flush()
            self._file.commit()
        except OSError as exc:
            self._file.close()
            raise ConfigError(self.path, "log.dir", f"cannot write the flight log ({exc.strerror or exc})") from exc
        log.info("event=flight_log path=%s crash_safe=\"readable by every MCAP reader up to its last commit, "
                 "every %.2f s, synced to disk\"", self.path, self.flush_period_s)
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

    @property
    def stop_reason(self) -> str | None:
        return self._stop_reason

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
            self._stop_reason = self._stop_reason or f"the recorder did not finish within {timeout_s:g} s"
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
            self._stop_reason = self._stop_reason or "the recorder crashed"
            log.exception("event=flight_log_writer_crashed path=%s written=%d later=dropped", self.path, self._written)
            self._file.close()

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
                self._commit()
        self._commit(final=True)
        self._file.close()

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
        self._writer.add_message(self._channels[type(rec)], rec.stamp_ns, data, rec.stamp_ns)
        self._uncommitted += 1
        if isinstance(rec, TickRecord):
            self._last_clock = (rec.t, rec.stamp_ns)

    def _commit(self, final: bool = False) -> None:
        """Close the chunk in progress and commit it (final: with the summary and footer)."""
        if self._failed:
            return
        try:
            if final:
                self._writer.finish()
            else:
                self._writer.flush()
            self._file.commit(final=final)
        except OSError as exc:
            self._lost += self._uncommitted
            self._uncommitted = 0
            self._stop(exc)
            return
        self._written += self._uncommitted
        self._uncommitted = 0

    def _stop(self, exc: OSError) -> None:
        """After a write error: stop writing, keep the reason, and try to end the log with it."""
        self._failed = True
        self._accepting = False
        self._stop_reason = write_error_reason(exc)
        now = time.monotonic_ns()
        t = self._last_clock[0] + (now - self._last_clock[1]) * 1e-9 if self._last_clock else 0.0
        ev = Event(t=t, stamp_ns=now, kind="log_stopped", detail={"reason": self._stop_reason, "errno": _errno_name(exc)})
        try:
            self._writer.add_message(self._channels[Event], now, _encode(ev), now)
            self._writer.flush()
            self._file.commit()
            recorded = "yes"
        except OSError:
            recorded = "no"
        log.error("event=flight_log_write_failed path=%s reason=%s error=%r written=%d stop_recorded=%s "
                  "later=dropped", self.path, self._stop_reason, exc, self._written, recorded)

    def _discard_queue(self) -> int:
        n = 0
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return n
            if item is not _STOP:
                n += 1


def write_error_reason(exc: OSError) -> str:
    """Why a write failed, in words: "disk full (ENOSPC)", "disk quota exceeded (EDQUOT)" or
    "write error (EIO: Input/output error)"."""
    code = _errno_name(exc)
    if exc.errno == errno.ENOSPC:
        return "disk full (ENOSPC)"
    if exc.errno == errno.EDQUOT:
        return "disk quota exceeded (EDQUOT)"
    return f"write error ({code or 'errno ' + str(exc.errno)}: {exc.strerror or exc})"


def _encode(rec: Any) -> bytes:
    return json_bytes(rec.to_json())


def _errno_name(exc: OSError) -> str:
    """The error's symbolic name ("ENOSPC"), "" when it has none."""
    return errno.errorcode.get(exc.errno or 0, "")
