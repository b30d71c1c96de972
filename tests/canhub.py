"""python-can-remote's hub as a real process on loopback: the CAN bus between processes here
(the kernel has no SocketCAN)."""

from __future__ import annotations

import contextlib
import socket
import subprocess
import sys
import time

from loopback import free_port


def start_hub(port: int) -> subprocess.Popen:
    """The hub serving a virtual bus on 127.0.0.1:``port``, once it accepts connections."""
    proc = subprocess.Popen([sys.executable, "-m", "can_remote", "-H", "127.0.0.1", "--interface", "virtual",
                             "--channel", "vcan0", "--port", str(port)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 10.0
    while True:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return proc
        if proc.poll() is not None or time.monotonic() > deadline:
            proc.kill()
            raise RuntimeError(f"the CAN hub did not start on port {port}")
        time.sleep(0.05)


def stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


@contextlib.contextmanager
def can_hub(port: int | None = None):
    """Yields (url, process) of a running hub; stops it at the end."""
    port = port or free_port()
    proc = start_hub(port)
    try:
        yield f"ws://127.0.0.1:{port}/", proc
    finally:
        stop(proc)
