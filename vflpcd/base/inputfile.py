"""Reading the files a user hands the daemon: only regular files, only up to a size limit.

Every reader of a mission, scenario, plant or vehicle file, controller or planner configuration,
waypoint CSV, model archive, training or flight log, CAN database, CAN key or TLS certificate
opens it here. A file is looked at (``stat``) before it is opened, opened without blocking (a FIFO
never waits for a writer) and looked at again (``fstat``) on the descriptor that is then read, and
at most ``limit + 1`` bytes are read: a device, a FIFO, a directory or an endless stream is refused
without reading it. Text must decode strictly; TOML and JSON may nest arrays and tables at most
``MAX_DEPTH`` deep. Every failure is one :class:`ConfigError` naming the file and what is wrong
with it.

Limits (bytes):

- ``TEXT_MAX_BYTES`` (2 MiB): TOML, JSON, CSV, DBC, key and certificate text. The shipped files
  are at most a few kB; 2 MiB holds a waypoint CSV of about 100,000 points.
- ``MODEL_MAX_BYTES`` (64 MiB), the archive on disk and its arrays unpacked: a model archive.
  The shipped ones are about 30 kB; 64 MiB is eight million float64 weights, and the unpacked
  limit bounds the memory a compressed archive can claim.
- ``DATA_MAX_BYTES`` (1 GiB), on disk and unpacked: a training log, and a flight log (about six
  hours of a 100 Hz mission).
- ``MAX_DEPTH`` (32): arrays and tables nested in TOML and JSON. The shipped TOML files nest 2
  deep, a model archive's metadata 5; Python's parsers recurse on nesting and, at the default
  recursion limit, fail a few hundred levels deep (tomllib) with a RecursionError.
"""

from __future__ import annotations

import json
import os
import re
import stat
from contextlib import contextmanager
from pathlib import Path
from typing import Any, BinaryIO, Iterator

import numpy as np

from vflpcd.base.errors import ConfigError

TEXT_MAX_BYTES = 2 * 2**20
MODEL_MAX_BYTES = 64 * 2**20
DATA_MAX_BYTES = 2**30
MAX_DEPTH = 32

FILE_FIELD = "<file>"
SYNTAX_FIELD = "<syntax>"

