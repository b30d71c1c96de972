"""The in-process platform: a simulated plant from ``sim/plants`` stepped in real time behind the
``Platform`` port, so that ``vflpcd run`` works with no hardware.

A physics thread ("inproc-physics") steps the plant at ``physics_rate_hz`` on absolute monotonic
deadlines (it catches up with whole steps when it falls behind, so simulated time stays real
time) with the last command held (zero-order hold). ``latest_state()`` returns the newest
``StampedState`` (one reference assignment: no lock needed). The plant stands still until
``enable()``: connect, plan, enable, then the clock runs.

Safe actions, as the real platforms do them: the vehicle brakes at its full deceleration with
the steering held until it stands still; the quadrotor holds its position for ``hold_s`` and
then lands (descends at ``land_speed`` to ``ground_z`` and stops its motors). A failsafe is
latched: later commands are ignored. ``at_rest`` (standing still below 0.05 m/s, or landed) is
what the daemon waits for before it exits; the physics runs until ``close``.

Fault injection for tests and drills (``inject``): "freeze" (the state stops updating: stale),
"nan" (non-finite states), "link" (``fault()`` reports a lost link and states stop), "stuck" (the
actuators stick at ``STUCK_COMMAND`` in the first control and zero in the others, a throttle that
stays open, and ignore the daemon's commands; the safe action still acts).
"""

from __future__ import annotations

import logging
import threading
import time

import numpy as np

from vflpcd.core.ports import PlatformBase, StampedState

log = logging.getLogger("sim.inproc")

FAULTS = ("freeze", "nan", "link", "stuck")
STUCK_COMMAND = 2.0           # the "stuck" actuators' first control: a_x (vehicle) or a_x (quadrotor), m/s^2


