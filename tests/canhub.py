"""python-can-remote's hub as a real process on loopback: the CAN bus between processes here
(the kernel has no SocketCAN)."""

from __future__ import annotations

import contextlib
from collections import Counter
import json
import socket
import struct
import subprocess
import sys
import threading
import time

import can
import numpy as np

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


def edited_copy(source, dest, replacements) -> None:
    """``source``'s text with each (old, new) of ``replacements`` made (each old found exactly once:
    a test fails loudly when the shipped file changes) written to ``dest``."""
    text = source.read_text()
    for old, new in replacements:
        assert text.count(old) == 1, f"{source} changed: {old!r} not found once"
        text = text.replace(old, new)
    dest.write_text(text)


def receive_for(bus: can.BusABC, seconds: float) -> list[can.Message]:
    """Every frame ``bus`` receives in the next ``seconds``."""
    out, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline:
        msg = bus.recv(0.01)
        if msg is not None:
            out.append(msg)
    return out


def ecu_stats(proc) -> dict:
    """The counters the ECU mock (``vflpcd sitl can-ecu``, a ``processes.Proc``) printed as it ended."""
    return next(json.loads(line)["ecu_stats"] for line in proc.out if line.startswith('{"ecu_stats"'))


class PacedSender:
    """Sends the rounds of ``rounds()`` (name, [(frame id, data), ...]) on a bus client of its own,
    at exponential gaps of mean 1 / rate_hz, from its own thread; ``log``: (monotonic time, name) of
    each round sent. A subclass sets its fields, then calls this ``__init__``, which starts it."""

    def __init__(self, url: str, rate_hz: float, seed: int, name: str) -> None:
        self.bus = can.Bus(interface="remote", channel=url)
        self.rate_hz = rate_hz
        self.rng = np.random.default_rng(seed)
        self.log: list[tuple[float, str]] = []
        self.error: BaseException | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self.started = time.monotonic()
        self._thread.start()

    def rounds(self):
        raise NotImplementedError

    def _run(self) -> None:
        next_t = self.started
        try:
            for name, frames in self.rounds():
                if self._stop.is_set():
                    return
                for frame_id, data in frames:
                    self.bus.send(can.Message(arbitration_id=frame_id, data=data, is_extended_id=False))
                self.log.append((time.monotonic(), name))
                next_t += self.rng.exponential(1.0 / self.rate_hz)
                time.sleep(max(0.0, next_t - time.monotonic()))
        except BaseException as exc:           # the test reports it
            self.error = exc

    @property
    def running(self) -> bool:
        return self._thread.is_alive()

    def sent(self, until: float = float("inf")) -> dict[str, int]:
        """Rounds sent by name, up to the monotonic time ``until``."""
        return dict(Counter(name for t, name in self.log if t <= until))

    def stop(self) -> float:
        """Stop sending; the time it stopped."""
        self._stop.set()
        self._thread.join(2.0)
        self.bus.shutdown()
        return time.monotonic()


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
