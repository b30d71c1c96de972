"""The CAN-bus vehicle: the daemon's ``Platform`` over python-can and the DBC (``config/can/vehicle.dbc``).

Receive path: a python-can ``Notifier`` on the asyncio loop feeds an ``AsyncBufferedReader``; a
task decodes each frame with ``drivers.can_codec`` (frames that fail a check are dropped and
counted by kind) and assembles the state in the plant's order (X, Y, psi, vx, vy, omega) from
InsPosition (X, Y), InsHeadingVelocity (psi, vx, vy; its alive counter checked) and
VehicleStatus (omega = YawRate; mode and fault bits). The state's stamp is the receive time of
its oldest part.

Send path: ``send(u)`` encodes VehicleCmd (AccelCmd = a_x, SteerAngleCmd = delta_f, clipped to
the vehicle's limits, Enable = 1, alive counter, checksum) and sends it at once; between two
control ticks the newest command is repeated at the message's cycle time (20 ms) while it is
younger than ``command_hold`` s, so a stalled controller never keeps the vehicle going: the
ECU's own command timeout then brakes it.

Faults (``fault()``, the daemon's link-loss failsafe): the bus is down, no INS frame for
``state_timeout`` s, the ECU reports that it took over (braking or stopped after a command
timeout or alive-counter errors, or manual) while the daemon commands, or VehicleCmd frames from
another sender were on the bus in the last ``FOREIGN_WINDOW_S`` (the bus does not echo the
driver's own frames: these are replayed, forged or a second commander's; counted in
``foreign_commands``). A lost bus is reopened every ``reconnect_s`` s;
frames from a restarted ECU are taken again at once (``link_restored`` in the log).

Safe action (``failsafe``): AccelCmd = a_min with the steering held until the vehicle stands
still, then Enable = 0 (the ECU holds the brakes in ``ready``). ``at_rest``: the last VehicleStatus
reported a standstill; the daemon waits for it before it exits.
``close`` sends Enable = 0 as the last command of an engaged vehicle (the hand-back: the ECU
brakes to ``ready``).

Authentication (``auth``, the mission's ``auth_key``; ``drivers/can_secoc.py``): every
VehicleCmd frame is followed by its authentication PDU (freshness value and truncated MAC), and
VehicleStatus and INS frames are used only when theirs verifies and is fresh; replayed, forged
and unauthenticated (plain-profile) frames are dropped and counted by kind in ``bad_frames``
(by message in ``auth_rejected``). INS frames that fail authentication do not refresh the state:
a run of them is the stale state of ``state_timeout`` and the fault says how many were rejected.
A foreign VehicleCmd that authenticates with a freshness value at or below the driver's own
newest one is a replay and is counted only; one above it (a second sender with the key) is
the foreign-command fault. Without ``auth`` (the plain profile) authentication PDUs are ignored.

``bus_log``: every frame received and sent, in python-can's format for the file's suffix
(.asc, .log, .blf), readable by cantools with the same DBC.
"""

from __future__ import annotations

import asyncio
import logging
import threading
import time
from pathlib import Path

import can
import numpy as np

from drivers.can_bus import BusConfig, bus_config, open_bus
from drivers.can_codec import (FRAME_ERRORS, LINK_MESSAGES, MODES, AliveCounter, CounterSource, FrameError,
                                VehicleCan)
from drivers.can_secoc import (AUTH_ERRORS, AUTH_SUFFIX, AuthConfig, AuthError, Receiver, Sender, auth_config,
                                secured_ids)
from vflpcd.core.ports import PlatformBase, StampedState

log = logging.getLogger("drivers.can_vehicle")

STATE_NAMES = ("X", "Y", "psi", "vx", "vy", "omega")
CONTROL_NAMES = ("a_x", "delta_f")
BUS_LOG_FORMATS = ("", "asc", "log", "blf")
STANDSTILL = 0.05          # m/s
FOREIGN_WINDOW_S = 1.0     # s: another sender's VehicleCmd this recent is a fault
INS = ("InsPosition", "InsHeadingVelocity")


class _LockedLogger(can.Listener):
    """A python-can file logger shared by the notifier thread (received) and the loop (sent)."""

    def __init__(self, path: Path) -> None:
        self._lock = threading.Lock()
        self._writer = can.Logger(str(path))
        self.frames = 0

    def on_message_received(self, msg: can.Message) -> None:
        with self._lock:
            self._writer.on_message_received(msg)
            self.frames += 1

    def stop(self) -> None:
        with self._lock:
            self._writer.stop()


