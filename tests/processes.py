"""Real processes for the integration tests: their output collected line by line as it comes."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
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
