"""``vflpcd sitl quad``: a PX4-like quadrotor autopilot over MAVLink 2 / UDP (software in the loop).

The quadrotor plant (``sim.plants.quadrotor``, ENU world, FLU body) runs in real time behind an
autopilot that speaks to a ground station as PX4 SITL does: it sends from its own port to the
station's listening port (``udpout``; MAVSDK listens with ``udpin://HOST:PORT``) as system 1,
component 1, and answers on the same socket.

- HEARTBEAT (1 Hz and on every change): MAV_TYPE_QUADROTOR, MAV_AUTOPILOT_PX4, base_mode
  CUSTOM_MODE_ENABLED | SAFETY_ARMED when armed, custom_mode = (sub << 24) | (main << 16) with
  PX4's modes (``sim.sitl.quad_modes``: AUTO.LOITER at boot, AUTO.TAKEOFF, AUTO.LAND, AUTO.RTL,
  POSCTL, ALTCTL, OFFBOARD = main 6).
- Commands (COMMAND_LONG / COMMAND_INT, each answered by COMMAND_ACK to its sender): arm/disarm
  (400; disarm refused in the air unless forced with 21196; arming sets home where it stands),
  take-off (22: climb to MIS_TAKEOFF_ALT at MPC_TKO_SPEED, then AUTO.LOITER), land (21: descend at
  MPC_LAND_SPEED, then disarm 1 s after touchdown), return (20, or AUTO.RTL by mode), DO_SET_MODE
  (176; SET_MODE is taken as this command and ACKed as it, as PX4 does): OFFBOARD only when armed
  and a setpoint is fresh, AUTO.RTL only in the air, AUTO.LOITER, AUTO.LAND, POSCTL and ALTCTL
  (both hold where they were entered); AUTO.MISSION, MANUAL, STABILIZED, ACRO and the rest are
  UNSUPPORTED. REQUEST_MESSAGE (512), GET_HOME_POSITION (410), REQUEST_AUTOPILOT_CAPABILITIES
  (520), SET_MESSAGE_INTERVAL (511), their unused parameters NaN or not; other commands
  UNSUPPORTED. Every command or mode change it refuses is followed by a STATUSTEXT (warning)
  saying why.
- Return (AUTO.RTL): climb where it is to RTL_RETURN_ALT above home (or stay at its altitude if
  higher) until within NAV_MC_ALT_RAD of it, fly level to home (the position loop's at most 2 m/s
  per axis) until within NAV_ACC_RAD, then descend at MPC_LAND_SPEED (EXTENDED_SYS_STATE: landing)
  onto home and disarm 1 s after touchdown, as PX4 does; each phase is announced by STATUSTEXT.
- Telemetry: LOCAL_POSITION_NED, ATTITUDE, ATTITUDE_QUATERNION at ``telemetry_rate_hz`` (or the
  interval a station set), SYS_STATUS (sensor and pre-arm bits; errors_comm = malformed frames)
  and EXTENDED_SYS_STATE at 2 Hz, GLOBAL_POSITION_INT at 5 Hz, HOME_POSITION on request (and
  once a second until asked) and on arming, AUTOPILOT_VERSION on request, STATUSTEXT on events.
- Missions: none. MISSION_REQUEST_LIST is answered by MISSION_COUNT 0, an upload (MISSION_COUNT)
  by MISSION_ACK MAV_MISSION_UNSUPPORTED and a STATUSTEXT.
- Parameters (PARAM_REQUEST_LIST / _READ / PARAM_SET; int32 values carried bytewise in the float
  field as PX4 does): ``PARAMS`` below. A value out of range is refused: the current value is
  echoed.
- Offboard: SET_POSITION_TARGET_LOCAL_NED in LOCAL_NED with type mask 3135 (acceleration) or 2503
  (velocity + yaw); anything else is rejected and counted. Offboard loss (no setpoint for
  COM_OF_LOSS_T): COM_OBL_ACT 1 holds (AUTO.LOITER) for NAV_OBL_HOLD_T s, then lands; 0 lands.

Everything runs on one thread: physics on absolute deadlines at ``physics_rate_hz``, ``select``
on the socket in between. Malformed input (random bytes, bad CRC, truncated frames, unknown ids,
frames that make the parser raise) is counted and never stops the loop.
"""

from __future__ import annotations