class _ErrorListener(can.Listener):
    """Passes the notifier's receive-thread failure on."""

    def __init__(self, on_error) -> None:
        self.on_error = on_error

    def on_message_received(self, msg: can.Message) -> None:
        pass


class CanVehicle(PlatformBase):
    """``bus``: which bus to open; ``limits``: the vehicle's ``BicycleLimits`` (a_min, a_max,
    delta_max); ``codec``: the DBC; ``state_timeout``, ``command_hold``, ``reconnect_s`` in s;
    ``bus_log``: a file to record the traffic to (None: no recording); ``auth``: the link's
    authentication (None: the plain profile; ValueError when the DBC lacks its PDUs)."""

    state_names = STATE_NAMES
    control_names = CONTROL_NAMES

    def __init__(self, bus: BusConfig, limits, codec: VehicleCan | None = None, *, state_timeout: float = 0.1,
                 command_hold: float = 0.1, reconnect_s: float = 0.5, bus_log: Path | None = None,
                 auth: AuthConfig | None = None) -> None:
        self.bus_cfg, self.limits = bus, limits
        self.codec = codec or VehicleCan()
        self.state_timeout, self.command_hold, self.reconnect_s = state_timeout, command_hold, reconnect_s
        self.bus_log = bus_log
        self.cycle_s = self.codec.message("VehicleCmd").cycle_time * 1e-3
        self.bad_frames = dict.fromkeys(FRAME_ERRORS + AUTH_ERRORS, 0)
        self.auth = auth
        self.auth_rejected = dict.fromkeys(LINK_MESSAGES, 0)  # frames failing authentication, by message
        self._ins_rejected = 0                                 # INS frames rejected since the last good one
        self._auth_tx: Sender | None = None
        self._auth_rx: Receiver | None = None
        if auth is not None:
            ids = secured_ids(self.codec.db, LINK_MESSAGES)
            self._names = {i: n for n, i in ids.items()}
            self._cmd_id = ids["VehicleCmd"]
            self._auth_tx = Sender(auth.key)
            self._auth_rx = Receiver(auth.key, ids.values(), self._on_auth_reject, clock_skew_s=auth.clock_skew_s)
        self.frames_ok = 0
        self.foreign_commands = 0            # VehicleCmd frames from another sender (replayed, forged, a second master)
        self._foreign_ns: int | None = None
        self.undecodable = 0                 # frames that passed the checks and still failed to decode
        self.frames_sent = 0
        self.send_failures = 0
        self.reconnects = 0
        self.ecu_mode: str | None = None
        self.ecu_faults: dict = {}
        self.failsafe_reason: str | None = None
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._reader: can.AsyncBufferedReader | None = None
        self._logger: _LockedLogger | None = None
        self._bus_error: str | None = None
        self._tasks: list[asyncio.Task] = []
        self._rx_task: asyncio.Task | None = None
        self._counter = CounterSource()
        self._ins_counter = AliveCounter()
        self._parts: dict[str, tuple[dict, int]] = {}
        self._latest: StampedState | None = None
        self._last_rx_ns: int | None = None
        self._link_up = False
        self._enabled = False
        self._command: np.ndarray | None = None
        self._command_ns = 0
        self._speed = 0.0

    # ------------------------------------------------------------------ Platform
    async def connect(self) -> None:
        aio = asyncio.get_running_loop()
        if self.bus_log is not None:
            self._logger = _LockedLogger(self.bus_log)
        await self._open(aio)
        self._tasks = [asyncio.create_task(self._cyclic_sender(), name="can-cyclic"),
                       asyncio.create_task(self._supervisor(aio), name="can-supervisor")]

    async def enable(self) -> None:
        """Engage: an ECU that stopped the vehicle after a timeout is re-armed first (Enable = 0 until
        it reports ``ready``); a manual ECU refuses (RuntimeError)."""
        if self.ecu_mode == "manual":
            raise RuntimeError("the ECU is in manual mode: a driver has the vehicle")
        deadline = time.monotonic() + 1.0
        while self.ecu_mode in ("braking", "stopped"):
            if time.monotonic() > deadline:
                raise RuntimeError(f"the ECU stays in {self.ecu_mode} mode after re-arming (Enable = 0)")
            self._transmit(0.0, 0.0, enable=False)
            await asyncio.sleep(self.cycle_s)
        self._enabled = True

    def latest_state(self) -> StampedState | None:
        return self._latest

    def fault(self) -> str | None:
        """Why the vehicle cannot be commanded now (None while healthy)."""
        if self._bus_error is not None:
            return f"CAN bus down ({self._bus_error})"
        now = time.monotonic_ns()
        if self._last_rx_ns is None or now - self._last_rx_ns > self.state_timeout * 1e9:
            if self._ins_rejected:
                return (f"no authenticated INS frames for {self.state_timeout:g} s on {self.bus_cfg.describe()} "
                        f"({self._ins_rejected} rejected)")
            return f"no INS frames for {self.state_timeout:g} s on {self.bus_cfg.describe()}"
        if self._enabled and self.failsafe_reason is None:
            if self.ecu_mode == "manual":
                return "the ECU switched to manual"
            if self.ecu_mode in ("braking", "stopped") and self.ecu_faults.get("FaultCmdTimeout"):
                return f"the ECU took over ({self.ecu_mode}: command timeout)"
            if self.ecu_mode in ("braking", "stopped") and self.ecu_faults.get("FaultBadCounter"):
                return f"the ECU took over ({self.ecu_mode}: alive-counter errors)"
            if self._foreign_ns is not None and now - self._foreign_ns < FOREIGN_WINDOW_S * 1e9:
                return (f"another sender's VehicleCmd frames on the bus ({self.foreign_commands}: replayed, "
                        f"forged or a second commander)")
        return None

    async def send(self, command: np.ndarray) -> None:
        u = np.asarray(command, dtype=float)
        if u.shape != (2,) or not np.all(np.isfinite(u)):
            raise ValueError(f"command must be 2 finite numbers {CONTROL_NAMES}, got {u!r}")
        if self.failsafe_reason is not None or not self._enabled:
            return
        lim = self.limits
        self._command = np.array([np.clip(u[0], lim.a_min, lim.a_max), np.clip(u[1], -lim.delta_max, lim.delta_max)])
        self._command_ns = time.monotonic_ns()
        self._transmit(*self._command, enable=True)

    async def failsafe(self, reason: str) -> None:
        if self.failsafe_reason is None:
            self.failsafe_reason = reason
            log.warning("event=safe_action reason=%s action=brake", reason)

    async def close(self) -> None:
        tasks = self._tasks + ([self._rx_task] if self._rx_task is not None else [])
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        self._tasks, self._rx_task = [], None
        if self._enabled:
            self._transmit(0.0, 0.0, enable=False)           # hand back: the ECU brakes to ready
        self._close_bus()
        if self._logger is not None:
            self._logger.stop()
        log.info("event=can_stats frames_ok=%d sent=%d bad=%s send_failures=%d reconnects=%d",
                 self.frames_ok, self.frames_sent, self.bad_frames, self.send_failures, self.reconnects)

    @property
    def at_rest(self) -> bool:
        """The last VehicleStatus reported a standstill."""
        return self._latest is not None and abs(self._speed) < STANDSTILL

    def link_stats(self) -> dict:
        return {"frames_ok": self.frames_ok, "frames_sent": self.frames_sent, "bad_frames": dict(self.bad_frames),
                "undecodable": self.undecodable, "foreign_commands": self.foreign_commands,
                "send_failures": self.send_failures, "reconnects": self.reconnects, "ecu_mode": self.ecu_mode,
                "authenticated": self.auth is not None, "auth_rejected": dict(self.auth_rejected)}

    def link_warnings(self) -> tuple[str, ...]:
        if self.auth is None:
            return ("the CAN link is not authenticated (no [platform] auth_key): replayed or forged frames "
                    "on the bus cannot be told from the vehicle's",)
        return ()

    # ------------------------------------------------------------------ bus
    async def _open(self, aio) -> None:
        self._bus = await aio.run_in_executor(None, open_bus, self.bus_cfg)
        self._reader = can.AsyncBufferedReader()
        listeners: list = [self._reader, _ErrorListener(self._on_bus_error)]
        if self._logger is not None:
            listeners.append(self._logger)
        self._notifier = can.Notifier(self._bus, listeners, timeout=0.1, loop=aio)
        self._bus_error = None
        if self._rx_task is not None:
            self._rx_task.cancel()
        self._rx_task = asyncio.create_task(self._receive(self._reader), name="can-receive")
        log.info("event=bus_open bus=%s authenticated=%s", self.bus_cfg.describe(), self.auth is not None)

    def _on_bus_error(self, exc: Exception) -> None:
        """The notifier's receive thread failed (called on the loop): the supervisor reopens the bus."""
        self._bus_error = f"{type(exc).__name__}: {exc}"
        log.warning("event=bus_error bus=%s reason=%s", self.bus_cfg.describe(), self._bus_error)

    def _close_bus(self) -> None:
        if self._notifier is not None:
            try:
                self._notifier.stop(timeout=0.5)
            except Exception:
                pass
        if self._bus is not None:
            try:
                self._bus.shutdown()
            except Exception:                     # a hub that went away fails its close handshake
                pass
        self._notifier = self._bus = None

    async def _supervisor(self, aio) -> None:
        """Reopens a failed bus and logs the link going down and coming back."""
        while True:
            await asyncio.sleep(self.reconnect_s / 5)
            if self._bus_error is not None:
                self._close_bus()
                try:
                    await self._open(aio)
                    self.reconnects += 1
                except OSError as exc:
                    log.debug("event=reopen_failed reason=%s", exc)
                    await asyncio.sleep(self.reconnect_s)
                    continue
            up = self._bus_error is None and self._last_rx_fresh()
            if up != self._link_up:
                self._link_up = up
                log.warning("event=%s bus=%s", "link_restored" if up else "link_lost", self.bus_cfg.describe())

    def _last_rx_fresh(self) -> bool:
        return self._last_rx_ns is not None and time.monotonic_ns() - self._last_rx_ns <= self.state_timeout * 1e9

    def _transmit(self, accel: float, steer: float, *, enable: bool) -> None:
        if self._bus is None or self._bus_error is not None:
            return
        frame = self.codec.encode("VehicleCmd", {"AccelCmd": accel, "SteerAngleCmd": steer, "Enable": int(enable),
                                                 "AliveCounter": self._counter.take()})
        frame.timestamp = time.time()
        frames = [frame]
        if self._auth_tx is not None:
            frames.append(self._auth_tx.protect(frame))
            frames[1].timestamp = frame.timestamp
            self._auth_rx.raise_floor(self._cmd_id, self._auth_tx.freshness(self._cmd_id))
        try:
            for f in frames:
                self._bus.send(f)
        except Exception as exc:                 # python-can and the remote hub raise their own types
            self.send_failures += 1
            self._bus_error = f"send failed: {type(exc).__name__}: {exc}"
            return
        self.frames_sent += 1
        if self._logger is not None:
            for f in frames:
                self._logger.on_message_received(f)

    async def _cyclic_sender(self) -> None:
        """VehicleCmd at its cycle time: the fresh command between ticks, or the safe action."""
        next_t = time.monotonic()
        while True:
            next_t += self.cycle_s
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            if self.failsafe_reason is not None:
                self._brake()
            elif self._command is not None and time.monotonic_ns() - self._command_ns <= self.command_hold * 1e9:
                if time.monotonic_ns() - self._command_ns >= self.cycle_s * 1e9 * 0.5:
                    self._transmit(*self._command, enable=True)

    def _brake(self) -> None:
        if self.at_rest:
            self._transmit(0.0, 0.0, enable=False)           # the ECU holds the vehicle in ready
        else:
            steer = float(self._parts.get("VehicleStatus", ({}, 0))[0].get("SteerAngle", 0.0))
            self._transmit(self.limits.a_min, steer, enable=True)

    # ------------------------------------------------------------------ receive
    async def _receive(self, reader: can.AsyncBufferedReader) -> None:
        async for msg in reader:
            try:
                if self._auth_rx is not None:
                    msg = self._auth_rx.feed(msg)
                    if msg is None:
                        continue
                frame = self.codec.decode(msg)
            except FrameError as exc:
                self._count_bad(exc.kind, str(exc))
                continue
            except Exception as exc:           # nothing on the bus may stop the receiver
                self.undecodable += 1
                log.warning("event=undecodable_frame id=0x%X reason=%s", msg.arbitration_id, exc)
                continue
            self._take(frame.name, frame.signals)

    def _count_bad(self, kind: str, detail: str) -> None:
        self.bad_frames[kind] += 1
        if sum(self.bad_frames.values()) in (1, 10, 100, 1000, 10000):
            log.warning("event=bad_frames counts=%s last=%s", self.bad_frames, detail)

    def _on_auth_reject(self, exc: AuthError) -> None:
        name = self._names[exc.frame_id]
        self.auth_rejected[name] += 1
        if name in INS:
            self._ins_rejected += 1
        self._count_bad(exc.kind, str(exc))

    def _take(self, name: str, signals: dict) -> None:
        now = time.monotonic_ns()
        if name.endswith(AUTH_SUFFIX):             # the plain profile: another node's authentication PDUs
            return
        if name == "VehicleCmd":                   # the bus does not echo our own: another node commands
            self.foreign_commands += 1
            self._foreign_ns = now
            if self.foreign_commands in (1, 10, 100, 1000, 10000):
                log.warning("event=foreign_command count=%d", self.foreign_commands)
            return
        if name == "InsHeadingVelocity" and not self._ins_counter.accept(signals["AliveCounter"]):
            self._count_bad("counter", f"InsHeadingVelocity counter {signals['AliveCounter']}")
            return
        self.frames_ok += 1
        self._parts[name] = (signals, now)
        if name == "VehicleStatus":
            self.ecu_mode = MODES.get(int(signals["Mode"]), "unknown")
            self.ecu_faults = {k: int(v) for k, v in signals.items() if k.startswith("Fault")}
            self._speed = float(signals["Speed"])
        elif name == "InsHeadingVelocity":
            self._last_rx_ns = now
            self._ins_rejected = 0
            self._assemble()

    def _assemble(self) -> None:
        try:
            (pos, t_pos), (hv, t_hv), (st, t_st) = (self._parts[n] for n in
                                                    ("InsPosition", "InsHeadingVelocity", "VehicleStatus"))
        except KeyError:
            return
        x = np.array([pos["PosX"], pos["PosY"], hv["Heading"], hv["VelX"], hv["VelY"], st["YawRate"]])
        self._latest = StampedState(x, min(t_pos, t_hv, t_st))


