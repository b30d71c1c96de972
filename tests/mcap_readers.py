"""A file's messages as the ``mcap`` package's own readers read them: the tests' check that a flight
log is readable by other MCAP readers than ``vflpcd.log.reader``."""

from __future__ import annotations

import io

from mcap.reader import NonSeekingReader, SeekingReader, make_reader
from mcap.records import Message

READERS = ("seeking", "stream")


class Unseekable(io.RawIOBase):
    """The bytes as a pipe shows them: readable, not seekable."""

    def __init__(self, data: bytes) -> None:
        self._f = io.BytesIO(data)

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        return self._f.readinto(b)


def mcap_messages(data: bytes, reader: str) -> list[tuple[str, Message]]:
    """(topic, message) of every message of the MCAP bytes ``data``, in log-time order, read by
    ``make_reader`` (CRCs validated) on a seekable stream ("seeking": the SeekingReader) or on a
    pipe-like one ("stream": the NonSeekingReader); raises what the reader raises."""
    stream = io.BytesIO(data) if reader == "seeking" else io.BufferedReader(Unseekable(data))
    r = make_reader(stream, validate_crcs=True)
    assert isinstance(r, {"seeking": SeekingReader, "stream": NonSeekingReader}[reader])
    return [(channel.topic, message) for _, channel, message in r.iter_messages()]
