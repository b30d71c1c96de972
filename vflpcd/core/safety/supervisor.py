"""The safety supervisor: the last check between any controller and the platform, every tick.

Rule (a last-chance braking filter). A command u passes when, after applying it for the reaction
time (one control period plus the actuator latency), the platform's emergency manoeuvre from the
state reached stops the body without coming closer than ``margin`` to any obstacle it knows of:
static ones, and moving ones along their constant-velocity prediction, each at the time the body
gets there (while they are ahead of the body's middle, or cross its heading: one that closes in
from behind along the heading does so by its own motion), and where it stops, it stays out of the way of the movers that cross its heading for
``mover_wait_s`` (a stop in a crossing car's path is no safe stop). Otherwise u is replaced by the emergency manoeuvre at once. So the body never enters a
known obstacle while a stop is still possible, and when none is possible any more it still brakes
(or, where the stop would leave it in a mover's way, drives on out of it).
After an intervention the command is handed back only once it keeps ``release_margin`` (more than
``margin``), so that the override does not chatter.

Ground vehicle (state [X, Y, psi, vx, vy, omega], the CoG; command [a_x, delta_f]). Prediction: a
kinematic bicycle on two arcs of constant curvature kappa = tan(delta) / L (closed form): during the
reaction time the command's acceleration and the mean of the steering angle before and after its
rate-limited move; then braking at ``decel_factor`` |a_min| with that steering held, to standstill.
The applied steering angle is not measured: it is tracked from the commands sent, through the
actuator's rate limit. A command also passes when the stop that straightens the steering at its
rate limit keeps the margin (a car steering back towards its lane beside an obstacle). Body:
covering discs (``Footprint``). Emergency: a_x = a_min, with the steering held or straightened,
whichever keeps further off; when no stop keeps the margin because it leaves the car in a mover's
way (at the first contact of the stop the mover closes on the body faster than the body on it, or
the stop meets nothing and only the standing does: a crossing car at a junction), a car still at
``GOING_ON_SPEED`` or more goes on at a_max with the controller's steering when the rule passes
that; when braking can no longer stop the car short of contact, a_x = a_min
with the steering (held, the controller's, or full lock either way) whose prediction, the steering
moving on at its rate limit through the stop, meets the obstacle at the lowest speed (or not at all).

Quadrotor (state [X, Y, Z, vx, vy, vz, ...]; command the world acceleration, gravity excluded).
Prediction: the clipped command for the reaction time, then a straight stop at ``decel_factor``
accel_max. Body: a sphere. Emergency: brake along -v to hover, then hold the position where the
speed fell below ``hold_speed`` (a PD law on that point).

Cost: one closed-form roll-out of K <= ``samples`` poses, a pre-filter over all obstacles in one
array operation (``obstacle_arrays``: bounding circles and boxes), exact signed distances (closed
form for circles and boxes) only for the obstacles that pass it: in one array operation each, or,
given the compiled loops of ``clearance_kernel`` and ``arc_kernel`` (``SupervisorLoops``), one
obstacle, pose and disc at a time in machine code, the same numbers without the arrays' temporaries.
"""

from __future__ import annotations

import math
import operator
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np

from vflpcd.core.footprint import Footprint
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.safety.arc_kernel import STRAIGHT, arc_point
from vflpcd.core.safety.obstacle_arrays import ObstacleArrays


GOING_ON_SPEED = 2.0   # m/s: a car this fast that braking leaves in a mover's way may go on instead (GroundSupervisor._override)


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
class SupervisorLoops:
    """The supervisor's loops compiled (``vflpcd.controllers.loops.supervisor_loops``):
    ``clearance_kernel``'s clearance test of round and box shapes and its pre-filter of the
    obstacles within reach, and ``arc_kernel``'s samples of the car's manoeuvre."""

    clearances: Callable
    within_reach: Callable
    arcs: Callable


