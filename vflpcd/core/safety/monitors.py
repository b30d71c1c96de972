"""Supervision of the plan and of the tracking: when to stop trusting the controller.

Each check returns None while all is well, or a reason ``"<kind>: <detail>"`` with kind one of
``REASONS``; the caller (the offline runner or the daemon) then hands the vehicle to its safe action
and records a failsafe event.

- ``undrivable_plan``: the plan ahead (within ``plan_lookahead_m``) has curvature beyond what the
  steering can do (kappa_max = tan(delta_max) / L) or a speed plan beyond the lateral-acceleration
  limit (v^2 |kappa| > a_lat_max), each by more than ``plan_tolerance`` (a fraction), for longer
  than ``plan_timeout`` seconds; a replan like that is refused at once (the previous plan stays,
  the refusal counts as a failed replan);
- ``no_plan``: there has been no plan, or replans have failed without one succeeding, for longer
  than ``plan_timeout`` seconds;
- ``tracking_error``: the body has been farther than ``tracking_bound`` metres from its plan's path
  (a controller without a plan: ``route_bound`` from the route) for longer than
  ``tracking_persist`` seconds; the distance is measured across the path, so a vehicle held back
  behind its timed reference (by the supervisor) is not off track;
- ``unresponsive``: over a ``response_window`` of driving above ``response_min_speed``, the measured
  acceleration (dv/dt) differs from the mean commanded one by more than ``response_accel_tol``, or
  (ground, while the steering asks for at least ``response_yaw_min`` rad/s RMS) the least-squares
  gain from the yaw rate the steering commands (kinematic: v tan(delta) / L) to the measured one
  lies outside ``response_yaw_gain`` (an understeering car turns less than the kinematic rate, one
  that ignores its steering or follows other commands does not follow it at all);
- ``blocked``: the safety supervisor has held the body at rest for ``blocked_s`` seconds.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from vflpcd.core.path import nearest_on_polyline

REASONS = ("undrivable_plan", "no_plan", "tracking_error", "unresponsive", "blocked")


@dataclass(frozen=True)
class MonitorConfig:
    """``[monitors]`` of config/safety.toml (a mission's ``[safety]`` table overrides it)."""

    plan_tolerance: float = 0.05
    plan_lookahead_m: float = 30.0
    plan_timeout: float = 2.0
    tracking_bound: float = 3.0
    route_bound: float = 8.0
    tracking_persist: float = 0.5
    response_window: float = 1.0
    response_accel_tol: float = 1.5
    response_yaw_min: float = 0.1
    response_yaw_gain: tuple = (0.3, 2.0)
    response_min_speed: float = 1.0
    blocked_s: float = 10.0
    defer_max_s: float = 3.0


@dataclass(frozen=True)
class PlanLimits:
    """kappa_max: the steering's curvature limit (1/m; inf for a quadrotor); a_lat_max (m/s^2)."""

    kappa_max: float
    a_lat_max: float


def check_plan(kappa: np.ndarray, v: np.ndarray, limits: PlanLimits, tolerance: float) -> str | None:
    """A plan's curvature kappa (K,) and speed plan v (K,) against the vehicle's limits."""
    k = np.abs(np.asarray(kappa, float))
    v = np.asarray(v, float)
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(v))):
        return "undrivable_plan: the plan has non-finite curvature or speed"
    i = int(np.argmax(k))
    if k[i] > limits.kappa_max * (1.0 + tolerance):
        return (f"undrivable_plan: peak curvature {k[i]:.3f} 1/m beyond the steering limit "
                f"{limits.kappa_max:.3f} 1/m")
    a = v * v * k
    j = int(np.argmax(a))
    if a[j] > limits.a_lat_max * (1.0 + tolerance):
        return (f"undrivable_plan: {v[j]:.2f} m/s on curvature {k[j]:.3f} 1/m needs lateral acceleration "
                f"{a[j]:.2f} m/s^2 (limit {limits.a_lat_max:g})")
    return None


