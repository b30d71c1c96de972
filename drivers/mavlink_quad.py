"""The MAVLink quadrotor: the daemon's ``Platform`` through MAVSDK 4.x (its asyncio API) over UDP.

Life cycle, as a PX4 offboard application flies it:
1. ``connect``: listen on ``url`` (``udpin://127.0.0.1:14540``: the autopilot sends to this
   port), wait for the first autopilot, subscribe to its telemetry and wait until it reports a
   usable local position and that it can be armed;
2. ``prepare``: set the take-off altitude (parameter MIS_TAKEOFF_ALT), arm, take off and wait
   until it hovers at the route's start height;
3. ``enable``: send a first (zero) acceleration setpoint, start offboard and check that the
   autopilot reports OFFBOARD;
4. ``send``: one acceleration setpoint per control tick (ENU converted to NED, its norm clipped
   to ``accel_max``), paced by the control loop;
5. ``failsafe``: hold for ``hold_s`` seconds, then land (repeated while the link is down, so an
   autopilot that comes back lands; ``event=land_commanded`` once the autopilot accepted it); on
   the ground it disarms a vehicle still armed; ``close`` lands a vehicle still in the air.
   ``at_rest``: the autopilot reports the vehicle on the ground and disarmed (the daemon waits
   for it before it exits).

State (the quadrotor plant's order: X, Y, Z, vx, vy, vz, qw, qx, qy, qz, p, q, r): position and
velocity from LOCAL_POSITION_NED, attitude from ATTITUDE_QUATERNION, body rates from ATTITUDE,
each converted from NED/FRD to ENU/FLU (``drivers.ned_enu``); ``origin`` is the ENU position of
the autopilot's local origin in the mission's frame. The stamp is the receive time of the oldest
part.

Faults (``fault()``, the daemon's link-loss failsafe): no position for ``telemetry_timeout`` s, the
autopilot reported disconnected, or it left OFFBOARD on its own (its offboard-loss failsafe, or a
pilot taking over) while the daemon commands.
"""

from __future__ import annotations

import asyncio
import logging
import time

import numpy as np

from drivers.ned_enu import attitude_ned_to_enu, enu_to_ned, frd_to_flu, ned_to_enu
from vflpcd.core.ports import PlatformBase, StampedState

log = logging.getLogger("drivers.mavlink_quad")

STATE_NAMES = ("X", "Y", "Z", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "p", "q", "r")
CONTROL_NAMES = ("ax", "ay", "az")