@dataclass(frozen=True)
class Verdict:
    """One tick's decision. command: what goes to the platform (n_u,); override: the emergency
    manoeuvre replaced the controller's command; engaged: an intervention began this tick (with
    ``reason``); released: one ended this tick; clearance: least predicted clearance under the
    controller's command (m, inf without obstacles); nearest: the obstacle that sets it; movers: a
    moving obstacle is within the manoeuvre's reach."""

    command: np.ndarray
    override: bool
    engaged: bool
    released: bool
    clearance: float
    nearest: str
    reason: str = ""
    movers: bool = False


class Supervisor:
    """The shared decision logic; ``GroundSupervisor`` and ``AerialSupervisor`` supply the platform's
    prediction (``_poses``), body and emergency manoeuvre, in DIM dimensions."""

    DIM: int

    def __init__(self, config: SupervisorConfig, footprint: Footprint, period: float,
                 loops: SupervisorLoops | None = None) -> None:
        self.cfg, self.period = config, float(period)
        self.reaction = self.period + config.latency_s
        self.offsets, self.radius = np.ascontiguousarray(footprint.offsets, float), float(footprint.radius)
        self.reach = float(np.max(np.abs(self.offsets)) + self.radius)
        self._middle = float(np.mean(self.offsets))            # body middle ahead of the reference point (m)
        self._loops = loops                                    # compiled, or None: the numpy paths
        self._no_heading = np.zeros((0, self.DIM))
        self.reset()

    def reset(self) -> None:
        self.active = False
        self.interventions = 0
        self.movers_near = False
        self._memo: tuple = (None, None, (np.inf, ""))
        self._tick_arrays: tuple = (None, (), None)

    # ------------------------------------------------------------------ per tick
    def filter(self, state: np.ndarray, command: np.ndarray, obstacles: Sequence[ObstacleState], t: float) -> Verdict:
        """The command to send at time t for ``state`` (n_x,), the controller's ``command`` (n_u,)
        and the known ``obstacles``."""
        state = np.asarray(state, float)
        u = self._clip(np.asarray(command, float))
        finite = bool(np.isfinite(u).all())
        clear, nearest = (self.predicted_clearance(state, u, obstacles, t) if finite else (-np.inf, ""))
        movers = finite and self.movers_near
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
            out = self._override(state, u, obstacles, t) if finite else self.emergency(state)
        else:
            out = u
            self._release(state)
        self._sent(out)
        return Verdict(out, override, engaged, released, float(clear), nearest, reason, movers)

    def predicted_clearance(self, state: np.ndarray, u: np.ndarray, obstacles: Sequence[ObstacleState],
                            t: float) -> tuple[float, str]:
        """Least clearance (m) of the body along the manoeuvre "u for the reaction time, then the stop",
        and the obstacle that sets it ("" and inf without obstacles near). For a moving obstacle the
        better of that and "u held as long" counts: passing a mover by going on is as safe as stopping
        before it, and braking into its way is not (going on counts every mover, also those that end
        up behind the body's middle)."""
        self.movers_near = False
        if not obstacles:
            return np.inf, ""
        arrays = full = self._arrays(obstacles, t)
        key = None if arrays.moving.any() else (state.tobytes(), u.tobytes(), self._estimate())
        memo_key, memo_arrays, memo_result = self._memo
        if key is not None and key == memo_key and arrays.stand_as(memo_arrays):
            return memo_result
        near = self._within_reach(state, u, arrays, t)
        self.movers_near = bool((near & arrays.moving).any())
        if not near.any():
            result = (np.inf, "")
        else:
            if not near.all():
                arrays = arrays.subset(near)
            pos, yaw, times = self._poses(state, u, True)
            (cs, ws), (cm, wm) = self._stop_clearances(pos, yaw, t + times, arrays)
            if min(cs, cm) < self.cfg.release_margin:
                for alt in self._alternative_stops(state, u):
                    (ca, wa), (cb, wb) = self._stop_clearances(*alt[:2], t + alt[2], arrays)
                    if min(ca, cb) > min(cs, cm):
                        (cs, ws), (cm, wm) = (ca, wa), (cb, wb)
            if cm < self.cfg.release_margin:
                # going on clears a mover only if no mover meets the body on the way, also one that
                # the turn brings behind the body's middle (a crossing car the body turns in front of),
                # for as long as a stop must stay out of the movers' way (mover_wait_s) beyond the stop:
                # every mover, as the way is longer than the stop that bounds "within reach"
                pos, yaw, times = self._poses(state, u, False, hold=self.cfg.mover_wait_s)
                _, (cg, wg) = self._clearances(pos, yaw, t + times, full, movers_only=True, behind=True)
                if cg > cm:
                    cm, wm = cg, wg
            result = (cs, ws) if cs <= cm else (cm, wm)
        self._memo = (key, full, result)
        return result

    def _stop_clearances(self, pos: np.ndarray, yaw: np.ndarray, times: np.ndarray, arrays: ObstacleArrays
                         ) -> tuple[tuple[float, str], tuple[float, str]]:
        """``_clearances`` of a stop (poses pos (K, d), yaw (K,) at absolute times (K,)), and of the
        body standing where it stops for ``mover_wait_s``, to the movers that cross its heading there
        (more across it than along it): a stop in a crossing car's or walker's way is no safe stop,
        wherever it comes from. Movers along the heading (a car following in the lane) do not count
        there: one that runs into a body at rest does so by its own motion."""
        static, mover = self._clearances(pos, yaw, times, arrays)
        if not arrays.moving.any() or self.cfg.mover_wait_s <= 0.0:
            return static, mover
        heading = self._heading(pos[-1:], yaw[-1:])[0]
        v = arrays.velocity
        along = np.abs(v @ heading)
        across = np.sqrt(np.maximum((v * v).sum(axis=1) - along ** 2, 0.0))
        crossing = arrays.moving & (across > along)
        if not crossing.any():
            return static, mover
        _, (cw, ww) = self._clearances(*self._standing(pos, yaw, times, with_stop=False),
                                       arrays.subset(crossing) if not crossing.all() else arrays,
                                       movers_only=True, behind=True)
        return static, (cw, ww) if cw < mover[0] else mover

    def _standing(self, pos: np.ndarray, yaw: np.ndarray, times: np.ndarray, with_stop: bool):
        """The body standing where the stop (pos (K, d), yaw (K,), times (K,)) ends, for ``mover_wait_s``
        after it: 8 poses (pos, yaw, times), preceded by the stop's own with ``with_stop``."""
        wait = times[-1] + np.linspace(0.0, self.cfg.mover_wait_s, 9)[1:]
        still = (np.repeat(pos[-1:], len(wait), axis=0), np.full(len(wait), yaw[-1]), wait)
        if not with_stop:
            return still
        return np.vstack([pos, still[0]]), np.concatenate([yaw, still[1]]), np.concatenate([times, wait])

    def _alternative_stops(self, state: np.ndarray, u: np.ndarray) -> list:
        """Other stops after "u for the reaction time" that the emergency manoeuvre can take (poses,
        yaws, times as ``_poses``): the better of them and the plain stop judges a command. There
        are none by default."""
        return []

    def _arrays(self, obstacles: Sequence[ObstacleState], t: float) -> ObstacleArrays:
        """``ObstacleArrays.of`` the obstacles, kept for the other predictions of the same tick (time t)
        about the same obstacle states (the objects themselves)."""
        when, states, arrays = self._tick_arrays
        if when == t and len(states) == len(obstacles) and all(map(operator.is_, states, obstacles)):
            return arrays
        states = tuple(obstacles)
        arrays = ObstacleArrays.of(states, self.DIM)
        self._tick_arrays = (t, states, arrays)
        return arrays

    def _estimate(self):
        """The platform's estimated internal state that the prediction uses (none by default). With every
        obstacle at rest, the same state, command, estimate and obstacles give the same clearance (as
        for a body held at rest in front of a wall, tick after tick): ``predicted_clearance`` keeps the
        last one."""
        return None

    def _within_reach(self, state: np.ndarray, u: np.ndarray, arrays: ObstacleArrays, t: float) -> np.ndarray:
        """Which obstacles may come within release_margin of the body during the manoeuvre "u for the
        reaction time, then the stop" and the ``mover_wait_s`` standing after it (its length and
        duration bound it), shape (n_o,) bool: a lower bound of each one's distance from the body now
        (bounding circle and oriented bounding box), less its own motion."""
        distance, duration = self._extent(state, u)
        duration += self.cfg.mover_wait_s
        pos, _ = self._pose_now(state)
        if self._loops is not None:
            near = np.empty(len(arrays), dtype=bool)
            self._loops.within_reach(np.ascontiguousarray(pos), arrays.motion, arrays.shape, float(t),
                                     float(t + duration), distance + self.reach + self.cfg.release_margin, near)
            return near
        gap = arrays.gap_bound(pos)
        velocity = arrays.velocity
        speed = np.sqrt((velocity * velocity).sum(axis=1))
        travel = speed * np.maximum(np.abs(t + duration - arrays.stamps), np.abs(t - arrays.stamps))
        return gap - travel <= distance + self.reach + self.cfg.release_margin

    def _extent(self, state: np.ndarray, u: np.ndarray) -> tuple[float, float]:  # pragma: no cover - abstract
        """Length (m) and duration (s) of the manoeuvre "u for the reaction time, then the stop"."""
        raise NotImplementedError

    def _clearances(self, pos: np.ndarray, yaw: np.ndarray, times: np.ndarray, arrays: ObstacleArrays,
                    movers_only: bool = False, behind: bool = False) -> tuple[tuple[float, str], tuple[float, str]]:
        """Least disc-cover clearance of the body at poses pos (K, d), yaw (K,) at absolute times (K,),
        to the static and to the moving obstacles (those within reach: ``_within_reach``), each with
        the id that sets it (``behind``: also movers behind the body's middle)."""
        if self._loops is not None and arrays.closed:
            return self._compiled_clearances(pos, yaw, times, arrays, movers_only, behind)
        discs = self._discs(pos, yaw)                                           # (K, n, d)
        K, n, d = discs.shape
        moving = arrays.moving
        static, mover = (np.inf, ""), (np.inf, "")
        if not movers_only and not moving.all():
            fixed = arrays.subset(~moving) if moving.any() else arrays
            gap = fixed.signed_distance(np.broadcast_to(discs.reshape(1, K * n, d), (len(fixed), K * n, d)))
            gap = gap.min(axis=1)
            i = int(gap.argmin())
            static = (float(gap[i]) - self.radius, fixed.states[i].id)
        if moving.any():
            movers = arrays.subset(moving) if not moving.all() else arrays
            shift = movers.velocity[:, None, :] * (times[None, :] - movers.stamps[:, None])[..., None]  # (n_m, K, d)
            rel = pos[None, :, :] - movers.centers[:, None, :] - shift
            # bounding-circle lower bound of each pose's clearance; beyond release_margin the exact
            # clearance cannot change a decision
            keep = np.sqrt((rel * rel).sum(axis=-1)) < (movers.bound + self.reach + self.cfg.release_margin)[:, None]
            if not behind:
                # a mover counts while it is ahead of the body's middle, or while it crosses the body's
                # heading (more across it than along it): one that closes in from behind along the
                # heading does so by its own motion, and braking cannot avoid it; a crossing car that
                # meets the side of a body braking in its way is met by the braking
                heading = self._heading(pos, yaw)[None]                         # (1, K, d) direction of travel
                along = (movers.velocity[:, None, :] * heading).sum(axis=-1)   # (n_m, K)
                across2 = (movers.velocity * movers.velocity).sum(axis=1)[:, None] - along * along
                keep &= (((rel + self._middle * heading) * heading).sum(axis=-1) < 0.0) | (across2 > along * along)
            if keep.any():
                pts = discs[None] - shift[:, :, None, :]                        # the movers frozen at their stamps
                gap = movers.signed_distance(pts.reshape(len(movers), K * n, d)).reshape(len(movers), K, n)
                gap = np.where(keep, gap.min(axis=2), np.inf).min(axis=1)
                i = int(gap.argmin())
                if gap[i] < np.inf:
                    mover = (float(gap[i]) - self.radius, movers.states[i].id)
        return static, mover

    def _compiled_clearances(self, pos: np.ndarray, yaw: np.ndarray, times: np.ndarray, arrays: ObstacleArrays,
                             movers_only: bool, behind: bool) -> tuple[tuple[float, str], tuple[float, str]]:
        """``_clearances`` by the compiled ``clearance_kernel.clearances_loop`` (round and box shapes)."""
        pos, yaw, times = np.ascontiguousarray(pos), np.ascontiguousarray(yaw), np.ascontiguousarray(times)
        heading = self._heading(pos, yaw) if not behind and arrays.moving.any() else self._no_heading
        cs, i, cm, j = self._loops.clearances(pos, yaw, times, self.offsets, arrays.motion, arrays.shape,
                                              np.ascontiguousarray(heading), not movers_only, True, behind,
                                              self._middle, self.reach, self.cfg.release_margin)
        return ((float(cs) - self.radius, arrays.states[i].id) if i >= 0 else (np.inf, ""),
                (float(cm) - self.radius, arrays.states[j].id) if j >= 0 else (np.inf, ""))

    def braking_meets_mover(self, state: np.ndarray, command: np.ndarray, obstacles: Sequence[ObstacleState],
                            t: float) -> str:
        """The id of a moving obstacle that braking now would leave in the body's way (while it brakes,
        or standing for ``mover_wait_s`` after) while the command held would clear it ("" when there
        is none): stopping there is worse than going on."""
        if not obstacles:
            return ""
        arrays = self._arrays(obstacles, t)
        if not arrays.moving.any():
            return ""
        pos, yaw, times = self._standing(*self._poses(state, self._brake_command(state), True), with_stop=True)
        _, (cm, who) = self._clearances(pos, yaw, t + times, arrays, movers_only=True, behind=True)
        if cm >= self.cfg.margin:
            return ""
        pos, yaw, times = self._poses(state, self._clip(np.asarray(command, float)), False)
        _, (cg, _) = self._clearances(pos, yaw, t + times, arrays, movers_only=True, behind=True)
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
            if np.linalg.norm(c - pos) - o.shape.bounding_radius() - self.reach > 1.0:
                continue
            if np.min(o.shape.signed_distance(discs, c, o.yaw)) > self.radius:
                continue                          # the cover contains the body: no contact
            gap = self.body.clearance(o.shape, c, o.yaw, pos, yaw)
            if gap < best:
                best, who = gap, o.id
        return best, who

    # ------------------------------------------------------------------ platform parts
    def _clip(self, u: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool, hold: float = 0.0):  # pragma: no cover - abstract
        raise NotImplementedError

    def _discs(self, pos: np.ndarray, yaw: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def emergency(self, state: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _override(self, state: np.ndarray, u: np.ndarray | None, obstacles: Sequence[ObstacleState],
                  t: float) -> np.ndarray:
        """What replaces the command u (None: there is none) when it fails: the emergency manoeuvre."""
        return self.emergency(state)

    def stop(self, state: np.ndarray, obstacles: Sequence[ObstacleState] = (), t: float = 0.0) -> np.ndarray:
        """The emergency manoeuvre's command, as sent (after a failsafe, without a controller). With the
        known obstacles at time t it is chosen as when a command is overridden (``_override``): a car
        whose stop with the steering held would run into one brakes with the steering that meets it
        slowest or not at all."""
        state = np.asarray(state, float)
        u = self._override(state, None, obstacles, t) if obstacles else self.emergency(state)
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
    DIM = 2

    def __init__(self, config: SupervisorConfig, footprint: Footprint, limits: CarLimits, period: float,
                 state_names: Sequence[str] = STATE, loops: SupervisorLoops | None = None) -> None:
        self.limits = limits
        self._idx = [tuple(state_names).index(n) for n in self.STATE]
        self.body = footprint
        super().__init__(config, footprint.with_discs(config.discs), period, loops)
        self.a_brake = config.decel_factor * -limits.a_min

    def reset(self) -> None:
        super().reset()
        self.delta: float | None = None           # applied steering estimate (rad)

    def _estimate(self):
        return self.delta

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

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool, ramp: bool = False,
               settle: float | None = None, hold: float = 0.0):
        """Poses (K, 2), yaws (K,) and times from now (K,) of "u for the reaction time, then the stop"
        (``brake``) or "u held as long" (not ``brake``; at least 1 s, and ``hold`` s more; a u that
        brakes the car to rest before then leaves it standing there, for the check of the movers that
        come its way: judged on its stop alone, braking to rest in a crossing car's way was a safe
        way to go on). The steering moves toward u's at the rate
        limit for one period and is then held; with ``ramp`` it keeps moving through the stop (the
        second arc has the steering reached halfway through it); with ``settle`` it moves from
        there toward ``settle`` through the stop (the emergency stop that straightens, ``settle`` 0)."""
        X, Y, psi, vx, vy, _ = state[self._idx].tolist()
        L, lim, T = self.limits.wheelbase, self.limits, self.reaction
        v0 = max(vx, 0.0)
        d0 = self._delta_now(state[self._idx])
        step = lim.delta_rate_max * self.period
        d1 = d0 + _clamp(float(u[1]) - d0, -step, step)
        k1, k2 = math.tan(0.5 * (d0 + d1)) / L, math.tan(d1) / L
        a1 = float(u[0])
        t1, v1, s1 = _run(v0, a1, T)
        t_stop = v1 / self.a_brake
        a2, t2 = (-self.a_brake, t_stop) if brake else (a1, max(t_stop, 1.0) + hold)
        wanted = T + t2
        t2, _, s2 = _run(v1, a2, t2)
        if ramp:
            turn = lim.delta_rate_max * (self.reaction + 0.5 * t2)
            k2 = math.tan(d0 + _clamp(float(u[1]) - d0, -turn, turn)) / L
        elif settle is not None:
            turn = lim.delta_rate_max * 0.5 * t2
            k2 = math.tan(d1 + _clamp(settle - d1, -turn, turn)) / L
        pos, yaw, times = self._poses_moving(X, Y, psi, vx, vy, v0, a1, t1, v1, a2, t2, k1, k2, s1, s2)
        if brake or t1 + t2 >= wanted - 1e-9:
            return pos, yaw, times
        rest = np.linspace(times[-1], wanted, 9)[1:]     # "u held" that brakes the car to rest: it stands
        return (np.vstack([pos, np.repeat(pos[-1:], len(rest), axis=0)]),
                np.concatenate([yaw, np.full(len(rest), yaw[-1])]), np.concatenate([times, rest]))

    def _poses_moving(self, X, Y, psi, vx, vy, v0, a1, t1, v1, a2, t2, k1, k2, s1, s2):
        """``_poses``' samples of the two arcs: s1 m of curvature k1 in t1 s from speed v0 at a1, then
        s2 m of k2 in t2 s from v1 at a2."""
        s_end = s1 + s2
        if s_end <= self.cfg.max_step_m:           # (nearly) at rest: the pose now and the end pose
            end = arc_point(X, Y, psi, k1, s_end, s_end)
            return np.array([[X, Y], end]), np.array([psi, psi + k1 * s_end]), np.array([0.0, t1 + t2])
        n = int(min(self.cfg.samples, max(2, math.ceil(s_end / self.cfg.max_step_m) + 1)))
        ds = s_end / (n - 1)
        n1 = min(n, int(s1 / ds) + 1)             # samples on the first arc (s <= s1)
        course = psi + (math.atan2(vy, vx) if vx > 0.5 else 0.0)
        if self._loops is not None:               # the same numbers, compiled (arc_kernel)
            pos, yaw, times = np.empty((n, 2)), np.empty(n), np.empty(n)
            self._loops.arcs(X, Y, course, psi, k1, k2, s1, ds, n1, v0, a1, t1, v1, a2, t2, pos, yaw, times)
            return pos, yaw, times
        s = np.arange(n) * ds
        sa, sb = s[:n1], s[n1:] - s1
        pos, yaw, times = np.empty((n, 2)), np.empty(n), np.empty(n)
        _arc_into(pos[:n1], X, Y, course, k1, sa)
        yaw[:n1] = psi + k1 * sa
        times[:n1] = _time_at(sa, v0, a1, t1)
        if n1 < n:
            Xb, Yb = arc_point(X, Y, course, k1, s1, s1)
            _arc_into(pos[n1:], Xb, Yb, course + k1 * s1, k2, sb)
            yaw[n1:] = psi + k1 * s1 + k2 * sb
            times[n1:] = t1 + _time_at(sb, v1, a2, t2)
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

    def _alternative_stops(self, state: np.ndarray, u: np.ndarray) -> list:
        """The stop that straightens the steering at its rate limit: a car steering back towards its
        lane beside an obstacle need not brake on the arc that turns it into the obstacle."""
        return [self._poses(state, u, True, settle=0.0)]

    def _override(self, state: np.ndarray, u: np.ndarray | None, obstacles: Sequence[ObstacleState],
                  t: float) -> np.ndarray:
        """Strongest braking with the steering held or straightened, whichever keeps further off,
        unless that can no longer stop the car short of contact: then strongest braking with the
        steering (that one, the controller's when there is a command u, or full lock either way,
        reached at the rate limit) whose prediction meets the obstacle slowest (or not at all)."""
        brake = self._brake_command(state)
        if not obstacles:
            return brake
        lim = self.limits
        clear = self.predicted_clearance(state, brake, obstacles, t)[0]
        straight = np.array([lim.a_min, 0.0])
        straight_clear = self.predicted_clearance(state, straight, obstacles, t)[0]
        if straight_clear > clear:      # the stop that straightens keeps further off (``_alternative_stops``)
            brake, clear = straight, straight_clear
        if clear >= self.cfg.margin:
            return brake
        arrays = self._arrays(obstacles, t)
        stop = self._stop_gaps(state, brake, arrays, t)
        if self.speed(state) >= GOING_ON_SPEED and not self._runs_into(stop, arrays, t):
            # braking leaves the body in a mover's way: going on may clear it
            going = self._going_on(state, u, obstacles, t)
            if going is not None:
                return going
        if clear < 0.0:
            best, harm = brake, self._harm(state, brake, stop)
            steers = (lim.delta_max, -lim.delta_max) if u is None else (float(u[1]), lim.delta_max, -lim.delta_max)
            for steer in steers:
                candidate = np.array([lim.a_min, steer])
                h = self._impact(state, candidate, arrays, t)
                if h < harm - 1e-3:
                    best, harm = candidate, h
            return best
        return brake

    def _going_on(self, state: np.ndarray, u: np.ndarray | None, obstacles: Sequence[ObstacleState],
                  t: float) -> np.ndarray | None:
        """A command that goes on where no stop keeps the margin (a car braked into a crossing car's
        way): the controller's steering (held where there is no command u) at the strongest
        acceleration, when the rule itself passes it (``margin``); None otherwise."""
        steer = float(u[1]) if u is not None else self._delta_now(np.asarray(state, float)[self._idx])
        candidate = np.array([self.limits.a_max, steer])
        if self.predicted_clearance(state, candidate, obstacles, t)[0] >= self.cfg.margin:
            return candidate
        return None

    def _stop_gaps(self, state: np.ndarray, u: np.ndarray, arrays: ObstacleArrays, t: float):
        """The poses (pos, yaw, times from now) of "u for the reaction time, then the stop" with the
        steering moving on through it, and each obstacle's disc-cover clearance (m) at each (n_o, K)."""
        pos, yaw, times = self._poses(state, u, True, ramp=True)
        discs = self._discs(pos, yaw)
        K, n, d = discs.shape
        shift = arrays.velocity[:, None, :] * (t + times[None, :] - arrays.stamps[:, None])[..., None]
        pts = (discs[None] - shift[:, :, None, :]).reshape(len(arrays), K * n, d)
        return pos, yaw, times, arrays.signed_distance(pts).reshape(len(arrays), K, n).min(axis=2) - self.radius

    @staticmethod
    def _runs_into(stop, arrays: ObstacleArrays, t: float) -> bool:
        """Whether the body, on a stop (``_stop_gaps``' poses and clearances to ``arrays`` at time t),
        runs into an obstacle: at its first contact it closes on the obstacle faster than the
        obstacle closes on it (a pedestrian stepping out in front of it), rather than being met (a
        crossing car into a body braked in its way), or it meets nothing at all (False)."""
        pos, _, times, gaps = stop
        hit = np.flatnonzero((gaps < 0.0).any(axis=0))
        if not hit.size:
            return False
        k = int(hit[0])
        i = int(np.argmin(gaps[:, k]))
        towards = arrays.centers[i] + arrays.velocity[i] * (t + times[k] - arrays.stamps[i]) - pos[k]
        towards = towards / max(float(np.linalg.norm(towards)), 1e-9)
        j = max(k, 1)
        body = (pos[j] - pos[j - 1]) / max(float(times[j] - times[j - 1]), 1e-9) if len(pos) > 1 else 0.0 * towards
        return float(body @ towards) >= float(-arrays.velocity[i] @ towards)

    def _impact(self, state: np.ndarray, u: np.ndarray, arrays: ObstacleArrays, t: float) -> float:
        """The harm of "u for the reaction time, then the stop" (``_harm``)."""
        return self._harm(state, u, self._stop_gaps(state, u, arrays, t))

    def _harm(self, state: np.ndarray, u: np.ndarray, stop) -> float:
        """The harm of the stop of command u (``_stop_gaps``' poses and clearances): the speed (m/s)
        at the first pose whose disc cover meets an obstacle, or minus the least clearance (m) when
        none does."""
        _, _, times, gaps = stop
        gap = gaps.min(axis=0)
        hit = np.flatnonzero(gap < 0.0)
        if not hit.size:
            return -float(gap.min())
        v0 = max(float(state[self._idx[3]]), 0.0)
        t1, v1, _ = _run(v0, float(u[0]), self.reaction)
        tau = float(times[hit[0]])
        return v0 + float(u[0]) * tau if tau <= t1 else max(v1 - self.a_brake * (tau - t1), 0.0)

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

    DIM = 3

    def __init__(self, config: SupervisorConfig, radius: float, limits: QuadLimits, period: float,
                 state_names: Sequence[str], loops: SupervisorLoops | None = None) -> None:
        self.limits = limits
        names = tuple(state_names)
        self._p = [names.index(n) for n in ("X", "Y", "Z")]
        self._v = [names.index(n) for n in ("vx", "vy", "vz")]
        self.body = Footprint.sphere(radius)
        super().__init__(config, self.body, period, loops)
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

    def _poses(self, state: np.ndarray, u: np.ndarray, brake: bool, hold: float = 0.0):
        p0, v0, T = state[self._p], state[self._v], self.reaction
        p1, v1 = p0 + v0 * T + 0.5 * u * T * T, v0 + u * T
        speed = float(np.linalg.norm(v1))
        t_stop = speed / self.a_brake
        t_end = T + (t_stop if brake else max(t_stop, 1.0) + hold)
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


def _arc_into(out: np.ndarray, x: float, y: float, heading: float, kappa: float, s: np.ndarray) -> None:
    """Points (K, 2) into out of the arc of curvature kappa from (x, y, heading) at lengths s (K,),
    s ascending from 0."""
    if len(s) == 0:
        return
    if abs(kappa * s[-1]) < STRAIGHT:
        mid = heading + 0.5 * kappa * s
        out[:, 0] = x + s * np.cos(mid)
        out[:, 1] = y + s * np.sin(mid)
        return
    end = heading + kappa * s
    out[:, 0] = x + (np.sin(end) - math.sin(heading)) / kappa
    out[:, 1] = y - (np.cos(end) - math.cos(heading)) / kappa