import json
import logging
import math
import os
import select
import signal
import struct
import threading
import time

import numpy as np

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402  (MAVLink 2 must be chosen before the import)

from drivers.ned_enu import attitude_enu_to_ned, enu_to_ned, flu_to_frd, ned_to_enu, quat_to_rot, yaw_ned_to_enu  # noqa: E402
from sim.sitl.quad_modes import (NO_MISSIONS, STATUSTEXT_LEN, Return, custom_mode, requested_mode,  # noqa: E402
                                 split_custom_mode)

log = logging.getLogger("sim.sitl.quad")
mav = mavutil.mavlink

ON_GROUND, IN_AIR, TAKEOFF, LANDING = 1, 2, 3, 4
MASK_ACCEL, MASK_VELOCITY = 3135, 2503
FORCE_DISARM = 21196
# the position loop of the hold, take-off, land and return modes: v_des = POSITION_GAIN (target - p),
# each axis within SPEED_MAX m/s (the climb of a take-off within MPC_TKO_SPEED, a descent at
# MPC_LAND_SPEED), then a = VELOCITY_GAIN (v_des - v) (damping ratio 0.71); OFFBOARD's velocity
# setpoints go through the same velocity loop
POSITION_GAIN, VELOCITY_GAIN, SPEED_MAX = 2.0, 4.0, 2.0
SENSORS = 0x1 | 0x2 | 0x4 | 0x8 | 0x20
PREARM = 0x10000000
FLOAT, INT32 = mav.MAV_PARAM_TYPE_REAL32, mav.MAV_PARAM_TYPE_INT32
# name: (default, type, minimum, maximum): PX4's names, ranges and defaults, but NAV_ACC_RAD's 0.5 m
# (PX4: 10 m): the return's descent begins within it of home
PARAMS = {"MIS_TAKEOFF_ALT": (2.5, FLOAT, 0.5, 100.0), "MPC_TKO_SPEED": (1.5, FLOAT, 0.3, 5.0),
          "MPC_LAND_SPEED": (0.7, FLOAT, 0.2, 3.0), "COM_OF_LOSS_T": (1.0, FLOAT, 0.1, 60.0),
          "COM_OBL_ACT": (1, INT32, 0, 1), "NAV_OBL_HOLD_T": (5.0, FLOAT, 0.0, 600.0),
          "RTL_RETURN_ALT": (60.0, FLOAT, 0.0, 150.0), "NAV_MC_ALT_RAD": (0.8, FLOAT, 0.05, 200.0),
          "NAV_ACC_RAD": (0.5, FLOAT, 0.05, 200.0)}
STREAMS = (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION)


def check_param(name: str, value) -> float:
    """``value`` as the parameter's type (ValueError naming it when unknown, non-finite or out of range)."""
    if name not in PARAMS:
        raise ValueError(f"unknown parameter {name!r} (known: {', '.join(PARAMS)})")
    _, ptype, lo, hi = PARAMS[name]
    v = float(value)
    if not math.isfinite(v) or not (lo <= v <= hi) or (ptype == INT32 and v != int(v)):
        raise ValueError(f"parameter {name} must be {'an integer' if ptype == INT32 else 'a number'} in "
                         f"[{lo:g}, {hi:g}], got {value!r}")
    return int(v) if ptype == INT32 else v


def _wire(value, ptype) -> float:
    """A parameter value in PARAM_VALUE's float field (int32: bytewise, as PX4)."""
    return struct.unpack("<f", struct.pack("<i", int(value)))[0] if ptype == INT32 else float(value)


def _unwire(raw: float, ptype):
    return struct.unpack("<i", struct.pack("<f", raw))[0] if ptype == INT32 else float(raw)


