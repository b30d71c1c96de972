"""A disk that fills up under one file, in this process: ``os.pwrite`` to that file fails with
ENOSPC once the file would grow past ``limit`` bytes; after that first failure ``slack`` bytes
stay free beyond the file's length then (the rest of its last disk block: 0 for none)."""

from __future__ import annotations

import errno
import os
from pathlib import Path


class FullDisk:
    """Install with ``monkeypatch.setattr(os, "pwrite", FullDisk(folder, limit, slack))``: the
    first ``*.mcap`` file opened in ``folder`` is the one that fills the disk."""

    def __init__(self, folder: Path, limit: int, slack: int = 0) -> None:
        self.folder, self.limit, self.slack = Path(folder), limit, slack
        self.real = os.pwrite
        self.inode: int | None = None
        self.failures = 0
        self._after_failure: int | None = None

    def _ours(self, fd: int) -> bool:
        if self.inode is None:
            found = sorted(self.folder.rglob("*.mcap"))
            if not found:
                return False
            self.inode = found[0].stat().st_ino
        return os.fstat(fd).st_ino == self.inode

    def __call__(self, fd: int, data, offset: int) -> int:
        if not self._ours(fd):
            return self.real(fd, data, offset)
        if self.failures and self._after_failure is None:
            self._after_failure = os.fstat(fd).st_size + self.slack
        limit = self.limit if self._after_failure is None else self._after_failure
        room = limit - offset
        if room <= 0 and len(data):
            self.failures += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return self.real(fd, bytes(data)[:room], offset)