def can_vehicle_from_scenario(scenario, options: dict, file=None, bus_log_stem: Path | None = None) -> CanVehicle:
    """The CAN vehicle of a mission. ``options``: the mission's [platform] table without ``kind``
    (interface, channel, dbc, state_timeout, command_hold, bus_log, auth_key, auth_clock_skew);
    ``bus_log_stem``: the flight log's path, whose suffix becomes ``bus_log``'s."""
    from vflpcd.config.vehicles import BicycleConfig
    from vflpcd.base.tomlread import Table

    t = Table(options, file, "platform")
    t.check_known({"interface", "channel", "dbc", "state_timeout", "command_hold", "bus_log", "auth_key",
                   "auth_clock_skew"})
    bus = bus_config(t)
    dbc = t.string("dbc", "")
    try:
        codec = VehicleCan(_resolve(dbc, file) if dbc else None)
    except Exception as exc:                     # cantools raises its own parse errors
        raise t.error("dbc", f"cannot load the CAN database: {exc}") from None
    missing = set(LINK_MESSAGES) - {m.name for m in codec.db.messages}
    if missing:
        raise t.error("dbc", f"the CAN database lacks {', '.join(sorted(missing))}")
    uncycled = [n for n in LINK_MESSAGES if not (codec.message(n).cycle_time or 0) > 0]
    if uncycled:
        raise t.error("dbc", f"the CAN database gives no cycle time (GenMsgCycleTime) for {', '.join(uncycled)}")
    auth = auth_config(t, file)
    if auth is not None:
        try:
            secured_ids(codec.db, LINK_MESSAGES)
        except ValueError as exc:
            raise t.error("dbc", str(exc)) from None
    fmt = t.string("bus_log", "asc", choices=BUS_LOG_FORMATS)
    log_file = bus_log_stem.with_suffix(f".{fmt}") if fmt and bus_log_stem is not None else None
    return CanVehicle(bus, BicycleConfig.load(scenario.params).limits, codec,
                      state_timeout=t.number("state_timeout", 0.1, min=0.02, max=5.0),
                      command_hold=t.number("command_hold", 0.1, min=0.02, max=1.0), bus_log=log_file, auth=auth)


def _resolve(name: str, mission_file) -> Path:
    path = Path(name).expanduser()
    if not path.is_absolute() and mission_file is not None:
        beside = Path(mission_file).parent / path
        if beside.exists():
            return beside
    if not path.exists():
        from vflpcd.base.paths import config_dir

        candidate = config_dir() / "can" / path
        if candidate.exists():
            return candidate
    return path