class QuadSitl:
    """The autopilot; ``gcs_port`` is the station's listening port, ``yaw_deg`` the start heading
    (NED, degrees: 90 faces east = ENU yaw 0), ``home`` (lat, lon, alt) the geodetic home."""

    def __init__(self, gcs_host: str = "127.0.0.1", gcs_port: int = 14540, *, physics_rate_hz: float = 250.0,
                 telemetry_rate_hz: float = 100.0, yaw_deg: float = 90.0, params: dict | None = None,
                 home=(47.397742, 8.545594, 488.0)) -> None:
        from sim.plants.quadrotor import Quadrotor
        from vflpcd.config.vehicles import QuadrotorParams

        self.plant = Quadrotor(QuadrotorParams.from_toml(),
                               np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, yaw_ned_to_enu(math.radians(yaw_deg))]))
        self.accel_max = self.plant.params.accel_max
        self.conn = mavutil.mavlink_connection(f"udpout:{gcs_host}:{gcs_port}", source_system=1, source_component=1,
                                               dialect="common")
        self.conn.mav.robust_parsing = True
        self.dt = 1.0 / physics_rate_hz
        self.home = tuple(float(v) for v in home)
        self.params = {name: spec[0] for name, spec in PARAMS.items()}
        for name, value in (params or {}).items():
            self.params[name] = check_param(name, value)
        default_interval = 1.0 / telemetry_rate_hz
        self.intervals = {mid: default_interval for mid in STREAMS}
        self.intervals.update({mav.MAVLINK_MSG_ID_SYS_STATUS: 0.5, mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 0.5,
                               mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 0.2, mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
                               mav.MAVLINK_MSG_ID_HOME_POSITION: 1.0})
        self._due = dict.fromkeys(self.intervals, 0.0)
        self.armed = False
        self._mode = "AUTO.LOITER"
        self.landed_state = ON_GROUND
        self._setpoint: tuple[str, np.ndarray, float, float] | None = None     # kind, NED vector, yaw, arrival
        self._target = np.zeros(3)
        self._home_enu = np.zeros(3)                    # where it was last armed (at boot: the origin)
        self._return: Return | None = None
        self._obl_land_at: float | None = None
        self._touchdown_at: float | None = None
        self._home_requested = False
        self._t0 = time.monotonic()
        self._warned = 0.0
        self.counts = {"frames_ok": 0, "malformed": 0, "rejected_setpoints": 0, "rejected_commands": 0,
                       "wrong_target": 0, "rejected_params": 0, "offboard_losses": 0, "setpoints": 0}
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ public
    def start(self) -> None:
        self._thread = threading.Thread(target=self.serve_forever, args=(self._stop,), name="sitl-quad", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        self.conn.close()

    def stats(self) -> dict:
        return {**self.counts, "mode": self.mode, "armed": self.armed, "landed_state": self.landed_state}

    @property
    def mode(self) -> str:
        return self._mode

    @property
    def position(self) -> np.ndarray:
        return self.plant.position()

    @property
    def in_air(self) -> bool:
        return self.landed_state != ON_GROUND

    # ------------------------------------------------------------------ loop
    def serve_forever(self, stop: threading.Event) -> None:
        period = int(self.dt * 1e9)
        next_step = time.monotonic_ns()
        sock = self.conn.port
        while not stop.is_set():
            now = time.monotonic_ns()
            while next_step <= now:
                self._step(self.dt)
                next_step += period
            self._send_due(time.monotonic())
            wait = max(0.0, (next_step - time.monotonic_ns()) * 1e-9)
            readable, _, _ = select.select([sock], [], [], wait)
            if readable:
                self._drain(sock)

    def _drain(self, sock) -> None:
        for _ in range(64):                                # bounded: physics must not starve
            try:
                data = sock.recv(65535)
            except BlockingIOError:
                return
            except OSError:                                # e.g. ICMP port unreachable from a gone station
                return
            self._on_datagram(data)

    def _on_datagram(self, data: bytes) -> None:
        parser = self.conn.mav
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:
            msgs = []
            self._malformed("parser raised")
        if len(parser.buf) - parser.buf_index > 0:           # a truncated frame: drop its bytes
            parser.buf, parser.buf_index = bytearray(), 0
            parser.expected_length = mav.HEADER_LEN_V1 if hasattr(mav, "HEADER_LEN_V1") else 6
            self._malformed("truncated frame")
        for msg in msgs:
            kind = msg.get_type()
            if kind == "BAD_DATA" or kind.startswith("UNKNOWN"):
                self._malformed(kind)
                continue
            try:
                self._on_message(msg, kind)
            except Exception as exc:
                self._malformed(f"{kind}: {type(exc).__name__}: {exc}")

    def _malformed(self, what: str) -> None:
        self.counts["malformed"] += 1
        now = time.monotonic()
        if now - self._warned >= 1.0:
            self._warned = now
            log.warning("event=malformed_input count=%d last=%s", self.counts["malformed"], what)

    # ------------------------------------------------------------------ messages
    def _on_message(self, msg, kind: str) -> None:
        target = getattr(msg, "target_system", 0)
        if target not in (0, 1):
            self.counts["wrong_target"] += 1
            return
        self.counts["frames_ok"] += 1
        if kind in ("COMMAND_LONG", "COMMAND_INT"):
            self._on_command(msg, kind)
        elif kind == "SET_MODE":                            # PX4 takes it as DO_SET_MODE and ACKs that
            main, sub = split_custom_mode(int(msg.custom_mode))
            self._command(mav.MAV_CMD_DO_SET_MODE, [float(msg.base_mode), float(main), float(sub)] + [0.0] * 4, msg)
        elif kind == "SET_POSITION_TARGET_LOCAL_NED":
            self._on_setpoint(msg)
        elif kind == "MISSION_REQUEST_LIST":                # no mission: an empty list, as PX4 without one
            self.conn.mav.mission_count_send(msg.get_srcSystem(), msg.get_srcComponent(), 0, msg.mission_type)
        elif kind == "MISSION_COUNT":                       # an upload: refused
            self.conn.mav.mission_ack_send(msg.get_srcSystem(), msg.get_srcComponent(), mav.MAV_MISSION_UNSUPPORTED,
                                           msg.mission_type)
            self._statustext(mav.MAV_SEVERITY_WARNING, f"upload: {NO_MISSIONS}")
        elif kind == "PARAM_REQUEST_LIST":
            for i, name in enumerate(PARAMS):
                self._param_value(name, i)
        elif kind == "PARAM_REQUEST_READ":
            self._on_param_read(msg)
        elif kind == "PARAM_SET":
            self._on_param_set(msg)

    def _on_command(self, msg, kind: str) -> None:
        p = [msg.param1, msg.param2, msg.param3, msg.param4]
        if kind == "COMMAND_LONG":
            p += [msg.param5, msg.param6, msg.param7]
        else:
            p += [msg.x, msg.y, msg.z]
        self._command(msg.command, p, msg)

    def _command(self, cmd: int, p: list, msg) -> None:
        """Decide, apply, ACK to the sender, then send what was asked for, or why it was refused."""
        result, reason = self._command_result(cmd, p)
        if result == mav.MAV_RESULT_ACCEPTED:
            self._apply(cmd, p)                    # the state changes before the ACK leaves
        else:
            self.counts["rejected_commands"] += 1
            log.info("event=command_rejected command=%d result=%d reason=%r", cmd, result, reason)
        self.conn.mav.command_ack_send(cmd, result, 0, 0, msg.get_srcSystem(), msg.get_srcComponent())
        if result == mav.MAV_RESULT_ACCEPTED:
            self._respond(cmd, p)                  # requested messages follow their ACK
        else:
            self._statustext(mav.MAV_SEVERITY_WARNING, reason)

    def _command_result(self, cmd: int, p: list) -> tuple[int, str]:
        """(MAV_RESULT, the reason when it is not ACCEPTED)."""
        denied, accepted = mav.MAV_RESULT_DENIED, (mav.MAV_RESULT_ACCEPTED, "")
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            if not math.isfinite(p[0]):
                return denied, "arm/disarm denied: param1 is not a number"
            if p[0] >= 0.5 or not self.in_air or p[1] == FORCE_DISARM:
                return accepted
            return denied, "disarm denied: in the air"
        if cmd == mav.MAV_CMD_NAV_TAKEOFF:
            return accepted if self.armed else (denied, "take-off denied: not armed")
        if cmd == mav.MAV_CMD_NAV_LAND:
            return accepted
        if cmd == mav.MAV_CMD_DO_SET_MODE:
            if not all(math.isfinite(v) for v in p[:3]):
                return denied, "mode change denied: a parameter is not a number"
            mode, reason = requested_mode(int(p[0]), int(p[1]), int(p[2]))
            if mode is None:
                return mav.MAV_RESULT_UNSUPPORTED, reason
            return self._mode_result(mode)
        if cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self._mode_result("AUTO.RTL")
        if cmd == mav.MAV_CMD_GET_HOME_POSITION:
            return accepted
        if cmd in (mav.MAV_CMD_REQUEST_MESSAGE, mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                   mav.MAV_CMD_SET_MESSAGE_INTERVAL):          # the unused parameters may be NaN (MAVSDK's are)
            used = 2 if cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL else 1
            if not all(math.isfinite(v) for v in p[:used]):
                return denied, "request denied: a parameter is not a number"
            return accepted
        return mav.MAV_RESULT_UNSUPPORTED, f"command {cmd} not supported by this SITL"

    def _mode_result(self, mode: str) -> tuple[int, str]:
        """Whether a mode it flies may be entered now."""
        if mode == "OFFBOARD" and not self.armed:
            return mav.MAV_RESULT_DENIED, "OFFBOARD denied: not armed"
        if mode == "OFFBOARD" and not self._setpoint_fresh(time.monotonic()):
            return mav.MAV_RESULT_DENIED, "OFFBOARD denied: no fresh setpoint"
        if mode == "AUTO.RTL" and not (self.armed and self.in_air):
            return mav.MAV_RESULT_DENIED, "RTL denied: not in the air"
        return mav.MAV_RESULT_ACCEPTED, ""

    def _apply(self, cmd: int, p: list) -> None:
        if cmd == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            self._set_armed(p[0] >= 0.5)
        elif cmd == mav.MAV_CMD_NAV_TAKEOFF:
            alt = p[6] if math.isfinite(p[6]) and p[6] > 0 else self.params["MIS_TAKEOFF_ALT"]
            pos = self.plant.position()
            self._target = np.array([pos[0], pos[1], alt])
            self._return = None
            self.landed_state = TAKEOFF
            self._set_mode("AUTO.TAKEOFF")
        elif cmd == mav.MAV_CMD_NAV_LAND:
            self._land()
        elif cmd == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            self._rtl()
        elif cmd == mav.MAV_CMD_DO_SET_MODE:
            mode, _ = requested_mode(int(p[0]), int(p[1]), int(p[2]))
            if mode == "OFFBOARD":
                self._offboard()
            elif mode == "AUTO.LAND":
                self._land()
            elif mode == "AUTO.RTL":
                self._rtl()
            else:                                  # AUTO.LOITER, POSCTL, ALTCTL: hold here
                self._hold(mode)
        elif cmd == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            self._set_interval(int(p[0]), p[1])

    def _respond(self, cmd: int, p: list) -> None:
        if cmd == mav.MAV_CMD_REQUEST_MESSAGE:
            self._send_requested(int(p[0]))
        elif cmd == mav.MAV_CMD_GET_HOME_POSITION:
            self._send_requested(mav.MAVLINK_MSG_ID_HOME_POSITION)
        elif cmd == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._send_requested(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)

    def _set_interval(self, msg_id: int, interval_us: float) -> None:
        if msg_id not in self.intervals:
            return
        if interval_us < 0:
            self.intervals[msg_id] = math.inf
        elif interval_us > 0:
            self.intervals[msg_id] = min(max(interval_us * 1e-6, 1.0 / 250.0), 1.0)

    def _on_setpoint(self, m) -> None:
        values = (m.vx, m.vy, m.vz, m.afx, m.afy, m.afz, m.yaw)
        if m.coordinate_frame != mav.MAV_FRAME_LOCAL_NED or m.type_mask not in (MASK_ACCEL, MASK_VELOCITY) \
                or not all(math.isfinite(v) for v in values):
            self.counts["rejected_setpoints"] += 1
            return
        if m.type_mask == MASK_ACCEL:
            self._setpoint = ("accel", np.array([m.afx, m.afy, m.afz]), 0.0, time.monotonic())
        else:
            self._setpoint = ("velocity", np.array([m.vx, m.vy, m.vz]), float(m.yaw), time.monotonic())
        self.counts["setpoints"] += 1

    def _on_param_read(self, m) -> None:
        name = m.param_id.rstrip("\x00") if isinstance(m.param_id, str) else m.param_id
        names = list(PARAMS)
        if m.param_index >= 0:
            if m.param_index < len(names):
                self._param_value(names[m.param_index], m.param_index)
            return
        if name in PARAMS:
            self._param_value(name, names.index(name))
        else:
            self.counts["rejected_params"] += 1

    def _on_param_set(self, m) -> None:
        name = m.param_id.rstrip("\x00")
        if name not in PARAMS:
            self.counts["rejected_params"] += 1
            return
        try:
            self.params[name] = check_param(name, _unwire(m.param_value, PARAMS[name][1]))
        except (ValueError, struct.error) as exc:
            self.counts["rejected_params"] += 1
            log.warning("event=param_rejected reason=%s", exc)
        self._param_value(name, list(PARAMS).index(name))

    def _param_value(self, name: str, index: int) -> None:
        ptype = PARAMS[name][1]
        self.conn.mav.param_value_send(name.encode(), _wire(self.params[name], ptype), ptype, len(PARAMS), index)

    # ------------------------------------------------------------------ modes
    def _set_mode(self, mode: str) -> None:
        if mode != self._mode:
            self._mode = mode
            log.info("event=mode mode=%s", mode)
            self._statustext(mav.MAV_SEVERITY_INFO, f"mode {mode}")
            self._heartbeat()

    def _set_armed(self, armed: bool) -> None:
        if armed != self.armed:
            self.armed = armed
            if armed:
                self._home_enu = self.plant.position().copy()        # home is where it is armed, as in PX4
            else:
                self.landed_state = ON_GROUND
                self._touchdown_at = None
            log.info("event=%s", "armed" if armed else "disarmed")
            self._statustext(mav.MAV_SEVERITY_INFO, "armed" if armed else "disarmed")
            self._heartbeat()
            if armed:
                self._send_message(mav.MAVLINK_MSG_ID_HOME_POSITION)

    def _flying(self, mode: str, target) -> None:
        """Enter ``mode`` flying to ``target`` (ENU): a landing or a return under way ends."""
        self._target = np.array(target, dtype=float)
        self._return = None
        if self.in_air:
            self.landed_state = IN_AIR
        self._set_mode(mode)

    def _hold(self, mode: str = "AUTO.LOITER") -> None:
        self._obl_land_at = None
        self._flying(mode, self.plant.position())

    def _offboard(self) -> None:
        self._flying("OFFBOARD", self.plant.position())

    def _land(self) -> None:
        self._target = self.plant.position().copy()
        self._return = None
        if self.in_air:
            self.landed_state = LANDING
        self._set_mode("AUTO.LAND")

    def _rtl(self) -> None:
        self._obl_land_at = None
        ret = Return(self.plant.position(), self._home_enu, return_alt=self.params["RTL_RETURN_ALT"],
                     alt_radius=self.params["NAV_MC_ALT_RAD"], xy_radius=self.params["NAV_ACC_RAD"])
        self._flying("AUTO.RTL", ret.target())
        self._return = ret
        self._statustext(mav.MAV_SEVERITY_INFO, f"RTL: climb to {ret.altitude:.1f} m")
        self._follow_return()

    def _follow_return(self) -> None:
        ret = self._return
        if ret is None or not ret.advance(self.plant.position()):
            return
        self._target = ret.target()
        log.info("event=rtl_phase phase=%s", ret.phase)
        if ret.phase == Return.DESCEND:
            self.landed_state = LANDING
            self._statustext(mav.MAV_SEVERITY_INFO, "RTL: landing at home")
        else:
            self._statustext(mav.MAV_SEVERITY_INFO, "RTL: flying home")

    def _setpoint_fresh(self, now: float) -> bool:
        return self._setpoint is not None and now - self._setpoint[3] <= self.params["COM_OF_LOSS_T"]

    # ------------------------------------------------------------------ physics
    def _step(self, dt: float) -> None:
        now = time.monotonic()
        self._supervise(now)
        if not self.armed or self.landed_state == ON_GROUND:
            return                                          # on the ground: motors idle, nothing moves
        self.plant.step(self._acceleration(now), dt)
        p = self.plant.position()
        if p[2] <= 0.0 or (self.landed_state == LANDING and p[2] <= 0.05):
            self._touchdown(p)

    def _supervise(self, now: float) -> None:
        if self._mode == "OFFBOARD" and not self._setpoint_fresh(now):
            self.counts["offboard_losses"] += 1
            log.warning("event=offboard_lost action=%s", "hold_then_land" if self.params["COM_OBL_ACT"] else "land")
            self._statustext(mav.MAV_SEVERITY_WARNING, "Offboard lost: hold, then land"
                             if self.params["COM_OBL_ACT"] else "Offboard lost: land")
            if self.params["COM_OBL_ACT"]:
                self._hold()
                self._obl_land_at = now + self.params["NAV_OBL_HOLD_T"]
            else:
                self._land()
        if self._obl_land_at is not None and now >= self._obl_land_at and self._mode == "AUTO.LOITER":
            self._obl_land_at = None
            self._land()
        if self._mode == "AUTO.TAKEOFF" and abs(self.plant.position()[2] - self._target[2]) < 0.05 \
                and abs(self.plant.velocity_world()[2]) < 0.1:
            self.landed_state = IN_AIR
            self._hold()
        if self._mode == "AUTO.RTL" and self.landed_state == IN_AIR:          # climbing or flying back
            self._follow_return()
        if self._touchdown_at is not None and now - self._touchdown_at >= 1.0 and self.armed:
            self._set_armed(False)

    def _touchdown(self, p) -> None:
        self.plant.reset(np.array([p[0], p[1], 0.0, 0.0, 0.0, 0.0, self.plant.heading()]))
        self.landed_state = ON_GROUND
        if self._touchdown_at is None:
            self._touchdown_at = time.monotonic()
            log.info("event=touchdown x=%.2f y=%.2f", p[0], p[1])
            self._statustext(mav.MAV_SEVERITY_INFO, "landed")

    def _acceleration(self, now: float) -> np.ndarray:
        """The ENU acceleration command of the current mode."""
        p, v = self.plant.position(), self.plant.velocity_world()
        if self._mode == "OFFBOARD" and self._setpoint is not None:
            kind, vec, yaw, _ = self._setpoint
            if kind == "accel":
                a = ned_to_enu(vec)
            else:
                a = VELOCITY_GAIN * (ned_to_enu(vec) - v)
                self.plant.set_yaw_setpoint(yaw_ned_to_enu(yaw))
            return self._clip(a)
        v_des = np.clip(POSITION_GAIN * (self._target - p), -SPEED_MAX, SPEED_MAX)
        if self._mode == "AUTO.TAKEOFF":                       # climbs at MPC_TKO_SPEED, whatever SPEED_MAX
            v_des[2] = min(POSITION_GAIN * (self._target[2] - p[2]), self.params["MPC_TKO_SPEED"])
        elif self.landed_state == LANDING:                     # AUTO.LAND, and AUTO.RTL's descent
            v_des[2] = -self.params["MPC_LAND_SPEED"]
        return self._clip(VELOCITY_GAIN * (v_des - v))

    def _clip(self, a: np.ndarray) -> np.ndarray:
        n = float(np.linalg.norm(a))
        return a * (self.accel_max / n) if n > self.accel_max else a

    # ------------------------------------------------------------------ telemetry
    def _send_due(self, now: float) -> None:
        for msg_id, interval in self.intervals.items():
            if now >= self._due[msg_id]:
                self._due[msg_id] = now + interval
                if msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION and self._home_requested:
                    continue
                self._send_message(msg_id)

    def _send_requested(self, msg_id: int) -> None:
        if msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION:
            self._home_requested = True
        self._send_message(msg_id)

    def _send_message(self, msg_id: int) -> None:
        m = self.conn.mav
        t_ms = int((time.monotonic() - self._t0) * 1000) & 0xFFFFFFFF
        x = self.plant.state
        if msg_id == mav.MAVLINK_MSG_ID_HEARTBEAT:
            self._heartbeat()
        elif msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            n, e, d = enu_to_ned(x[0:3])
            vn, ve, vd = enu_to_ned(x[3:6])
            m.local_position_ned_send(t_ms, n, e, d, vn, ve, vd)
        elif msg_id in (mav.MAVLINK_MSG_ID_ATTITUDE, mav.MAVLINK_MSG_ID_ATTITUDE_QUATERNION):
            q = attitude_enu_to_ned(x[6:10])
            rates = flu_to_frd(x[10:13])
            if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
                R = quat_to_rot(q)
                roll, pitch = math.atan2(R[2, 1], R[2, 2]), -math.asin(max(-1.0, min(1.0, R[2, 0])))
                m.attitude_send(t_ms, roll, pitch, math.atan2(R[1, 0], R[0, 0]), *rates)
            else:
                m.attitude_quaternion_send(t_ms, *q, *rates)
        elif msg_id == mav.MAVLINK_MSG_ID_SYS_STATUS:
            bits = SENSORS | (PREARM if self._armable() else 0)
            m.sys_status_send(bits, bits, bits, 200, 16000, -1, 90, 0, min(self.counts["malformed"], 65535), 0, 0, 0, 0)
        elif msg_id == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            m.extended_sys_state_send(0, self.landed_state)
        elif msg_id == mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            lat, lon, alt = self._geodetic(x[0:3])
            n, e, d = enu_to_ned(x[3:6])
            hdg = int(math.degrees(yaw_ned_to_enu(self.plant.heading())) % 360 * 100)
            m.global_position_int_send(t_ms, lat, lon, int(alt * 1000), int(x[2] * 1000), int(n * 100), int(e * 100),
                                       int(d * 100), hdg)
        elif msg_id == mav.MAVLINK_MSG_ID_HOME_POSITION:
            lat, lon, alt = self._geodetic(self._home_enu)
            m.home_position_send(lat, lon, int(alt * 1000), *enu_to_ned(self._home_enu), [1.0, 0.0, 0.0, 0.0],
                                 0.0, 0.0, 0.0)
        elif msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            caps = (mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2 | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                    | mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
                    | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT)
            m.autopilot_version_send(caps, 0x010E0000, 0, 0, 0, bytes(8), bytes(8), bytes(8), 0, 0, 0x5154)

    def _heartbeat(self) -> None:
        base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        status = mav.MAV_STATE_CRITICAL if self._obl_land_at is not None else (
            mav.MAV_STATE_ACTIVE if self.armed else mav.MAV_STATE_STANDBY)
        self.conn.mav.heartbeat_send(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, base, custom_mode(self._mode),
                                     status)

    def _statustext(self, severity: int, text: str) -> None:
        self.conn.mav.statustext_send(severity, text.encode()[:STATUSTEXT_LEN])

    def _armable(self) -> bool:
        return not self.armed

    def _geodetic(self, enu) -> tuple[int, int, float]:
        lat0, lon0, alt0 = self.home
        lat = lat0 + math.degrees(enu[1] / 6378137.0)
        lon = lon0 + math.degrees(enu[0] / (6378137.0 * math.cos(math.radians(lat0))))
        return int(lat * 1e7), int(lon * 1e7), alt0 + float(enu[2])


# ---------------------------------------------------------------------- command line
def add_arguments(p) -> None:
    p.add_argument("--host", default="127.0.0.1", help="the ground station's host (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=14540, help="the ground station's listening port (default 14540)")
    p.add_argument("--physics-rate", type=float, default=250.0, help="plant steps per second (default 250)")
    p.add_argument("--telemetry-rate", type=float, default=100.0, help="position and attitude messages per second")
    p.add_argument("--yaw-deg", type=float, default=90.0, help="start heading, NED degrees (90: facing east)")
    p.add_argument("--home", type=float, nargs=3, default=(47.397742, 8.545594, 488.0), metavar=("LAT", "LON", "ALT"))
    p.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help=f"initial parameter value (repeatable): {', '.join(PARAMS)}")
    p.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))