_KINDS = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a character device"),
          (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
_OPEN_FLAGS = os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY | os.O_CLOEXEC


def _reason(exc: Exception) -> str:
    return exc.strerror if isinstance(exc, OSError) and exc.strerror else str(exc)


def _check(path: Path, st: os.stat_result, limit: int) -> None:
    if not stat.S_ISREG(st.st_mode):
        kind = next((name for test, name in _KINDS if test(st.st_mode)), "a special file")
        raise ConfigError(path, FILE_FIELD, f"not a regular file ({kind})")
    if st.st_size > limit:
        raise ConfigError(path, FILE_FIELD, f"too large ({st.st_size} bytes, the limit is {limit})")


def _system(path: Path, call, *args):
    """``call(path, *args)``, its OSError a ConfigError."""
    try:
        return call(path, *args)
    except FileNotFoundError:
        raise ConfigError(path, FILE_FIELD, "file not found") from None
    except (OSError, ValueError) as exc:            # permissions, loops, names too long, NUL bytes
        raise ConfigError(path, FILE_FIELD, f"cannot read ({_reason(exc)})") from None


def open_binary(path: str | Path, limit: int) -> BinaryIO:
    """``path`` opened for reading once it is known to be a regular file of at most ``limit``
    bytes (checked before opening and again on the open descriptor). The caller closes it."""
    path = Path(path)
    _check(path, _system(path, os.stat), limit)     # a device is refused without opening it
    fd = _system(path, os.open, _OPEN_FLAGS)
    try:
        _check(path, os.fstat(fd), limit)           # the file that was opened, not the one looked at
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_bytes(path: str | Path, limit: int = TEXT_MAX_BYTES) -> bytes:
    """The whole file (``open_binary``); never more than ``limit + 1`` bytes are read."""
    with open_binary(path, limit) as fh:
        try:
            data = fh.read(limit + 1)
        except OSError as exc:
            raise ConfigError(path, FILE_FIELD, f"cannot read ({_reason(exc)})") from None
    if len(data) > limit:                           # it grew, or its size was not its length (/proc)
        raise ConfigError(path, FILE_FIELD, f"too large (more than {limit} bytes)")
    return data


def read_text(path: str | Path, limit: int = TEXT_MAX_BYTES, encoding: str = "utf-8") -> str:
    """The file as text (``read_bytes``), strictly decoded."""
    data = read_bytes(path, limit)
    try:
        return data.decode(encoding)
    except UnicodeDecodeError as exc:
        raise ConfigError(path, SYNTAX_FIELD, f"not {encoding.upper()} text ({exc.reason} at byte {exc.start})") from None


# Strings and comments of TOML (a superset of JSON's), whose brackets do not nest.
_SPECIAL = re.compile(r"[\[\]{}\"'#]")
_STRING_END = {'"""': re.compile(r'(?:[^"\\]++|\\.|"(?!""))*+""""{0,2}+', re.S),
               "'''": re.compile(r"(?:[^']++|'(?!''))*+''''{0,2}+"),
               '"': re.compile(r'(?:[^"\\\n]++|\\.)*+"'), "'": re.compile(r"[^'\n]*+'")}


def check_depth(text: str, file: str | Path | None, field: str = SYNTAX_FIELD, limit: int = MAX_DEPTH) -> None:
    """Refuse TOML or JSON text whose arrays and tables nest deeper than ``limit``, before a
    recursive parser sees it. A linear scan of the brackets outside strings and comments."""
    if text.count("[") + text.count("{") <= limit:
        return
    depth, pos = 0, 0
    while (m := _SPECIAL.search(text, pos)) is not None:
        c, pos = m.group(), m.end()
        if c in "[{":
            depth += 1
            if depth > limit:
                line = text.count("\n", 0, pos) + 1
                raise ConfigError(file, field, f"nested deeper than {limit} arrays or tables (line {line})")
        elif c in "]}":
            depth = max(depth - 1, 0)
        elif c == "#":
            end = text.find("\n", pos)
            pos = len(text) if end < 0 else end
        else:
            quote = text[m.start():m.start() + 3] if text.startswith(c * 3, m.start()) else c
            pos = m.start() + len(quote)
            end = _STRING_END[quote].match(text, pos)
            if end is None:                         # unterminated: the parser reports it
                return
            pos = end.end()


def parse_json(text: str, file: str | Path | None, field: str = SYNTAX_FIELD) -> Any:
    """JSON text (``check_depth`` first); its errors a ConfigError naming ``field``."""
    check_depth(text, file, field)
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise ConfigError(file, field, f"not valid JSON ({exc.msg} at line {exc.lineno})") from None
    except RecursionError:
        raise ConfigError(file, field, "nested too deeply") from None


@contextmanager
def open_npz(path: str | Path, limit: int = MODEL_MAX_BYTES) -> Iterator[np.lib.npyio.NpzFile]:
    """A NumPy ``.npz`` archive without pickles (``open_binary``), at most ``limit`` bytes on disk
    and at most ``limit`` bytes unpacked, as a context manager."""
    path = Path(path)
    with open_binary(path, limit) as fh:
        try:
            npz = np.load(fh, allow_pickle=False)
        except Exception as exc:                    # zipfile/pickle/format errors mean the same to a user
            raise ConfigError(path, FILE_FIELD, f"not a readable NumPy .npz archive ({type(exc).__name__})") from None
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise ConfigError(path, FILE_FIELD, "not a readable NumPy .npz archive (a single .npy array)")
        with npz:
            unpacked = sum(info.file_size for info in npz.zip.infolist())
            if unpacked > limit:
                raise ConfigError(path, FILE_FIELD, f"too large unpacked ({unpacked} bytes, the limit is {limit})")
            yield npz