class MavlinkQuad(PlatformBase):
    """``url``: MAVSDK's connection URL; ``origin``: ENU position (3,) of the autopilot's local NED
    origin; ``takeoff_altitude``: m above that origin; ``accel_max``: the norm limit of an
    acceleration setpoint (m/s^2); the rest are time limits in seconds."""

    safe_action = "hold_then_land"
    prepares = True

    state_names = STATE_NAMES
    control_names = CONTROL_NAMES

    def __init__(self, url: str = "udpin://127.0.0.1:14540", *, origin=(0.0, 0.0, 0.0), takeoff_altitude: float = 2.0,
                 accel_max: float = 6.0, telemetry_timeout: float = 0.3, health_timeout: float = 20.0,
                 takeoff_timeout: float = 30.0, hold_s: float = 2.0) -> None:
        self.url = url
        self.origin = np.asarray(origin, dtype=float)
        self.takeoff_altitude, self.accel_max = float(takeoff_altitude), float(accel_max)
        self.telemetry_timeout, self.health_timeout = telemetry_timeout, health_timeout
        self.takeoff_timeout, self.hold_s = takeoff_timeout, hold_s
        self.failsafe_reason: str | None = None
        self.flight_mode: str | None = None
        self.armed: bool | None = None
        self.in_air: bool | None = None
        self.landed_state: str | None = None
        self.connected = False
        self.setpoints = 0
        self.send_failures = 0
        self.link_losses = 0
        self._mavsdk = None
        self._system = None
        self._action = self._offboard = self._telemetry = None
        self._tasks: list[asyncio.Task] = []
        self._pv: tuple[np.ndarray, int] | None = None
        self._quat: tuple[np.ndarray, int] | None = None
        self._rates: tuple[np.ndarray, int] = (np.zeros(3), 0)
        self._health = None
        self._latest: StampedState | None = None
        self._enabled = False
        self._link_up = False

    # ------------------------------------------------------------------ Platform
    async def connect(self) -> None:
        from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
        from mavsdk.asyncio.plugins.action import ActionAsync
        from mavsdk.asyncio.plugins.offboard import OffboardAsync
        from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

        route_mavsdk_log()
        self._mavsdk = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
        await self._mavsdk.add_any_connection(self.url)
        log.info("event=listening url=%s", self.url)
        while self._system is None:
            self._system = await self._mavsdk.first_autopilot(timeout_s=1.0)
        self.connected = True
        self._action, self._offboard = ActionAsync(self._system), OffboardAsync(self._system)
        self._telemetry = tel = TelemetryAsync(self._system)
        streams = {"position": (tel.subscribe_position_velocity_ned(), self._on_position),
                   "attitude": (tel.subscribe_attitude_quaternion(), self._on_attitude),
                   "rates": (tel.subscribe_attitude_angular_velocity_body(), self._on_rates),
                   "mode": (tel.subscribe_flight_mode(), self._on_mode),
                   "armed": (tel.subscribe_armed(), self._on_armed),
                   "landed": (tel.subscribe_landed_state(), self._on_landed),
                   "health": (tel.subscribe_health(), self._on_health),
                   "connected": (self._system.is_connected_state(), self._on_connected)}
        self._tasks = [asyncio.create_task(self._follow(name, gen, fn), name=f"mavsdk-{name}")
                       for name, (gen, fn) in streams.items()]
        self._tasks.append(asyncio.create_task(self._watch_link(), name="mavsdk-link"))
        await self._wait_for(lambda: self._health is not None and self._health.is_local_position_ok
                             and self._health.is_armable, self.health_timeout, "a local position and armable")
        log.info("event=autopilot_ready")

    async def prepare(self) -> None:
        """Arm and take off to the route's start height (already there: nothing to do)."""
        if self.in_air and self._latest is not None and abs(self._latest.state[2] - self._target_z()) < 0.3:
            return
        await self._action.set_takeoff_altitude(self.takeoff_altitude)      # PX4 parameter MIS_TAKEOFF_ALT
        await self._action.arm()
        await self._action.takeoff()
        log.info("event=takeoff altitude=%.2f", self.takeoff_altitude)
        await self._wait_for(lambda: self._latest is not None and abs(self._latest.state[2] - self._target_z()) < 0.15
                             and float(np.linalg.norm(self._latest.state[3:6])) < 0.2 and self.flight_mode != "TAKEOFF",
                             self.takeoff_timeout, "a hover at the take-off altitude")

    async def enable(self) -> None:
        from mavsdk.asyncio.plugins.offboard import AccelerationNed

        await self._offboard.set_acceleration_ned(AccelerationNed(0.0, 0.0, 0.0))
        await self._offboard.start()
        await self._wait_for(lambda: self.flight_mode == "OFFBOARD", 2.0, "OFFBOARD reported")
        self._enabled = True
        log.info("event=offboard_started")

    def latest_state(self) -> StampedState | None:
        return self._latest

    def fault(self) -> str | None:
        if self._telemetry_stale():
            return f"no position from the autopilot for {self.telemetry_timeout:g} s ({self.url})"
        if not self.connected:
            return "the autopilot link is down"
        if self._enabled and self.failsafe_reason is None and self.flight_mode not in ("OFFBOARD", None):
            return f"the autopilot left OFFBOARD (now {self.flight_mode})"
        return None

    async def send(self, command: np.ndarray) -> None:
        from mavsdk.asyncio.plugins.offboard import AccelerationNed

        a = np.asarray(command, dtype=float)
        if a.shape != (3,) or not np.all(np.isfinite(a)):
            raise ValueError(f"command must be 3 finite numbers {CONTROL_NAMES}, got {a!r}")
        if self.failsafe_reason is not None or not self._enabled:
            return
        norm = float(np.linalg.norm(a))
        if norm > self.accel_max:
            a = a * (self.accel_max / norm)
        n, e, d = enu_to_ned(a)
        await self._offboard.set_acceleration_ned(AccelerationNed(float(n), float(e), float(d)))
        self.setpoints += 1

    async def failsafe(self, reason: str) -> None:
        if self.failsafe_reason is None:
            self.failsafe_reason = reason
            log.warning("event=safe_action reason=%s action=hold_then_land", reason)
            self._tasks.append(asyncio.create_task(self._hold_then_land(), name="mavsdk-safe-action"))

    async def close(self) -> None:
        if self.in_air and self.failsafe_reason is None and self._action is not None:
            await self._try("land", self._action.land())
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)
        self._tasks = []
        log.info("event=mavlink_stats setpoints=%d send_failures=%d link_losses=%d",
                 self.setpoints, self.send_failures, self.link_losses)

    @property
    def at_rest(self) -> bool:
        """Landed and disarmed, as the autopilot reports it."""
        return self.landed_state == "ON_GROUND" and self.armed is False

    def link_stats(self) -> dict:
        return {"setpoints": self.setpoints, "send_failures": self.send_failures, "link_losses": self.link_losses,
                "flight_mode": self.flight_mode, "landed_state": self.landed_state, "armed": self.armed}

    # ------------------------------------------------------------------ safe action
    async def _hold_then_land(self) -> None:
        """Hold, then land; while the autopilot is unreachable keep trying, so that it lands once back.
        A vehicle on the ground that is still armed (e.g. stopped before its take-off) is disarmed."""
        if self.in_air is False:
            if self.armed:
                await self._try("disarm", self._action.disarm())
            return
        await self._try("hold", self._action.hold())
        await asyncio.sleep(self.hold_s)
        while self.landed_state != "ON_GROUND":
            if self.flight_mode != "LAND" and not self._telemetry_stale():
                if await self._try("land", self._action.land()):
                    log.warning("event=land_commanded altitude=%.2f", self._altitude())
            await asyncio.sleep(0.5)
        log.warning("event=landed")

    def _telemetry_stale(self) -> bool:
        """No position for ``telemetry_timeout`` s."""
        return self._pv is None or time.monotonic_ns() - self._pv[1] > self.telemetry_timeout * 1e9

    async def _try(self, what: str, coro) -> bool:
        try:
            await asyncio.wait_for(coro, 3.0)
            return True
        except Exception as exc:                  # ActionError, a time-out: the link may be down
            log.warning("event=%s_failed reason=%s", what, exc)
            return False

    # ------------------------------------------------------------------ telemetry
    async def _follow(self, name: str, stream, on_value) -> None:
        try:
            async for value in stream:
                on_value(value)
        except asyncio.CancelledError:
            raise
        except Exception:
            log.exception("event=telemetry_stream_failed stream=%s", name)

    def _on_position(self, pv) -> None:
        p, v = pv.position, pv.velocity
        pos = ned_to_enu((p.north_m, p.east_m, p.down_m)) + self.origin
        vel = ned_to_enu((v.north_m_s, v.east_m_s, v.down_m_s))
        self._pv = (np.concatenate([pos, vel]), time.monotonic_ns())
        self._assemble()

    def _on_attitude(self, q) -> None:
        self._quat = (attitude_ned_to_enu((q.w, q.x, q.y, q.z)), time.monotonic_ns())

    def _on_rates(self, w) -> None:
        self._rates = (frd_to_flu((w.roll_rad_s, w.pitch_rad_s, w.yaw_rad_s)), time.monotonic_ns())

    def _on_mode(self, mode) -> None:
        name = mode.name
        if name != self.flight_mode:
            log.info("event=flight_mode mode=%s", name)
        self.flight_mode = name

    def _on_armed(self, armed: bool) -> None:
        self.armed = bool(armed)

    def _on_landed(self, state) -> None:
        self.landed_state = state.name
        self.in_air = state.name not in ("ON_GROUND", "UNKNOWN")

    def _on_health(self, health) -> None:
        self._health = health

    def _on_connected(self, connected: bool) -> None:
        self.connected = bool(connected)

    def _assemble(self) -> None:
        if self._pv is None or self._quat is None:
            return
        (pv, t_pv), (q, t_q), (w, _) = self._pv, self._quat, self._rates
        self._latest = StampedState(np.concatenate([pv, q, w]), min(t_pv, t_q))

    async def _watch_link(self) -> None:
        while True:
            await asyncio.sleep(0.05)
            up = not self._telemetry_stale() and self.connected
            if up != self._link_up:
                if not up:
                    self.link_losses += 1
                log.warning("event=%s url=%s", "link_restored" if up else "link_lost", self.url)
                self._link_up = up

    # ------------------------------------------------------------------ helpers
    def _altitude(self) -> float:
        """Height above the autopilot's local origin (m; NaN before the first position)."""
        return float(self._latest.state[2] - self.origin[2]) if self._latest is not None else float("nan")

    def _target_z(self) -> float:
        return float(self.origin[2] + self.takeoff_altitude)

    async def _wait_for(self, condition, timeout_s: float, what: str) -> None:
        deadline = time.monotonic() + timeout_s
        while not condition():
            if time.monotonic() > deadline:
                raise TimeoutError(f"the autopilot did not reach {what} within {timeout_s:g} s")
            await asyncio.sleep(0.02)