def run(args) -> int:
    from vflpcd.base.errors import ConfigError

    def bad(option: str, message: str) -> ConfigError:
        return ConfigError("command line", option, message)

    if not 1 <= args.port <= 65535:
        raise bad("--port", f"must lie in [1, 65535], got {args.port}")
    if not 50.0 <= args.physics_rate <= 2000.0:
        raise bad("--physics-rate", f"must lie in [50, 2000], got {args.physics_rate:g}")
    if not 1.0 <= args.telemetry_rate <= 250.0:
        raise bad("--telemetry-rate", f"must lie in [1, 250], got {args.telemetry_rate:g}")
    if not math.isfinite(args.yaw_deg):
        raise bad("--yaw-deg", "must be finite")
    params = {}
    for item in args.param:
        name, sep, value = item.partition("=")
        try:
            if not sep:
                raise ValueError(f"expected NAME=VALUE, got {item!r}")
            params[name] = check_param(name, value)
        except ValueError as exc:
            raise bad("--param", str(exc)) from None
    sitl = QuadSitl(args.host, args.port, physics_rate_hz=args.physics_rate, telemetry_rate_hz=args.telemetry_rate,
                    yaw_deg=args.yaw_deg, params=params, home=args.home)
    stop = threading.Event()
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    log.info("event=sitl_started gcs=%s:%d", args.host, args.port)
    sitl.serve_forever(stop)
    sitl.conn.close()
    print(json.dumps({"sitl_stats": sitl.stats()}), flush=True)
    return 0
