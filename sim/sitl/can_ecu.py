"""``vflpcd sitl can-ecu MISSION``: the vehicle's drive-by-wire ECU and INS, mocked behind the DBC.

The mission's route (a ground scenario) gives the dynamic bicycle plant and its start pose; the
plant runs in real time. On the bus (``config/can/vehicle.dbc``, the mission's ``[platform]``
interface and channel, or ``--interface``/``--channel``):

- it publishes VehicleStatus (speed, yaw rate, applied steering, mode, fault bits) and the INS
  messages InsPosition and InsHeadingVelocity at the database's cycle times (20 ms, 10 ms);
- it follows VehicleCmd (0x100) frames that pass every check of ``drivers.can_codec`` (length,
  checksum, ranges) and whose alive counter advanced by one; every other frame on 0x100, and
  frames with unknown ids, are dropped and counted by kind.

Modes (the Mode signal), as a drive-by-wire ECU behaves:
- ``ready`` (1): at start, and after a hand-back; brakes held. Until the first engagement the
  plant is held at the route's start state (its start speed included), as the in-process
  platform holds it until ``enable()``.
- ``automatic`` (2): a valid frame with Enable = 1; the plant follows AccelCmd and SteerAngleCmd
  (held between frames; the plant applies its own limits).
- ``braking`` (3): no valid command for ``cmd_timeout`` s while automatic (FaultCmdTimeout set),
  or a valid Enable = 0 frame: full deceleration (a_min) with the steering held.
- ``stopped`` (4): standstill after a timeout; latched until a valid Enable = 0 frame re-arms the
  ECU (``ready``). A hand-back (Enable = 0) brakes to ``ready`` directly.
FaultBadCounter, FaultBadChecksum and FaultOutOfRange are set for 1 s after such a frame.
End-to-end supervision, as a drive-by-wire ECU's frame check does: ``max_counter_errors``
alive-counter errors within one second while automatic (frames replayed or injected beside the
commander's) take the vehicle over like a command timeout, with FaultBadCounter held: braking,
then a latched ``stopped`` (0 turns it off).

Authentication (the mission's ``[platform] auth_key``, the daemon's key; ``drivers/can_secoc.py``):
every frame the ECU and the INS send is followed by its authentication PDU, and a VehicleCmd is
followed only when its own verifies and its freshness value is newer than any before. Replayed,
forged and unauthenticated (plain-profile) commands are dropped before any other check and
counted by kind in ``bad_frames``; they take nothing over, the authenticated stream goes on.

A bus that fails (e.g. the python-can-remote hub goes away) counts as a command loss: the ECU
brakes and reopens the bus every 0.5 s. Nothing a peer sends can stop the loop.
"""

from __future__ import annotations

import json
import logging
import signal
import threading
import time

import numpy as np

from drivers.can_codec import (FRAME_ERRORS, LINK_MESSAGES, MODES, AliveCounter, CounterSource, FrameError,
                                VehicleCan)
from drivers.can_secoc import AUTH_ERRORS, AuthConfig, AuthError, Receiver, Sender, secured_ids

log = logging.getLogger("sim.sitl.can_ecu")

READY, AUTOMATIC, BRAKING, STOPPED = 1, 2, 3, 4
STANDSTILL = 0.05                 # m/s
FAULT_HOLD_S = 1.0
FAULT_BITS = {"counter": "FaultBadCounter", "checksum": "FaultBadChecksum", "range": "FaultOutOfRange"}


