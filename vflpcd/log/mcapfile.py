"""An MCAP file that every MCAP reader reads completely after each commit, also when the process
writing it is killed.

MCAP readers need a file to end in a Footer record and the magic: a seeking reader (the ``mcap``
package's ``make_reader`` on a file, Foxglove) reads the footer at the end first, and a stream
reader stops at the first Footer it meets. ``McapFile`` is the output stream of an ``mcap``
``Writer``: what the writer writes stays in memory until ``commit()``, which appends it to the
file followed by a closing trailer (DataEnd, a Footer without a summary, the magic) and then turns
the previous trailer into a record that readers skip (opcode 0x80, one of the application
opcodes 0x80-0xFF that MCAP readers skip). The writes of one commit, in this order:

1. the new trailer, at the offset where the new bytes will end (the file is now: everything
   committed, the old trailer, a hole, the new trailer: a stream reader stops at the old
   trailer, a seeking reader finds the new one, which points it to a linear read);
2. the new bytes, into the hole;
3. ``os.fdatasync`` (the committed part survives a power cut from here on);
4. two bytes over the old trailer's first record (its opcode and the low byte of its length):
   the old trailer becomes a skipped record and readers go on into the new bytes.

A process killed between any two of them, or inside write 2 or 4, leaves a file that every
reader reads up to the last complete commit (only a kill that lands inside write 1 itself, a
50-byte write the kernel may cut at a page boundary, can spoil the end for a seeking reader;
stream readers still read it). A write error (a full disk) cuts the file back to its last commit
and is raised to the caller. ``commit(final=True)`` commits the writer's own summary and footer
the same way and then cuts off the trailer after them (a single truncation).
"""

from __future__ import annotations

import errno
import os
import struct
from pathlib import Path

from mcap.data_stream import RecordBuilder
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC

SKIP_OPCODE = 0x80


def _trailer() -> bytes:
    builder = RecordBuilder()
    DataEnd(0).write(builder)
    Footer(0, 0, 0).write(builder)
    return builder.end() + MCAP0_MAGIC


TRAILER = _trailer()
# The trailer's DataEnd record (length 4, high bytes 0) as a skipped record as long as the
# whole trailer: its opcode byte and the low byte of its length. Written as one 2-byte write:
# cut after the opcode, it is a skipped record of length 4 followed by the old Footer.
SKIP = struct.pack("<BB", SKIP_OPCODE, len(TRAILER) - 9)
assert len(TRAILER) - 9 < 256 and TRAILER[2:9] == bytes(7)


class McapFile:
    """The file at ``path`` (created or emptied; OSError when that fails), written through
    ``write``/``tell`` (what an ``mcap`` Writer calls) and made readable by ``commit()``."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        self._pending = bytearray()
        self._trailer_at: int | None = None   # where the closing trailer of the last commit starts
        self._base = 0                        # where the pending bytes will go
        self._final = False

    # -- the Writer's side -------------------------------------------------------------------

    def write(self, data: bytes) -> int:
        self._pending += data
        return len(data)

    def tell(self) -> int:
        """The offset in the file the next byte written will have."""
        return self._base + len(self._pending)

    def flush(self) -> None:
        """Nothing: the bytes reach the file at ``commit()``."""

    def fileno(self) -> int:
        return self._fd

    # -- the owner's side --------------------------------------------------------------------

    @property
    def pending(self) -> int:
        """Bytes written since the last commit."""
        return len(self._pending)

    @property
    def committed(self) -> int:
        """The file's length after the last commit."""
        return self._base

    def commit(self, final: bool = False) -> None:
        """Append the pending bytes and close the file with a trailer (``final``: the pending bytes
        end with the writer's own footer; nothing may be written after). On OSError the pending
        bytes are dropped, the file is cut back to its last commit and the error raised."""
        if self._final:
            raise ValueError("the MCAP file was finished")
        data = bytes(self._pending)
        self._pending.clear()
        if not data:
            return
        end = self._base + len(data)
        try:
            _pwrite_all(self._fd, TRAILER, end)
            _pwrite_all(self._fd, data, self._base)
            _datasync(self._fd)
            if self._trailer_at is not None:
                _pwrite_all(self._fd, SKIP, self._trailer_at)
        except OSError:
            try:
                os.ftruncate(self._fd, self._base)
            except OSError:
                pass
            raise
        self._trailer_at, self._base, self._final = end, end + len(TRAILER), final
        if final:                   # the writer's footer ends the file; a failure here leaves the
            try:                    # trailer after it, which readers read as well
                os.ftruncate(self._fd, end)
                _datasync(self._fd)
                self._trailer_at, self._base = None, end
            except OSError:
                pass

    def close(self) -> None:
        """Close the file (pending bytes are not written); idempotent, and silent on a close that
        fails (the descriptor is released either way; what was committed is on disk)."""
        if self._fd >= 0:
            fd, self._fd = self._fd, -1
            try:
                os.close(fd)
            except OSError:
                pass


def _pwrite_all(fd: int, data: bytes, offset: int) -> None:
    view = memoryview(data)
    while view:
        n = os.pwrite(fd, view, offset)
        if n <= 0:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        view, offset = view[n:], offset + n


def _datasync(fd: int) -> None:
    try:
        os.fdatasync(fd)
    except OSError as exc:
        if exc.errno != errno.EINVAL:      # EINVAL: a file that cannot be synced (a device, a pipe)
            raise
