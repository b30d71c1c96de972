"""python-can-remote's hub as a real process on loopback: the CAN bus between processes here
(the kernel has no SocketCAN)."""

from __future__ import annotations

import contextlib
import socket
import struct
import subprocess
import sys
import threading
import time

import can

from loopback import free_port

INS_POSITION = 0x300     # config/can/vehicle.dbc


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


class BusTap:
    """A bus client of its own that records every frame: (monotonic receive time, id, data)."""

    def __init__(self, url: str) -> None:
        self.bus = can.Bus(interface="remote", channel=url)
        self.frames: list[tuple[float, int, bytes]] = []
        self.x = float("-inf")                 # the newest InsPosition's PosX
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="can-tap", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                msg = self.bus.recv(0.05)
                if msg is None:
                    continue
                self.frames.append((time.monotonic(), msg.arbitration_id, bytes(msg.data)))
                self.on_frame(msg)
        except BaseException as exc:           # the test reports it
            self.error = exc

    def on_frame(self, msg: can.Message) -> None:
        """Every frame after it is recorded: the newest InsPosition's PosX becomes ``x``."""
        if msg.arbitration_id == INS_POSITION:
            self.x = struct.unpack_from("<i", bytes(msg.data))[0] * 1e-3

    def wait_x(self, x: float, timeout: float) -> float:
        """When the car (InsPosition) passed ``x``."""
        deadline = time.monotonic() + timeout
        while self.x < x:
            assert self.error is None, f"the bus tap failed: {self.error!r}"
            assert time.monotonic() < deadline, f"the car did not pass x = {x} m within {timeout} s (x = {self.x})"
            time.sleep(0.01)
        return time.monotonic()

    def since(self, frame_id: int, t0: float, t1: float = float("inf")) -> list[tuple[float, bytes]]:
        return [(t, d) for t, i, d in list(self.frames) if i == frame_id and t0 <= t <= t1]

    def close(self) -> None:
        self._stop.set()
        self._thread.join(2.0)
        self.bus.shutdown()


def close_all(sender, tap: BusTap | None, *procs) -> None:
    """A test's clean-up: stop the frame ``sender`` (an attacker or a replay) if it still runs,
    close the ``tap``, kill the processes (``processes.Proc``) that did not end."""
    if sender is not None and sender.running:
        sender.stop()
    if tap is not None:
        tap.close()
    for proc in procs:
        if proc is not None and proc.p.poll() is None:
            proc.kill()
