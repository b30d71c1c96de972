"""McapFile: after every commit, and at every point inside one where the writing process may die,
the file is an MCAP file that the ``mcap`` package's readers read to its last complete commit."""

from __future__ import annotations

import errno
import io
import os

import pytest
from mcap.reader import SeekingReader
from mcap.stream_reader import StreamReader
from mcap.writer import CompressionType, Writer

from mcap_readers import READERS, mcap_messages

from vflpcd.log.mcapfile import SKIP, TRAILER, McapFile

COMMITS = 4
PER_COMMIT = 30


def messages(data: bytes, reader: str) -> list[int]:
    """The message numbers ``reader`` reads from ``data`` (raises what the reader raises)."""
    return [int(m.data) for _, m in mcap_messages(data, reader)]


def write_run(path, on_commit=None) -> None:
    """COMMITS commits of PER_COMMIT messages numbered 0, 1, ..., then the final one."""
    f = McapFile(path)
    w = Writer(f, compression=CompressionType.NONE)
    w.start()
    channel = w.register_channel("/n", "json", w.register_schema("n", "jsonschema", b"{}"))
    n = 0
    for _ in range(COMMITS):
        for _ in range(PER_COMMIT):
            w.add_message(channel, n, str(n).encode(), n)
            n += 1
        w.flush()
        f.commit()
        if on_commit:
            on_commit(f)
    w.add_message(channel, n, str(n).encode(), n)
    w.finish()
    f.commit(final=True)
    f.close()


def test_each_commit_is_a_complete_file_for_seeking_and_stream_readers(tmp_path):
    path = tmp_path / "run.mcap"
    states = []
    write_run(path, lambda f: states.append(path.read_bytes()))
    for i, data in enumerate(states, start=1):
        assert data.endswith(TRAILER)
        for reader in READERS:
            assert messages(data, reader) == list(range(i * PER_COMMIT)), (i, reader)
    final = path.read_bytes()
    for reader in READERS:
        assert messages(final, reader) == list(range(COMMITS * PER_COMMIT + 1))
    summary = SeekingReader(io.BytesIO(final)).get_summary()
    assert summary is not None and len(summary.chunk_indexes) == COMMITS + 1     # indexed at the end
    assert summary.statistics.message_count == COMMITS * PER_COMMIT + 1


def test_a_process_killed_anywhere_in_a_commit_leaves_the_last_commit_readable(tmp_path, monkeypatch):
    """Snapshots of the file after every write call of the commits, and inside each write after
    every few bytes (what a kill leaves when it cuts a write): each reader reads whole commits."""
    path = tmp_path / "run.mcap"
    real = os.pwrite
    cuts: list[tuple[str, bytes]] = []

    def spy(fd, data, offset):
        data = bytes(data)
        before = path.read_bytes()
        kind = "skip" if data == SKIP else "trailer" if data == TRAILER else "data"
        for j in range(1, len(data), max(1, len(data) // 40)):       # cut inside this write
            state = bytearray(before) + bytes(max(0, offset + j - len(before)))
            state[offset:offset + j] = data[:j]
            cuts.append((kind, bytes(state)))
        n = real(fd, data, offset)
        cuts.append(("after", path.read_bytes()))
        return n

    monkeypatch.setattr(os, "pwrite", spy)
    write_run(path)
    monkeypatch.setattr(os, "pwrite", real)
    kinds = {k for k, _ in cuts}
    assert kinds == {"skip", "trailer", "data", "after"}
    committed = [i * PER_COMMIT for i in range(COMMITS + 1)] + [COMMITS * PER_COMMIT + 1]
    writes = 0
    for kind, data in cuts:
        if writes < 2:                  # the first commit (its trailer, then its bytes) is not complete
            writes += kind == "after"
            continue
        readers = ("stream",) if kind == "trailer" else READERS  # see McapFile's docstring
        for reader in readers:
            got = messages(data, reader)
            assert len(got) in committed and got == list(range(len(got))), (kind, reader, len(got))
    assert messages(path.read_bytes(), "seeking") == list(range(committed[-1]))


def test_a_write_error_cuts_the_file_back_to_its_last_commit(tmp_path, monkeypatch):
    path = tmp_path / "run.mcap"
    f = McapFile(path)
    w = Writer(f, compression=CompressionType.NONE)
    w.start()
    channel = w.register_channel("/n", "json", w.register_schema("n", "jsonschema", b"{}"))
    w.add_message(channel, 0, b"0", 0)
    w.flush()
    f.commit()
    good = path.read_bytes()
    real = os.pwrite
    calls = []

    def full(fd, data, offset):                 # the new trailer goes in, then the disk is full
        calls.append(len(data))
        if len(calls) > 1:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real(fd, data, offset)

    monkeypatch.setattr(os, "pwrite", full)
    for n in range(1, 50):
        w.add_message(channel, n, str(n).encode(), n)
    w.flush()
    with pytest.raises(OSError) as err:
        f.commit()
    monkeypatch.setattr(os, "pwrite", real)
    assert err.value.errno == errno.ENOSPC and f.pending == 0
    assert path.read_bytes() == good and f.committed == len(good)
    assert messages(path.read_bytes(), "seeking") == [0]
    f.close()
    f.close()


def test_the_final_commit_ends_in_the_writers_footer_and_closes_the_file_for_writing(tmp_path):
    path = tmp_path / "run.mcap"
    kept = []
    write_run(path, kept.append)
    f = kept[0]
    with pytest.raises(ValueError):
        f.commit()
    footer = list(StreamReader(io.BytesIO(path.read_bytes())).records)[-1]
    assert type(footer).__name__ == "Footer" and footer.summary_start > 0     # not a commit's trailer