class InProcPlatform(PlatformBase):
    """``plant``: a ``sim.plants`` plant at its start state (its ``state_names``/``control_names``);
    ``brake``: the vehicle's braking acceleration (its a_min, m/s^2); ``hold_s``, ``land_speed``,
    ``ground_z``: the quadrotor's hold time (s), descent speed (m/s) and ground height (m)."""

    injects_faults = True

    def __init__(self, plant, *, physics_rate_hz: float = 200.0, brake: float = -6.0,
                 hold_s: float = 2.0, land_speed: float = 0.5, ground_z: float = 0.0) -> None:
        if not (10.0 <= physics_rate_hz <= 2000.0):
            raise ValueError(f"physics_rate_hz must lie in [10, 2000], got {physics_rate_hz}")
        self.plant = plant
        self.state_names = tuple(plant.state_names)
        self.control_names = tuple(plant.control_names)
        self.aerial = "Z" in self.state_names
        self.safe_action = "hold_then_land" if self.aerial else "brake_to_stop"
        self.dt = 1.0 / physics_rate_hz
        self.brake, self.hold_s, self.land_speed, self.ground_z = brake, hold_s, land_speed, ground_z
        self._command = np.zeros(len(self.control_names))
        self._latest: StampedState | None = None
        self._running = False
        self._enabled = False
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._fault: str | None = None
        self.failsafe_reason: str | None = None
        self.failsafe_stamp_ns: int | None = None     # when the safe action took over
        self.landed = False
        self.commands = 0
        self.steps = 0
        self._sim_time = 0.0                 # seconds simulated since enable()
        self._t_failsafe = 0.0               # simulated time of the failsafe
        self._hold_point = None              # where the quadrotor holds

    # ------------------------------------------------------------------ Platform
    async def connect(self) -> None:
        self._publish()
        self._thread = threading.Thread(target=self._physics, name="inproc-physics", daemon=True)
        self._thread.start()

    async def enable(self) -> None:
        self._enabled = True

    def latest_state(self) -> StampedState | None:
        return self._latest

    def fault(self) -> str | None:
        """A link fault the driver detected (None while healthy)."""
        return "link lost (injected)" if self._fault == "link" else None

    async def send(self, command: np.ndarray) -> None:
        u = np.asarray(command, dtype=float)
        if u.shape != self._command.shape or not np.all(np.isfinite(u)):
            raise ValueError(f"command must be {len(self.control_names)} finite numbers {self.control_names}, got {u!r}")
        if self.failsafe_reason is None:
            if self._fault != "stuck":
                self._command = u
            self.commands += 1

    async def failsafe(self, reason: str) -> None:
        if self.failsafe_reason is None:
            self.failsafe_reason = reason
            self._hold_point = self.plant.position().copy()
            self.failsafe_stamp_ns = time.monotonic_ns()
            self._t_failsafe = self._sim_time
            log.warning("event=safe_action reason=%s action=%s", reason, "hold_then_land" if self.aerial else "brake")

    async def close(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=1.0)

    # ------------------------------------------------------------------ tests and drills
    def inject(self, fault: str | None) -> None:
        """Start (or with None clear) an injected fault: one of ``FAULTS``."""
        if fault is not None and fault not in FAULTS:
            raise ValueError(f"unknown fault {fault!r} (known: {', '.join(FAULTS)})")
        self._fault = fault
        if fault == "stuck":
            self._command = np.zeros_like(self._command)
            self._command[0] = STUCK_COMMAND

    @property
    def at_rest(self) -> bool:
        """Standing still (vehicle) or landed (quadrotor)."""
        return self.landed if self.aerial else float(np.linalg.norm(self.plant.velocity_world())) < 0.05

    # ------------------------------------------------------------------ physics
    def _physics(self) -> None:
        period_ns = int(round(self.dt * 1e9))
        next_ns = time.monotonic_ns()
        while not self._stop.is_set():
            now = time.monotonic_ns()
            if now < next_ns:
                time.sleep((next_ns - now) * 1e-9)
                continue
            while next_ns <= now:
                if self._enabled and not self.landed:
                    self.plant.step(self._control(), self.dt)
                    self._sim_time += self.dt
                    self.steps += 1
                next_ns += period_ns
            self._publish()

    def _publish(self) -> None:
        if self._fault in ("freeze", "link"):
            return
        x = self.plant.state
        if self._fault == "nan":
            x[0] = np.nan
        self._latest = StampedState(x, time.monotonic_ns())

    def _control(self) -> np.ndarray:
        """The command held over the next physics step: the daemon's, or the safe action's."""
        if self.failsafe_reason is None:
            return self._command
        if not self.aerial:
            steer = self.plant.applied_control[1]
            return np.array([self.brake, steer])
        p, v = self.plant.position(), self.plant.velocity_world()
        target = self._hold_point.copy()
        v_ref = np.zeros(3)
        if self._sim_time - self._t_failsafe >= self.hold_s:          # hold, then land
            target[2] = min(p[2], target[2])
            v_ref[2] = -self.land_speed
            if p[2] <= self.ground_z + 0.05:
                self.landed = True
                log.warning("event=landed x=%.2f y=%.2f", p[0], p[1])
        a = 1.5 * (target - p) + 2.5 * (v_ref - v)
        a[2] = 2.5 * (v_ref[2] - v[2]) + (1.5 * (target[2] - p[2]) if v_ref[2] == 0.0 else 0.0)
        return a


def inproc_from_scenario(scenario, options: dict, file=None, flight_log=None) -> InProcPlatform:
    """The in-process platform of a mission: the route's plant at its start state. ``options``: the
    mission's [platform] table without ``kind`` (physics_rate_hz, seed, hold_s, land_speed)."""
    from sim.plants import make_plant
    from vflpcd.base.tomlread import Table

    t = Table(options, file, "platform")
    t.check_known({"physics_rate_hz", "seed", "hold_s", "land_speed"})
    rate = t.number("physics_rate_hz", 200.0, min=10.0, max=2000.0)
    seed = t.integer("seed", 0, min=0)
    plant = make_plant(scenario, seed)
    brake = -6.0
    if scenario.platform == "ground":
        from vflpcd.config.vehicles import BicycleConfig

        brake = BicycleConfig.load(scenario.params).limits.a_min
    return InProcPlatform(plant, physics_rate_hz=rate, brake=brake, hold_s=t.number("hold_s", 2.0, min=0.0),
                          land_speed=t.number("land_speed", 0.5, positive=True))