class PlanWatch:
    """The plan being followed and the replans (from the controller's counters), every tick.

    A replan is admitted (``admit``) only when the stretch of it that lies within ``plan_lookahead_m``
    of its start is drivable; a refused one counts as a failed replan and the previous plan stays.
    ``update`` checks the current plan over the look-ahead from the body's nearest point on it, and
    gives the reason to stop once the plan has been missing, undrivable ahead or not renewed after
    failing replans for longer than ``plan_timeout``."""

    def __init__(self, cfg: MonitorConfig, limits: PlanLimits, nearest=None) -> None:
        self.cfg, self.limits = cfg, limits
        self._nearest_loop = nearest              # path_kernel.polyline_nearest compiled, or None
        self.reset()

    def reset(self) -> None:
        self.version, self.failures, self.failing_since, self.why = -1, 0, None, ""
        self.bad_s = np.zeros(0)
        self.stale = False
        self.undrivable = ""
        self.near: int | None = None

    def admit(self, plan) -> str | None:
        """The reason to refuse a new plan (``kappa``, ``v``, ``s``), or None."""
        ahead = plan.s <= plan.s[0] + self.cfg.plan_lookahead_m
        return check_plan(plan.kappa[ahead], plan.v[ahead], self.limits, self.cfg.plan_tolerance)

    def update(self, t: float, plan, version: int, failures: int, position: np.ndarray) -> tuple[str | None, float]:
        """plan: the controller's current plan (``xy``, ``s``, ``kappa``, ``v``) or None; version,
        failures: its installed- and failed-replan counts; position: the body's (d,). Returns the
        reason to stop (or None) and the distance from the body to the plan's path (m, NaN without)."""
        if version != self.version:
            self.version, self.stale, self.near = version, False, None
            self.bad_s = self._bad_points(plan) if plan is not None else np.zeros(0)
        if failures != self.failures:
            self.failures, self.stale = failures, True
            self.why = "replans fail"
        distance, why = np.nan, ""
        if plan is None:
            why = "no plan"
        else:
            distance, i = self._nearest(position, plan.xy)
            s_now = plan.s[i]
            j = np.searchsorted(self.bad_s, s_now)
            if j < len(self.bad_s) and self.bad_s[j] <= s_now + self.cfg.plan_lookahead_m:
                why = self.undrivable
            elif self.stale:
                why = self.why
        if not why:
            self.failing_since = None
            return None, distance
        if self.failing_since is None:
            self.failing_since = t
        if t - self.failing_since > self.cfg.plan_timeout:
            kind = "undrivable_plan" if why == self.undrivable else "no_plan"
            detail = why.split(": ", 1)[-1] if kind == "undrivable_plan" else f"{why} ({self.failures} failed replans)"
            return (f"{kind}: no valid plan for {t - self.failing_since:.1f} s (limit {self.cfg.plan_timeout:g} s): "
                    f"{detail}"), distance
        return None, distance

    def _nearest(self, position: np.ndarray, xy: np.ndarray) -> tuple[float, int]:
        """The nearest segment, searched near the last one (the whole path after a new plan, or when
        the body is not near the window's inside)."""
        if self.near is not None:
            lo = max(self.near - 10, 0)
            distance, j = nearest_on_polyline(position, xy[lo:self.near + 40], self._nearest_loop)
            if lo < lo + j < min(self.near + 39, len(xy) - 2) or len(xy) <= 50:
                self.near = lo + j
                return distance, self.near
        distance, self.near = nearest_on_polyline(position, xy, self._nearest_loop)
        return distance, self.near

    def _bad_points(self, plan) -> np.ndarray:
        """Arc lengths of the plan's points beyond the limits (sorted); remembers the first reason."""
        k, v = np.abs(plan.kappa), plan.v
        tol = 1.0 + self.cfg.plan_tolerance
        bad = (k > self.limits.kappa_max * tol) | (v * v * k > self.limits.a_lat_max * tol) | ~np.isfinite(k * v)
        self.undrivable = check_plan(plan.kappa, plan.v, self.limits, self.cfg.plan_tolerance) or ""
        return np.sort(plan.s[bad])