def route_mavsdk_log() -> None:
    """MAVSDK's native log into this process's logging (logger ``mavsdk``) instead of stdout."""
    from mavsdk.logging import LogLevel, log_subscribe

    logger = logging.getLogger("mavsdk")
    levels = {LogLevel.DEBUG: logging.DEBUG, LogLevel.INFO: logging.INFO, LogLevel.WARN: logging.WARNING,
              LogLevel.ERROR: logging.ERROR}

    def forward(level, message, file, line) -> bool:
        logger.log(levels.get(level, logging.INFO), "%s", message)
        return True
    log_subscribe(forward)


def mavlink_quad_from_scenario(scenario, options: dict, file=None, flight_log=None) -> MavlinkQuad:
    """The MAVLink quadrotor of a mission. ``options``: the mission's [platform] table without ``kind``
    (url, origin, takeoff_altitude, telemetry_timeout, health_timeout, takeoff_timeout, hold_s)."""
    from vflpcd.config.vehicles import QuadrotorParams
    from vflpcd.base.tomlread import Table

    t = Table(options, file, "platform")
    t.check_known({"url", "origin", "takeoff_altitude", "telemetry_timeout", "health_timeout", "takeoff_timeout",
                   "hold_s"})
    url = t.string("url", "udpin://127.0.0.1:14540")
    if not url.startswith(("udpin://", "udpout://", "tcpin://", "tcpout://", "serial://")):
        raise t.error("url", f"expected a MAVSDK connection URL such as udpin://127.0.0.1:14540, got {url!r}")
    origin = t.vector("origin", 3, default=[0.0, 0.0, 0.0])
    start_z = float(scenario.start[2]) if len(scenario.start) > 2 else 2.0
    takeoff = t.number("takeoff_altitude", start_z - float(origin[2]), min=0.5, max=100.0)
    return MavlinkQuad(url, origin=origin, takeoff_altitude=takeoff, accel_max=QuadrotorParams.from_toml().accel_max,
                       telemetry_timeout=t.number("telemetry_timeout", 0.3, min=0.05, max=10.0),
                       health_timeout=t.number("health_timeout", 20.0, min=1.0, max=300.0),
                       takeoff_timeout=t.number("takeoff_timeout", 30.0, min=1.0, max=300.0),
                       hold_s=t.number("hold_s", 2.0, min=0.0, max=600.0))