class CanEcu:
    """``bus_factory()``: opens the bus (called again after a bus error); ``plant``: a DynamicBicycle
    at its start state; ``limits``: its BicycleLimits; ``codec``: the DBC; ``auth``: the link's
    authentication (None: the plain profile)."""

    def __init__(self, bus_factory, plant, limits, codec: VehicleCan, *, cmd_timeout_s: float = 0.1,
                 physics_rate_hz: float = 200.0, max_counter_errors: int = 5, auth: AuthConfig | None = None) -> None:
        self.bus_factory, self.plant, self.limits, self.codec = bus_factory, plant, limits, codec
        self.cmd_timeout_s, self.dt = cmd_timeout_s, 1.0 / physics_rate_hz
        self.max_counter_errors = max_counter_errors
        self._counter_errors: list[float] = []     # times of the alive-counter errors in the last second
        self._mode = READY
        self._engaged = False              # the plant is held at its start state until the first Enable = 1
        self._timeout_fault = False        # FaultCmdTimeout: a command timeout took the vehicle over
        self._latched = False              # a take-over (timeout or counter errors) ends in a latched stop
        self._fault_until = dict.fromkeys(FAULT_BITS.values(), 0.0)
        self._command = np.array([limits.a_min, 0.0])
        self._last_cmd = 0.0
        self._counter = AliveCounter()
        self._ins_counter = CounterSource()
        self._bus = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._warned: dict[str, float] = {}
        self.counts = {"commands_ok": 0, "timeouts": 0, "counter_errors": 0, "bus_errors": 0, "status_sent": 0,
                       "ins_sent": 0, "reopens": 0, "malformed": 0}
        self.bad_frames = dict.fromkeys(FRAME_ERRORS + AUTH_ERRORS, 0)
        self._ids = {m.frame_id for m in codec.db.messages}
        self._cmd_id = codec.message("VehicleCmd").frame_id
        self.auth = auth
        self._auth_tx = self._auth_rx = None
        if auth is not None:
            secured_ids(codec.db, LINK_MESSAGES)      # the DBC has the authentication PDUs (ValueError)
            self._auth_tx = Sender(auth.key)
            self._auth_rx = Receiver(auth.key, (self._cmd_id,), self._on_auth_reject,
                                     clock_skew_s=auth.clock_skew_s)
        self.status_period = codec.message("VehicleStatus").cycle_time * 1e-3
        self.ins_period = codec.message("InsPosition").cycle_time * 1e-3

    # ------------------------------------------------------------------ public
    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, args=(self._stop,), name="can-ecu", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)

    def stats(self) -> dict:
        return {**self.counts, "bad_frames": dict(self.bad_frames), "mode": self.mode}

    @property
    def mode(self) -> str:
        return MODES[self._mode]

    @property
    def faults(self) -> dict:
        now = time.monotonic()
        bits = {name: int(now < until) for name, until in self._fault_until.items()}
        return {"FaultCmdTimeout": int(self._timeout_fault), **bits}

    @property
    def speed(self) -> float:
        return float(self.plant.state[3])

    @property
    def position(self) -> np.ndarray:
        return self.plant.position()

    @property
    def heading(self) -> float:
        return self.plant.heading()

    @property
    def standstill(self) -> bool:
        return self.speed < STANDSTILL

    # ------------------------------------------------------------------ loop
    def serve_forever(self, stop: threading.Event) -> None:
        period = int(self.dt * 1e9)
        now = time.monotonic_ns()
        next_step, next_status, next_ins = now + period, now, now
        next_open = now
        while not stop.is_set():
            now = time.monotonic_ns()
            if self._bus is None and now >= next_open:
                self._open()
                next_open = now + int(0.5e9)
            while next_step <= now:
                self._step()
                next_step += period
            if next_ins <= now:
                self._send_ins()
                next_ins += int(self.ins_period * 1e9)
                if next_ins <= now:                       # fell behind: skip, keep the cycle
                    next_ins = now + int(self.ins_period * 1e9)
            if next_status <= now:
                self._send_status()
                next_status += int(self.status_period * 1e9)
                if next_status <= now:
                    next_status = now + int(self.status_period * 1e9)
            wait = (min(next_step, next_ins, next_status) - time.monotonic_ns()) * 1e-9
            self._receive(max(wait, 0.0))
        self._close()

    def _open(self) -> None:
        try:
            self._bus = self.bus_factory()
            self.counts["reopens"] += 1
            log.info("event=bus_open")
        except Exception as exc:
            self._bus = None
            self._warn("bus", f"event=bus_open_failed reason={exc}")
            time.sleep(0.05)

    def _close(self) -> None:
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:
                pass
        self._bus = None

    def _bus_error(self, exc: Exception) -> None:
        self.counts["bus_errors"] += 1
        self._warn("bus", f"event=bus_error reason={type(exc).__name__}: {exc}")
        self._close()
        if self._mode == AUTOMATIC:
            self._take_over()

    def _receive(self, timeout: float) -> None:
        if self._bus is None:
            time.sleep(min(timeout, 0.01))
            return
        try:
            msg = self._bus.recv(timeout)
        except Exception as exc:
            self._bus_error(exc)
            return
        if msg is None:
            return
        try:
            self._on_frame(msg)
        except Exception as exc:                       # nothing on the bus may stop the ECU
            self.counts["malformed"] += 1
            self._warn("malformed", f"event=malformed_frame reason={type(exc).__name__}: {exc}")

    def _on_frame(self, msg) -> None:
        if self._auth_rx is not None:
            msg = self._auth_rx.feed(msg)
            if msg is None:
                return
        if msg.arbitration_id != self._cmd_id or msg.is_extended_id:
            if msg.arbitration_id not in self._ids or msg.is_extended_id:
                self._bad("unknown_id", f"id 0x{msg.arbitration_id:X}")
            return
        try:
            frame = self.codec.decode(msg)
        except FrameError as exc:
            self._bad(exc.kind, str(exc))
            return
        s = frame.signals
        if not self._counter.accept(s["AliveCounter"]):
            self._bad("counter", f"counter {s['AliveCounter']}")
            self._counter_error()
            return
        self.counts["commands_ok"] += 1
        self._last_cmd = time.monotonic()
        if s["Enable"]:
            if self._mode in (READY, AUTOMATIC):
                self._mode, self._engaged = AUTOMATIC, True
                self._command = np.array([s["AccelCmd"], s["SteerAngleCmd"]])
        elif self._mode == STOPPED:
            self._mode, self._latched, self._timeout_fault = READY, False, False      # re-armed
            self._fault_until["FaultBadCounter"] = 0.0
        elif self._mode == AUTOMATIC:
            self._mode = BRAKING                                   # hand-back: brake to ready

    def _bad(self, kind: str, detail: str) -> None:
        self.bad_frames[kind] += 1
        if kind in FAULT_BITS:
            bit = FAULT_BITS[kind]
            self._fault_until[bit] = max(self._fault_until[bit], time.monotonic() + FAULT_HOLD_S)
        self._warn(kind, f"event=bad_frame kind={kind} detail={detail} counts={self.bad_frames}")

    def _on_auth_reject(self, exc: AuthError) -> None:
        self._bad(exc.kind, str(exc))

    def _counter_error(self) -> None:
        """End-to-end supervision: too many counter errors in a second take the vehicle over."""
        if not self.max_counter_errors:
            return
        now = time.monotonic()
        self._counter_errors = [t for t in self._counter_errors if now - t < 1.0] + [now]
        if len(self._counter_errors) >= self.max_counter_errors and self._mode == AUTOMATIC:
            self._fault_until["FaultBadCounter"] = now + 1e9          # held while latched
            self._take_over("counter_errors")

    def _take_over(self, why: str = "command_timeout") -> None:
        self._mode, self._latched, self._timeout_fault = BRAKING, True, why == "command_timeout"
        self.counts["timeouts" if why == "command_timeout" else why] += 1
        log.warning("event=%s action=brake_to_stop speed=%.2f", why, self.speed)

    # ------------------------------------------------------------------ physics
    def _step(self) -> None:
        if not self._engaged:
            return
        if self._mode == AUTOMATIC and time.monotonic() - self._last_cmd > self.cmd_timeout_s:
            self._take_over()
        if self._mode == AUTOMATIC:
            u = self._command
        else:
            u = np.array([self.limits.a_min, self.plant.applied_control[1]])   # brakes, steering held
        self.plant.step(u, self.dt)
        if self._mode == BRAKING and self.standstill:
            self._mode = STOPPED if self._latched else READY
            log.warning("event=standstill mode=%s", self.mode)

    # ------------------------------------------------------------------ publishing
    def _send(self, name: str, signals: dict) -> bool:
        if self._bus is None:
            return False
        msg = self.codec.message(name)
        clamped = {}
        for s in msg.signals:
            if s.name in signals:
                v = float(signals[s.name])
                clamped[s.name] = min(max(v, s.minimum), s.maximum) if np.isfinite(v) else 0.0
        frame = self.codec.encode(name, clamped)
        try:
            self._bus.send(frame)
            if self._auth_tx is not None:
                self._bus.send(self._auth_tx.protect(frame))
            return True
        except Exception as exc:
            self._bus_error(exc)
            return False

    def _send_status(self) -> None:
        x = self.plant.state
        ok = self._send("VehicleStatus", {"Speed": max(x[3], 0.0), "YawRate": x[5],
                                          "SteerAngle": self.plant.applied_control[1], "Mode": self._mode,
                                          **self.faults})
        self.counts["status_sent"] += int(ok)

    def _send_ins(self) -> None:
        x = self.plant.state
        ok = self._send("InsPosition", {"PosX": x[0], "PosY": x[1]})
        ok = self._send("InsHeadingVelocity", {"Heading": x[2], "VelX": x[3], "VelY": x[4],
                                               "AliveCounter": self._ins_counter.take()}) and ok
        self.counts["ins_sent"] += int(ok)

    def _warn(self, kind: str, line: str) -> None:
        now = time.monotonic()
        if now - self._warned.get(kind, -1e9) >= 1.0:
            self._warned[kind] = now
            log.warning(line)


