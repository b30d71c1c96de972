"""The safety layer of every loop (offline runner, benchmarks, daemon): one ``step`` per tick.

``SafetyGuard.step`` takes the controller's command and returns what may reach the actuator: the
supervisor's verdict (``supervisor.py``: the command, or the emergency manoeuvre when a collision
is imminent), and a failsafe reason when the loop must give up the mission: the body touches a
known obstacle (``collision``), or a monitor of ``monitors.py`` fires (an undrivable plan, no valid
plan, a tracking error, a vehicle that does not follow its commands, a body held at rest by the
supervisor). A failsafe other than a collision is put off (for at most ``defer_max_s``) while
stopping would leave the body in a moving obstacle's way and the command clears it. After a
failsafe the loop applies ``emergency(state)`` (or the platform's own safe
action) until the end.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.safety.monitors import (MonitorConfig, Persistence, PlanLimits, PlanWatch, ResponseWatch,
                                         TrackingWatch)
from vflpcd.core.safety.supervisor import Supervisor, Verdict

REST_SPEED = 0.05     # m/s: below this the body counts as at rest
CONTACT_CHECK_M = 0.05  # m: a predicted disc-cover clearance below which the exact contact is checked


@dataclass(frozen=True)
class GuardStep:
    """command (n_u,) to send; verdict: the supervisor's; trip: a failsafe reason or None."""

    command: np.ndarray
    verdict: Verdict
    trip: str | None


class SafetyGuard:
    """supervisor: a ``GroundSupervisor`` or ``AerialSupervisor``; monitors: their thresholds;
    plan_limits: the vehicle's curvature and lateral-acceleration limits; period: the control
    period (s); nearest: ``path_kernel.polyline_nearest`` compiled, for the plan monitor's search
    (None: its numpy path)."""

    def __init__(self, supervisor: Supervisor, monitors: MonitorConfig, plan_limits: PlanLimits,
                 period: float, nearest=None) -> None:
        self.supervisor, self.cfg = supervisor, monitors
        self.plans = PlanWatch(monitors, plan_limits, nearest)
        self.tracking = TrackingWatch(monitors)
        self.response = ResponseWatch(monitors, period)
        self.reset()

    def reset(self) -> None:
        self.supervisor.reset()
        self.plans.reset()
        self.tracking.reset()
        self.response.reset()
        self.held = Persistence()
        self.deferred_since: float | None = None
        self._controller, self._planning = None, None

    @property
    def interventions(self) -> int:
        return self.supervisor.interventions

    def emergency(self, state: np.ndarray, obstacles: Sequence[ObstacleState] = (), t: float = 0.0) -> np.ndarray:
        """The platform's emergency manoeuvre (brake, steering held / brake to hover and hold); with
        the known obstacles at time t, a car brakes with the steering that keeps it off them
        (``Supervisor.stop``)."""
        return self.supervisor.stop(state, obstacles, t)

    def step(self, t: float, state: np.ndarray, command: np.ndarray, obstacles: Sequence[ObstacleState],
             controller=None, route_error: float = np.nan) -> GuardStep:
        """state (n_x,), the controller's command (n_u,) at time t, the known obstacles; controller:
        checked for its plan when it has one (``planning``, a ``PlanningController``, whose
        ``plan_gate`` is then set to refuse undrivable replans); route_error: the distance to the
        route (m), the tracking error of a controller without a plan of its own (a planning one's
        is the distance to its plan's path)."""
        sup = self.supervisor
        state = np.asarray(state, float)
        verdict = sup.filter(state, command, obstacles, t)
        # the predicted clearance starts at the body's pose now and the disc cover contains the body:
        # only where it is (nearly) gone, or a mover may close in from behind, can there be contact
        maybe = verdict.clearance <= CONTACT_CHECK_M or (verdict.clearance < 0.5 and verdict.movers)
        contact = sup.contact(state, obstacles, t) if maybe else (np.inf, "")
        trip = None
        if contact[0] <= 0.0:
            trip = f"collision: the body overlaps {contact[1]} by {-contact[0]:.2f} m"
        if controller is not self._controller:
            self._controller = controller
            self._planning = controller.planning if controller is not None else None
            if self._planning is not None:
                self._planning.plan_gate = self.plans.admit
        bound = self.cfg.route_bound
        planning = self._planning
        if planning is not None:
            reason, distance = self.plans.update(t, planning.current_plan, planning.replans,
                                                 planning.replan_failures, sup.position(state))
            trip = trip or reason
            if planning.current_plan is not None:
                route_error, bound = distance, self.cfg.tracking_bound
        trip = trip or self.tracking.update(t, route_error, bound)
        trip = trip or self.response.update(t, *sup.response_sample(state, verdict.command))
        trip = trip or self._blocked(t, state, verdict)
        if trip and not trip.startswith("collision") and self._defer(t, state, command, obstacles):
            trip = None
        elif not trip:
            self.deferred_since = None
        return GuardStep(verdict.command, verdict, trip)

    def _defer(self, t: float, state: np.ndarray, command: np.ndarray, obstacles) -> bool:
        """Whether to put off giving up the mission because stopping now would leave the body in a
        mover's way while the command clears it (for at most ``defer_max_s``)."""
        if self.deferred_since is not None and t - self.deferred_since >= self.cfg.defer_max_s:
            return False
        if not self.supervisor.braking_meets_mover(state, command, obstacles, t):
            return False
        if self.deferred_since is None:
            self.deferred_since = t
        return True

    # ------------------------------------------------------------------ pieces
    def _blocked(self, t: float, state: np.ndarray, verdict: Verdict) -> str | None:
        held = self.held.update(t, verdict.override and self.supervisor.speed(state) < REST_SPEED)
        if held is not None and held >= self.cfg.blocked_s:
            return f"blocked: held at rest by the safety supervisor for {held:.1f} s ({verdict.nearest} in the way)"
        return None

    @staticmethod
    def at_rest(speed: float) -> bool:
        return speed < REST_SPEED
