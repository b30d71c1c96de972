"""The safety supervisor: the last check between any controller and the platform, every tick.

Rule (a last-chance braking filter). A command u passes when, after applying it for the reaction
time (one control period plus the actuator latency), the platform's emergency manoeuvre from the
state reached stops the body without coming closer than ``margin`` to any obstacle it knows of:
static ones, and moving ones along their constant-velocity prediction, each at the time the body
gets there. Otherwise u is replaced by the emergency manoeuvre at once. So the body never enters a
known obstacle while a stop is still possible, and when none is possible any more it still brakes.
After an intervention the command is handed back only once it keeps ``release_margin`` (more than
``margin``), so that the override does not chatter.

Ground vehicle (state [X, Y, psi, vx, vy, omega], the CoG; command [a_x, delta_f]). Prediction: a
kinematic bicycle on two arcs of constant curvature kappa = tan(delta) / L (closed form): during the
reaction time the command's acceleration and the mean of the steering angle before and after its
rate-limited move; then braking at ``decel_factor`` |a_min| with that steering held, to standstill.
The applied steering angle is not measured: it is tracked from the commands sent, through the
actuator's rate limit. Body: covering discs (``Footprint``). Emergency: a_x = a_min, steering held.


Quadrotor (state [X, Y, Z, vx, vy, vz, ...]; command the world acceleration, gravity excluded).
Prediction: the clipped command for the reaction time, then a straight stop at ``decel_factor``
accel_max. Body: a sphere. Emergency: brake along -v to hover, then hold the position where the
speed fell below ``hold_speed`` (a PD law on that point).

Cost: one closed-form roll-out of K <= ``samples`` poses, a bounding-circle pre-filter over all
obstacles in one array operation, exact signed distances only for the obstacles that pass it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from vflpcd.core.footprint import Footprint
from vflpcd.core.obstacles import ObstacleState


LARGE_SHAPE_M = 3.0      # m: a bounding radius beyond which the reach test uses the exact distance (walls)


@dataclass(frozen=True)
class SupervisorConfig:
    """The supervisor's thresholds (``[supervisor]`` of config/safety.toml; a mission's ``[safety]``
    table overrides them). Distances m, times s, speeds m/s, gains 1/s^2 and 1/s."""

    margin: float = 0.10
    release_margin: float = 0.35
    latency_s: float = 0.05
    decel_factor: float = 0.9
    samples: int = 40
    max_step_m: float = 0.25
    discs: int = 8
    mover_wait_s: float = 2.0
    hold_speed: float = 0.2
    hold_kp: float = 2.0
    hold_kd: float = 2.5


@dataclass(frozen=True)
class CarLimits:
    """What the supervisor needs of a car: wheelbase L (m), a_min < 0 < a_max (m/s^2), delta_max (rad),
    delta_rate_max (rad/s)."""

    wheelbase: float
    a_min: float
    a_max: float
    delta_max: float
    delta_rate_max: float


@dataclass(frozen=True)
class QuadLimits:
    """What the supervisor needs of a quadrotor: the per-axis acceleration limit (m/s^2)."""

    accel_max: float


@dataclass(frozen=True)
class Verdict:
    """One tick's decision. command: what goes to the platform (n_u,); override: the emergency
    manoeuvre replaced the controller's command; engaged: an intervention began this tick (with
    ``reason``); released: one ended this tick; clearance: least predicted clearance under the
    controller's command (m, inf without obstacles); nearest: the obstacle that sets it."""

    command: np.ndarray
    override: bool
    engaged: bool
    released: bool
    clearance: float
    nearest: str
    reason: str = ""