# ---------------------------------------------------------------------- command line
def add_arguments(p) -> None:
    from pathlib import Path

    p.add_argument("mission", type=Path, help="the mission the ECU plays the vehicle of ([platform] kind = \"can\")")
    p.add_argument("--interface", default=None, help="override the mission's bus interface (socketcan, remote, virtual)")
    p.add_argument("--channel", default=None, help="override the mission's bus channel (vcan0, ws://127.0.0.1:PORT/)")
    p.add_argument("--dbc", default=None, help="CAN database (default config/can/vehicle.dbc)")
    p.add_argument("--cmd-timeout", type=float, default=0.1, help="brake to a stop after this long without a "
                                                                  "valid command, s (default 0.1)")
    p.add_argument("--max-counter-errors", type=int, default=5,
                   help="alive-counter errors within 1 s that take the vehicle over to a latched stop "
                        "(end-to-end supervision; 0: off; default 5)")
    p.add_argument("--physics-rate", type=float, default=200.0, help="plant steps per second (default 200)")
    p.add_argument("--seed", type=int, default=0, help="plant noise seed (default 0)")
    p.add_argument("--connect-timeout", type=float, default=10.0, help="give up opening the bus after this long, s")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))


def run(args) -> int:
    from drivers.can_bus import BusConfig, bus_config, open_bus
    from drivers.can_secoc import auth_config
    from sim.plants import make_plant
    from vflpcd.config.vehicles import BicycleConfig
    from vflpcd.base.errors import ConfigError
    from vflpcd.config.mission import load_mission
    from vflpcd.base.tomlread import Table

    def check(name: str, value: float, lo: float, hi: float) -> None:
        if not (lo <= value <= hi):
            raise ConfigError("command line", f"--{name}", f"must lie in [{lo:g}, {hi:g}], got {value:g}")

    check("cmd-timeout", args.cmd_timeout, 0.02, 5.0)
    check("max-counter-errors", args.max_counter_errors, 0, 1000)
    check("physics-rate", args.physics_rate, 50.0, 2000.0)
    check("connect-timeout", args.connect_timeout, 0.0, 600.0)
    check("seed", args.seed, 0, 2**32 - 1)
    mission = load_mission(args.mission)
    if mission.platform.kind != "can":
        raise ConfigError(mission.file, "platform.kind", f"the ECU mock plays can platforms, not {mission.platform.kind}")
    table = Table(mission.platform.options, mission.file, "platform")
    base = bus_config(table)
    auth = auth_config(table, mission.file)
    try:
        cfg = BusConfig(args.interface or base.interface, args.channel or base.channel)
    except ValueError as exc:
        raise ConfigError("command line", "--channel", str(exc)) from None
    try:
        codec = VehicleCan(args.dbc)
    except Exception as exc:
        raise ConfigError("command line", "--dbc", f"cannot load the CAN database: {exc}") from None
    if auth is not None:
        try:
            secured_ids(codec.db, LINK_MESSAGES)
        except ValueError as exc:
            raise ConfigError("command line", "--dbc", str(exc)) from None
    bus = _open_with_retry(open_bus, cfg, args.connect_timeout)
    if bus is None:
        print(f"vflpcd sitl can-ecu: error: cannot open {cfg.describe()} within {args.connect_timeout:g} s")
        return 1
    first = [bus]

    def factory():
        return first.pop() if first else open_bus(cfg)

    sc = mission.scenario
    ecu = CanEcu(factory, make_plant(sc, args.seed), BicycleConfig.load(sc.params).limits, codec,
                 cmd_timeout_s=args.cmd_timeout, physics_rate_hz=args.physics_rate,
                 max_counter_errors=args.max_counter_errors, auth=auth)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    log.info("event=ecu_started bus=%s scenario=%s cmd_timeout=%.3f authenticated=%s", cfg.describe(), sc.name,
             args.cmd_timeout, auth is not None)
    ecu.serve_forever(stop)
    print(json.dumps({"ecu_stats": ecu.stats()}), flush=True)
    return 0


def _open_with_retry(open_bus, cfg, timeout_s: float):
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            return open_bus(cfg)
        except OSError as exc:
            if time.monotonic() >= deadline:
                log.error("event=bus_open_failed reason=%s", exc)
                return None
            time.sleep(0.5)
