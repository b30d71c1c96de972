"""Real processes for the integration tests: their output collected line by line as it comes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


class Proc:
    """``python -m vflpcd ARGS`` (or ``argv`` as given) with stdout and stderr read by threads."""

    def __init__(self, *args: str, argv: list[str] | None = None) -> None:
        self.argv = argv or [sys.executable, "-m", "vflpcd", *args]
        self.p = subprocess.Popen(self.argv, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.out: list[str] = []
        self.err: list[tuple[float, str]] = []
        self._threads = [threading.Thread(target=self._read, args=(self.p.stdout, False), daemon=True),
                         threading.Thread(target=self._read, args=(self.p.stderr, True), daemon=True)]
        for t in self._threads:
            t.start()

    def _read(self, stream, is_err: bool) -> None:
        for line in stream:
            if is_err:
                self.err.append((time.monotonic(), line.rstrip("\n")))
            else:
                self.out.append(line.rstrip("\n"))

    def wait_line(self, text: str, timeout: float, after: float = 0.0) -> float:
        """When the first stderr line containing ``text`` arrived at or after monotonic time ``after``
        (AssertionError after ``timeout``)."""
        deadline = time.monotonic() + timeout
        exited_at = None
        while time.monotonic() < deadline:
            for t, line in list(self.err):
                if t >= after and text in line:
                    return t
            if self.p.poll() is not None:
                exited_at = exited_at or time.monotonic()
                if time.monotonic() - exited_at > 0.5:       # its last lines have been read
                    break
            time.sleep(0.02)
        raise AssertionError(f"{text!r} not logged by {self.argv[3:5]} within {timeout} s; "
                             f"last lines:\n" + "\n".join(line for _, line in self.err[-15:]))

    def lines_with(self, text: str) -> list[tuple[float, str]]:
        return [(t, line) for t, line in self.err if text in line]

    def wait(self, timeout: float) -> int:
        rc = self.p.wait(timeout)
        for t in self._threads:
            t.join(2.0)
        return rc

    def stop(self, sig=signal.SIGTERM, timeout: float = 10.0) -> int:
        if self.p.poll() is None:
            self.p.send_signal(sig)
        try:
            return self.wait(timeout)
        except subprocess.TimeoutExpired:
            self.p.kill()
            return self.wait(5.0)

    def text(self) -> str:
        return "\n".join(self.out) + "\n" + "\n".join(line for _, line in self.err)

    def kill(self, timeout: float = 5.0) -> list["ProcInfo"]:
        """SIGKILL it and see its descendants end too (``kill_tree``); those that lingered."""
        lingered = kill_tree(self.p, timeout)
        self.wait(5.0)
        return lingered


# Processes as /proc shows them (Linux): for the tests that nothing outlives a daemon they kill.

@dataclass(frozen=True)
class ProcInfo:
    """One process: ids, state (``Z``: a zombie, ended), start time (clock ticks since boot: with
    the pid, a process's identity) and command line."""

    pid: int
    ppid: int
    pgrp: int
    session: int
    state: str
    start: int
    cmdline: str

    def alive(self) -> bool:
        now = proc_info(self.pid)
        return now is not None and now.start == self.start and now.state != "Z"


def proc_info(pid: int) -> ProcInfo | None:
    """The process ``pid`` now, None when there is none."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
        cmdline = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except (FileNotFoundError, ProcessLookupError):
        return None
    fields = stat[stat.rindex(")") + 2:].split()         # the command name may hold spaces and ")"
    return ProcInfo(pid, int(fields[1]), int(fields[2]), int(fields[3]), fields[0], int(fields[19]),
                    cmdline.strip())


def processes() -> list[ProcInfo]:
    """Every process now."""
    found = (proc_info(int(d.name)) for d in Path("/proc").iterdir() if d.name.isdigit())
    return [p for p in found if p is not None]


def descendants(pid: int) -> list[ProcInfo]:
    """The living children of ``pid``, their children, and so on."""
    table = [p for p in processes() if p.state != "Z"]
    out, parents = [], {pid}
    while True:
        new = [p for p in table if p.ppid in parents and p not in out]
        if not new:
            return out
        out += new
        parents = {p.pid for p in new}


def session_members(sid: int) -> list[ProcInfo]:
    """The living processes of session ``sid`` or of process group ``sid``."""
    return [p for p in processes() if sid in (p.session, p.pgrp) and p.state != "Z"]


def wait_gone(procs: list[ProcInfo], timeout: float) -> list[ProcInfo]:
    """Wait until none of ``procs`` is alive (at most ``timeout`` s); those still alive."""
    deadline = time.monotonic() + timeout
    while True:
        left = [p for p in procs if p.alive()]
        if not left or time.monotonic() >= deadline:
            return left
        time.sleep(0.02)


def kill_tree(proc: subprocess.Popen, timeout: float = 5.0) -> list[ProcInfo]:
    """SIGKILL ``proc`` (its descendants read first: once it is gone they have another parent),
    reap it, give its descendants ``timeout`` s to end by themselves, then SIGKILL those left;
    returns those that had to be killed."""
    below = descendants(proc.pid) if proc.poll() is None else []
    if proc.poll() is None:
        proc.kill()
    proc.wait(5.0)
    left = wait_gone(below, timeout)
    for p in left:
        if p.alive():
            try:
                os.kill(p.pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
    return left