class Supervisor:
    """The shared decision logic; ``GroundSupervisor`` and ``AerialSupervisor`` supply the platform's
    prediction (``_poses``), body and emergency manoeuvre."""

    def __init__(self, config: SupervisorConfig, footprint: Footprint, period: float) -> None:
        self.cfg, self.period = config, float(period)
        self.reaction = self.period + config.latency_s
        self.offsets, self.radius = np.asarray(footprint.offsets, float), float(footprint.radius)
        self.reach = float(np.max(np.abs(self.offsets)) + self.radius)
        self._middle = float(np.mean(self.offsets))            # body middle ahead of the reference point (m)
        self._far: dict[tuple, tuple[np.ndarray, float]] = {}     # large static obstacles: pose, distance
        self.reset()

    def reset(self) -> None:
        self.active = False
        self.interventions = 0

    # ------------------------------------------------------------------ per tick
    def filter(self, state: np.ndarray, command: np.ndarray, obstacles: Sequence[ObstacleState], t: float) -> Verdict:
        """The command to send at time t for ``state`` (n_x,), the controller's ``command`` (n_u,)
        and the known ``obstacles``."""
        state = np.asarray(state, float)
        u = self._clip(np.asarray(command, float))
        finite = bool(np.all(np.isfinite(u)))
        clear, nearest = (self.predicted_clearance(state, u, obstacles, t) if finite else (-np.inf, ""))
        was = self.active
        needed = self.cfg.release_margin if was else self.cfg.margin
        override = not finite or clear < needed
        self.active = override
        engaged, released = override and not was, was and not override
        reason = ""
        if engaged:
            self.interventions += 1
            reason = ("non-finite command" if not finite else
                      f"predicted clearance {clear:.2f} m to {nearest} under the command (margin {needed:g} m)")
        if override:
            out = self.emergency(state)
        else:
            out = u
            self._release(state)
        self._sent(out)
        return Verdict(out, override, engaged, released, float(clear), nearest, reason)

    def predicted_clearance(self, state: np.ndarray, u: np.ndarray, obstacles: Sequence[ObstacleState],
                            t: float) -> tuple[float, str]:
        """Least clearance (m) of the body along the manoeuvre "u for the reaction time, then the stop",
        and the obstacle that sets it ("" and inf without obstacles near). For a moving obstacle the
        better of that and "u held as long" counts: passing a mover by going on is as safe as stopping
        before it, and braking into its way is not."""
        if not obstacles:
            return np.inf, ""
        arrays = self._arrays(obstacles)
        near = self._within_reach(state, u, obstacles, arrays, t)
        if not np.any(near):
            return np.inf, ""
        if not np.all(near):
            obstacles = [o for o, n in zip(obstacles, near) if n]
            arrays = tuple(a[near] for a in arrays)
        pos, yaw, times = self._poses(state, u, True)
        (cs, ws), (cm, wm) = self._clearances(pos, yaw, t + times, obstacles, arrays)
        if cm < self.cfg.release_margin:
            pos, yaw, times = self._poses(state, u, False)
            _, (cg, wg) = self._clearances(pos, yaw, t + times, obstacles, arrays, movers_only=True)
            if cg > cm:
                cm, wm = cg, wg
        return (cs, ws) if cs <= cm else (cm, wm)

    def _within_reach(self, state: np.ndarray, u: np.ndarray, obstacles: Sequence[ObstacleState], arrays,
                      t: float) -> np.ndarray:
        """Which obstacles may come within release_margin of the body during the manoeuvre "u for the
        reaction time, then the stop" (its length and duration bound it), shape (n_o,) bool: a lower
        bound of each one's distance from the body now (the exact signed distance for a large shape,
        whose bounding circle says little, else the bounding circle's), less its own motion."""
        centers, vel, stamps, _, bound = arrays
        distance, duration = self._extent(state, u)
        pos, _ = self._pose_now(state)
        d = pos.shape[0]
        gap = np.sqrt(np.sum((centers[:, :d] - pos) ** 2, axis=1)) - bound     # a copy: large shapes overwrite
        for i in np.flatnonzero(bound > LARGE_SHAPE_M):
            gap[i] = self._large_gap(obstacles[i], centers[i, :d], pos, vel[i])
        travel = np.sqrt(np.sum(vel[:, :d] ** 2, axis=1)) * np.maximum(np.abs(t + duration - stamps), np.abs(t - stamps))
        return gap - travel <= distance + self.reach + self.cfg.release_margin

    def _large_gap(self, o: ObstacleState, center: np.ndarray, pos: np.ndarray, vel: np.ndarray) -> float:
        """A lower bound of a large obstacle's distance from pos: its exact signed distance, reused
        for a static one (less how far the body has moved since) while that leaves it far away."""
        if np.any(vel != 0.0):
            return float(o.shape.signed_distance(pos[None, :], center, o.yaw)[0])
        key = (o.id, o.shape, float(center[0]), float(center[1]), o.yaw)
        seen = self._far.get(key)
        if seen is not None:
            bound = seen[1] - float(np.sqrt(np.sum((pos - seen[0]) ** 2)))
            if bound > LARGE_SHAPE_M:
                return bound
        gap = float(o.shape.signed_distance(pos[None, :], center, o.yaw)[0])
        if len(self._far) > 256:
            self._far.clear()
        self._far[key] = (pos.copy(), gap)
        return gap

    def _extent(self, state: np.ndarray, u: np.ndarray) -> tuple[float, float]:  # pragma: no cover - abstract
        """Length (m) and duration (s) of the manoeuvre "u for the reaction time, then the stop"."""
        raise NotImplementedError

    def _arrays(self, obstacles: Sequence[ObstacleState]):
        """The obstacles as arrays, once per tick: centres, velocities, stamps, moving, bounding radii."""
        centers = np.array([o.center for o in obstacles], float)
        vel = np.array([o.velocity for o in obstacles], float)
        stamps = np.array([o.stamp for o in obstacles], float)
        bound = np.fromiter((self._bounding(o.shape) for o in obstacles), float, len(obstacles))
        return centers, vel, stamps, np.any(vel != 0.0, axis=1), bound

    def _clearances(self, pos: np.ndarray, yaw: np.ndarray, times: np.ndarray, obstacles: Sequence[ObstacleState],
                    arrays, movers_only: bool = False, behind: bool = False) -> tuple[tuple[float, str], tuple[float, str]]:
        """Least disc-cover clearance of the body at poses pos (K, d), yaw (K,) at absolute times (K,),
        to the static and to the moving obstacles, each with the id that sets it (``behind``: also
        movers behind the body's middle)."""
        d = pos.shape[1]
        centers, vel, stamps, moving, bound = arrays
        dt = times[None, :] - stamps[:, None]                                  # (n_o, K)
        rel = pos[None, :, :] - centers[:, None, :d] - vel[:, None, :d] * dt[..., None]
        # bounding-circle lower bound of each pose's clearance; beyond release_margin the exact
        # clearance cannot change a decision
        close = np.sqrt(np.einsum("okd,okd->ok", rel, rel)) < (bound + self.reach + self.cfg.release_margin)[:, None]
        near = close.any(axis=1)
        if movers_only:
            near &= moving
        static, mover = [np.inf, ""], [np.inf, ""]
        if not near.any():
            return tuple(static), tuple(mover)
        discs = self._discs(pos, yaw)                                          # (K, n, d)
        heading = None
        for i in np.flatnonzero(near):
            o, keep = obstacles[i], close[i]
            if moving[i]:
                if not behind:
                    # a mover counts only while it is ahead of the body's middle: one that closes in
                    # from behind does so by its own motion, and braking cannot avoid it
                    if heading is None:
                        heading = self._heading(pos, yaw)                      # (K, d) direction of travel
                    keep = keep & (np.einsum("kd,kd->k", rel[i] + self._middle * heading, heading) < 0.0)
                    if not keep.any():
                        continue
                pts = discs[keep] - (vel[i, :d] * dt[i][keep][:, None])[:, None, :]   # obstacle frozen at its stamp
                best = mover
            else:
                pts, best = discs[keep], static
            gap = float(o.shape.signed_distance(pts.reshape(-1, d), centers[i, :d], o.yaw).min()) - self.radius
            if gap < best[0]:
                best[0], best[1] = gap, o.id
        return tuple(static), tuple(mover)

    def braking_meets_mover(self, state: np.ndarray, command: np.ndarray, obstacles: Sequence[ObstacleState],
                            t: float) -> str:
        """The id of a moving obstacle that braking now would leave in the body's way (while it brakes,
        or standing for ``mover_wait_s`` after) while the command held would clear it ("" when there
        is none): stopping there is worse than going on."""
        if not obstacles:
            return ""
        arrays = self._arrays(obstacles)
        if not np.any(arrays[3]):
            return ""
        pos, yaw, times = self._poses(state, self._brake_command(state), True)
        wait = times[-1] + np.linspace(0.0, self.cfg.mover_wait_s, 9)[1:]     # then standing there
        pos = np.vstack([pos, np.repeat(pos[-1:], len(wait), axis=0)])
        yaw, times = np.concatenate([yaw, np.full(len(wait), yaw[-1])]), np.concatenate([times, wait])
        _, (cm, who) = self._clearances(pos, yaw, t + times, obstacles, arrays, movers_only=True, behind=True)
        if cm >= self.cfg.margin:
            return ""
        pos, yaw, times = self._poses(state, self._clip(np.asarray(command, float)), False)
        _, (cg, _) = self._clearances(pos, yaw, t + times, obstacles, arrays, movers_only=True, behind=True)
        return who if cg >= self.cfg.release_margin else ""

    def contact(self, state: np.ndarray, obstacles: Sequence[ObstacleState], t: float) -> tuple[float, str]:
        """Exact clearance (m, negative: overlap) of the body now to the nearest known obstacle that the
        disc cover touches, and its id (inf and "" when it touches none: then there is no contact)."""
        if not obstacles:
            return np.inf, ""
        pos, yaw = self._pose_now(np.asarray(state, float))
        discs = self._discs(pos[None, :], np.array([yaw]))[0]
        best, who = np.inf, ""
        for o in obstacles:
            c = o.center_at(t)[: len(pos)]
            if np.linalg.norm(c - pos) - self._bounding(o.shape) - self.reach > 1.0:
                continue
            if np.min(o.shape.signed_distance(discs, c, o.yaw)) > self.radius:
                continue                          # the cover contains the body: no contact
            gap = self.body.clearance(o.shape, c, o.yaw, pos, yaw)
            if gap < best:
                best, who = gap, o.id
        return best, who

    @staticmethod
    def _bounding(shape) -> float:
        return float(shape.bounding_radius())

    # ------------------------------------------------------------------ platform parts
    def _clip(self, u: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool):  # pragma: no cover - abstract
        raise NotImplementedError

    def _discs(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def emergency(self, state: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def stop(self, state: np.ndarray) -> np.ndarray:
        """The emergency manoeuvre's command, as sent (after a failsafe, without a controller)."""
        u = self.emergency(state)
        self._sent(u)
        return u

    def _brake_command(self, state: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        """The emergency manoeuvre's braking command from ``state``, without changing any state."""
        raise NotImplementedError

    def _heading(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _pose_now(self, state: np.ndarray) -> tuple[np.ndarray, float]:  # pragma: no cover - abstract
        raise NotImplementedError

    def position(self, state: np.ndarray) -> np.ndarray:
        """The body's reference point (d,) in ``state``."""
        return self._pose_now(np.asarray(state, float))[0]

    def speed(self, state: np.ndarray) -> float:  # pragma: no cover - abstract
        """The body's speed (m/s) in ``state``."""
        raise NotImplementedError

    def response_sample(self, state: np.ndarray, sent: np.ndarray) -> tuple:  # pragma: no cover - abstract
        """What ``ResponseWatch.update`` compares after t: speed, the velocity whose rate is the
        acceleration, the commanded acceleration, measured and commanded yaw rates (NaN: none)."""
        raise NotImplementedError

    def _release(self, state: np.ndarray) -> None:
        """The controller has the platform again (nothing to forget by default)."""

    def _sent(self, u: np.ndarray) -> None:
        """Called with every command handed to the platform."""


class GroundSupervisor(Supervisor):
    """The car: kinematic-bicycle arcs, covering discs, braking with the steering held."""

    STATE = ("X", "Y", "psi", "vx", "vy", "omega")

    def __init__(self, config: SupervisorConfig, footprint: Footprint, limits: CarLimits, period: float,
                 state_names: Sequence[str] = STATE) -> None:
        self.limits = limits
        self._idx = [tuple(state_names).index(n) for n in self.STATE]
        self.body = footprint
        super().__init__(config, footprint.with_discs(config.discs), period)
        self.a_brake = config.decel_factor * -limits.a_min

    def reset(self) -> None:
        super().reset()
        self.delta: float | None = None           # applied steering estimate (rad)

    def _clip(self, u: np.ndarray) -> np.ndarray:
        lim = self.limits
        return np.array([_clamp(u[0], lim.a_min, lim.a_max), _clamp(u[1], -lim.delta_max, lim.delta_max)])

    def _delta_now(self, x: np.ndarray) -> float:
        if self.delta is None:                    # first tick: the steering that explains the yaw rate
            vx, om = x[3], x[5]
            self.delta = float(np.arctan(self.limits.wheelbase * om / vx)) if vx > 1.0 else 0.0
        return self.delta

    def _extent(self, state: np.ndarray, u: np.ndarray) -> tuple[float, float]:
        v0 = max(float(state[self._idx[3]]), 0.0)
        t1, v1, s1 = _run(v0, float(u[0]), self.reaction)
        return s1 + v1 * v1 / (2.0 * self.a_brake), t1 + v1 / self.a_brake

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool):
        """Poses (K, 2), yaws (K,) and times from now (K,) of "u for the reaction time, then the stop"
        (``brake``) or "u held as long" (not ``brake``)."""
        x = state[self._idx]
        L, lim, T = self.limits.wheelbase, self.limits, self.reaction
        v0 = max(float(x[3]), 0.0)
        d0 = self._delta_now(x)
        step = lim.delta_rate_max * self.period
        d1 = d0 + _clamp(float(u[1]) - d0, -step, step)
        k1, k2 = np.tan(0.5 * (d0 + d1)) / L, np.tan(d1) / L
        a1 = float(u[0])
        t1, v1, s1 = _run(v0, a1, T)
        t_stop = v1 / self.a_brake
        a2, t2 = (-self.a_brake, t_stop) if brake else (a1, max(t_stop, 1.0))
        t2, _, s2 = _run(v1, a2, t2)
        s_end = s1 + s2
        if s_end <= self.cfg.max_step_m:           # (nearly) at rest: the pose now and the end pose
            course = float(x[2])
            chord = _chord(k1, s_end)
            end = (x[0] + chord * math.cos(course + 0.5 * k1 * s_end), x[1] + chord * math.sin(course + 0.5 * k1 * s_end))
            return (np.array([[x[0], x[1]], end]), np.array([x[2], x[2] + k1 * s_end]),
                    np.array([0.0, t1 + t2]))
        n = int(min(self.cfg.samples, max(2, np.ceil(s_end / self.cfg.max_step_m) + 1)))
        s = np.arange(n) * (s_end / (n - 1))
        first = s <= s1
        sig = np.where(first, s, s - s1)
        times = np.where(first, _time_at(sig, v0, a1, t1), t1 + _time_at(sig, v1, a2, t2))
        course = x[2] + (np.arctan2(x[4], x[3]) if x[3] > 0.5 else 0.0)
        c1, sn1 = np.cos(course + 0.5 * k1 * s1), np.sin(course + 0.5 * k1 * s1)
        chord1 = _chord(k1, s1)
        kap = np.where(first, k1, k2)
        half = 0.5 * kap * sig
        ang = np.where(first, course, course + k1 * s1) + half
        chord = sig * _sinc(half)
        pos = np.empty((n, 2))
        pos[:, 0] = np.where(first, x[0], x[0] + chord1 * c1) + chord * np.cos(ang)
        pos[:, 1] = np.where(first, x[1], x[1] + chord1 * sn1) + chord * np.sin(ang)
        yaw = x[2] + np.where(first, k1 * s, k1 * s1 + k2 * sig)
        return pos, yaw, times

    def _pose_now(self, state: np.ndarray) -> tuple[np.ndarray, float]:
        x = state[self._idx]
        return x[:2], float(x[2])

    def _heading(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        return np.stack([np.cos(yaw), np.sin(yaw)], axis=1)

    def speed(self, state: np.ndarray) -> float:
        return float(state[self._idx[3]])

    def response_sample(self, state: np.ndarray, sent: np.ndarray) -> tuple:
        """v_x, [v_x], [a_x commanded], the yaw rate and v_x tan(delta) / L of the applied steering."""
        x = state[self._idx]
        delta = self.delta if self.delta is not None else 0.0
        return x[3], x[3:4], sent[:1], x[5], x[3] * math.tan(delta) / self.limits.wheelbase

    def _discs(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        axis = np.stack([np.cos(yaw), np.sin(yaw)], axis=1)                       # (K, 2)
        return pos[:, None, :] + self.offsets[None, :, None] * axis[:, None, :]

    def emergency(self, state: np.ndarray) -> np.ndarray:
        """Strongest braking with the steering held where it is."""
        return self._brake_command(state)

    def _brake_command(self, state: np.ndarray) -> np.ndarray:
        x = np.asarray(state, float)[self._idx]
        return np.array([self.limits.a_min, self._delta_now(x)])

    def _sent(self, u: np.ndarray) -> None:
        if self.delta is None:
            return
        step = self.limits.delta_rate_max * self.period
        self.delta = self.delta + _clamp(float(u[1]) - self.delta, -step, step)


class AerialSupervisor(Supervisor):
    """The quadrotor: a point mass with the command for the reaction time, then a straight stop."""

    def __init__(self, config: SupervisorConfig, radius: float, limits: QuadLimits, period: float,
                 state_names: Sequence[str]) -> None:
        self.limits = limits
        names = tuple(state_names)
        self._p = [names.index(n) for n in ("X", "Y", "Z")]
        self._v = [names.index(n) for n in ("vx", "vy", "vz")]
        self.body = Footprint.sphere(radius)
        super().__init__(config, self.body, period)
        self.a_brake = config.decel_factor * limits.accel_max

    def reset(self) -> None:
        super().reset()
        self.hold_at: np.ndarray | None = None

    def _clip(self, u: np.ndarray) -> np.ndarray:
        return np.clip(u, -self.limits.accel_max, self.limits.accel_max)

    def _extent(self, state: np.ndarray, u: np.ndarray) -> tuple[float, float]:
        v0, T = state[self._v], self.reaction
        speed = float(np.linalg.norm(v0 + u * T))
        return float(np.linalg.norm(v0 * T + 0.5 * u * T * T)) + speed * speed / (2.0 * self.a_brake), \
            T + speed / self.a_brake

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool):
        p0, v0, T = state[self._p], state[self._v], self.reaction
        p1, v1 = p0 + v0 * T + 0.5 * u * T * T, v0 + u * T
        speed = float(np.linalg.norm(v1))
        t_stop = speed / self.a_brake
        t_end = T + (t_stop if brake else max(t_stop, 1.0))
        reach = np.linalg.norm(p1 - p0) + (speed * t_stop / 2 if brake else speed * (t_end - T))
        n = int(min(self.cfg.samples, max(2, np.ceil(reach / self.cfg.max_step_m) + 2)))
        tau = np.linspace(0.0, t_end, n)
        ta = np.minimum(tau, T)[:, None]
        pos = p0 + v0 * ta + 0.5 * u * ta * ta
        tb = np.maximum(tau - T, 0.0)[:, None]
        if brake:
            direction = v1 / speed if speed > 1e-9 else np.zeros(3)
            later = p1 + direction * (speed * tb - 0.5 * self.a_brake * tb * tb)
        else:
            later = p1 + v1 * tb + 0.5 * u * tb * tb
        pos = np.where((tau <= T)[:, None], pos, later)
        return pos, np.zeros(n), tau

    def _pose_now(self, state: np.ndarray) -> tuple[np.ndarray, float]:
        return state[self._p], 0.0

    def speed(self, state: np.ndarray) -> float:
        return float(np.linalg.norm(state[self._v]))

    def response_sample(self, state: np.ndarray, sent: np.ndarray) -> tuple:
        """|v|, v, the commanded acceleration; no yaw check."""
        v = state[self._v]
        return float(np.linalg.norm(v)), v, sent, np.nan, np.nan

    def _heading(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        step = np.diff(pos, axis=0, append=pos[-1:] + (pos[-1:] - pos[-2:-1] if len(pos) > 1 else 0.0))
        return step / np.maximum(np.linalg.norm(step, axis=1, keepdims=True), 1e-9)

    def _discs(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:
        return pos[:, None, :]

    def emergency(self, state: np.ndarray) -> np.ndarray:
        """Brake along -v while faster than hold_speed, then hold the point where that happened."""
        x = np.asarray(state, float)
        p, v = x[self._p], x[self._v]
        speed = float(np.linalg.norm(v))
        if self.hold_at is None and speed > self.cfg.hold_speed:
            return np.clip(-v / speed * self.a_brake, -self.limits.accel_max, self.limits.accel_max)
        if self.hold_at is None:
            self.hold_at = p.copy()
        a = -self.cfg.hold_kp * (p - self.hold_at) - self.cfg.hold_kd * v
        return np.clip(a, -self.limits.accel_max, self.limits.accel_max)

    def _release(self, state: np.ndarray) -> None:
        self.hold_at = None

    def _brake_command(self, state: np.ndarray) -> np.ndarray:
        v = np.asarray(state, float)[self._v]
        speed = float(np.linalg.norm(v))
        return -v / speed * self.a_brake if speed > 1e-9 else np.zeros(3)


def _clamp(x: float, lo: float, hi: float) -> float:
    """x (a number; NaN stays NaN) into [lo, hi]."""
    return float(lo if x < lo else hi if x > hi else x)


def _run(v0: float, a: float, duration: float) -> tuple[float, float, float]:
    """Time (s), final speed (m/s) and distance (m) of ``duration`` s at acceleration a from speed v0,
    ending early at standstill (the vehicle does not reverse)."""
    if a < 0.0 and v0 + a * duration <= 0.0:
        duration = v0 / -a
        return duration, 0.0, 0.5 * v0 * duration
    return duration, v0 + a * duration, v0 * duration + 0.5 * a * duration * duration


def _time_at(s: np.ndarray, v0: float, a: float, t_max: float) -> np.ndarray:
    """Time (s) at which distance s (K,) is covered from speed v0 at acceleration a (at most t_max)."""
    if abs(a) > 1e-9:
        t = (-v0 + np.sqrt(np.maximum(v0 * v0 + 2.0 * a * s, 0.0))) / a
    else:
        t = s / max(v0, 1e-9)
    return np.minimum(t, t_max)


def _sinc(u: np.ndarray) -> np.ndarray:
    """sin(u) / u, 1 at u = 0."""
    small = np.abs(u) < 1e-6
    return np.where(small, 1.0 - u * u / 6.0, np.sin(u) / np.where(small, 1.0, u))


def _chord(kappa: float, s: float) -> float:
    """Chord length of an arc of curvature kappa and length s: s sinc(kappa s / 2)."""
    half = 0.5 * kappa * s
    return s if abs(half) < 1e-6 else s * math.sin(half) / half