class Persistence:
    """How long a condition has held: ``update(t, holds)`` gives the seconds since the first tick of
    the current run of ticks on which it held, None when it does not hold now."""

    def __init__(self) -> None:
        self.since: float | None = None

    def update(self, t: float, holds: bool) -> float | None:
        if not holds:
            self.since = None
            return None
        if self.since is None:
            self.since = t
        return t - self.since


class TrackingWatch:
    """The distance to the reference, with a persistence time."""

    def __init__(self, cfg: MonitorConfig) -> None:
        self.cfg = cfg
        self.reset()

    def reset(self) -> None:
        self.off = Persistence()

    def update(self, t: float, error: float, bound: float) -> str | None:
        held = self.off.update(t, bool(np.isfinite(error) and error > bound))
        if held is not None and held >= self.cfg.tracking_persist:
            return f"tracking_error: {error:.2f} m from the path for {held:.1f} s (bound {bound:g} m)"
        return None


class ResponseWatch:
    """Commanded against measured response over a sliding window of ticks.

    Each tick: ``update(t, speed, velocity, accel_cmd, yaw_rate, yaw_rate_cmd)`` with the measured
    speed (m/s), a velocity-like signal whose rate is the acceleration (vehicle: [v_x]; quadrotor:
    the velocity vector), the commanded acceleration (same shape), and (ground) measured and
    expected yaw rates (NaN for a quadrotor). The window is a ring of ``response_window / period``
    ticks."""

    def __init__(self, cfg: MonitorConfig, period: float) -> None:
        self.cfg = cfg
        self.n = max(2, int(round(cfg.response_window / period)) + 1)
        self.reset()

    def reset(self) -> None:
        self.count, self.i = 0, 0
        self.t = np.zeros(self.n)
        self.speed = np.zeros(self.n)
        self.yaw = np.zeros(self.n)
        self.yaw_cmd = np.zeros(self.n)
        self.vel: np.ndarray | None = None
        self.cmd: np.ndarray | None = None

    def update(self, t: float, speed: float, velocity: np.ndarray, accel_cmd: np.ndarray,
               yaw_rate: float = np.nan, yaw_rate_cmd: float = np.nan) -> str | None:
        if self.vel is None:
            self.vel, self.cmd = np.zeros((self.n, len(velocity))), np.zeros((self.n, len(velocity)))
        i = self.i
        self.t[i], self.speed[i], self.yaw[i], self.yaw_cmd[i] = t, speed, yaw_rate, yaw_rate_cmd
        self.vel[i], self.cmd[i] = velocity, accel_cmd
        self.i, self.count = (i + 1) % self.n, self.count + 1
        if self.count < self.n or self.speed.min() < self.cfg.response_min_speed:
            return None
        first = self.i                                   # the oldest row; i is the newest
        span = self.t[i] - self.t[first]
        if span <= 0.0:
            return None
        measured = (self.vel[i] - self.vel[first]) / span
        commanded = (self.cmd.sum(axis=0) - self.cmd[i]) / (self.n - 1)    # the commands that acted over the span
        e = measured - commanded
        gap = math.sqrt(float(e @ e))
        if gap > self.cfg.response_accel_tol:
            return (f"unresponsive: measured acceleration {np.round(measured, 2).tolist()} m/s^2 against "
                    f"{np.round(commanded, 2).tolist()} commanded over {span:.1f} s")
        if np.isfinite(yaw_rate):
            power = float(np.dot(self.yaw_cmd, self.yaw_cmd))
            if power >= self.n * self.cfg.response_yaw_min ** 2:
                gain = float(np.dot(self.yaw, self.yaw_cmd)) / power
                lo, hi = self.cfg.response_yaw_gain
                if not lo <= gain <= hi:
                    return (f"unresponsive: yaw rate {gain:.2f} times what the steering commands over {span:.1f} s "
                            f"(expected {lo:g} to {hi:g})")
        return None
