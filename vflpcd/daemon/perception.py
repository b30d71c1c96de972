"""Perception input: obstacles detected by an external perception stack, received over Zenoh.

Key expression: ``vflpc/<vehicle_id>/perception/obstacles``. Payload: one UTF-8 JSON object
(at most 64 KiB)::

    {"stamp": 1718000000.25,                  # UNIX time (s) at which the positions hold
     "obstacles": [                           # at most 64
        {"id": "ped-3",                       # non-empty string (<= 64 chars), unique
         "shape": {"kind": "circle", "radius": 0.6},   # "circle" (dim 2) | "sphere" (dim 3),
                                                         # 0 < radius < limits.max_radius
         "center": [12.0, 3.5],               # (dim,) world ENU position, m, inside limits' area
         "velocity": [0.0, -1.2]}]}           # (dim,) world ENU velocity, m/s, speed <= limits.max_speed

Extra fields are ignored. Numbers must be finite; ``stamp`` may lie at most 1 s in the future
of the receiver's clock. ``PerceptionLimits`` bound the magnitudes by the mission's world (the
route's bounding box grown by a margin, a top speed, a largest radius), so that no value can
overflow when it is propagated or planned with.

The Zenoh callback first spends the message budget (``MessageBudget``, a token bucket of
``rate_hz`` messages a second): a message beyond it is dropped before it is parsed and counted in
``dropped``. A message within it is validated; a valid one replaces the latest (one assignment),
an invalid one is counted in ``rejected`` (``last_reject``: its reason). Drops and rejections are
reported through ``on_event(kind, detail)`` (read at call time, so it may be set after
construction; it must not block) at most once per ``report_period_s`` and kind, aggregated:
``perception_dropped`` {count, total, budget_hz} and ``perception_rejected`` {count, total, reason};
the first of a quiet period is reported at once. Reports are due from the Zenoh callback, from
``snapshot`` (the control thread, every tick) and at ``close``. ``snapshot`` returns the latest
message's obstacles propagated at constant velocity, or nothing when the message is older than
``max_age_s``.
"""

from __future__ import annotations

import json
import logging
import math
import threading
import time
from dataclasses import dataclass
from typing import Any, Callable

import numpy as np

from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Circle, Sphere
from vflpcd.daemon.telemetry import key_expressions

log = logging.getLogger("vflpcd.daemon.perception")

MAX_PAYLOAD_BYTES = 64 * 1024
MAX_OBSTACLES = 64
MAX_ID_CHARS = 64
MAX_FUTURE_S = 1.0
ID_PREFIX = "perception:"
SHAPE_KINDS = {2: ("circle", Circle), 3: ("sphere", Sphere)}
AREA_STEP_M = 0.5          # spacing of the route points whose bounding box spans the area
REPORT_PERIOD_S = 1.0
DROPPED, REJECTED = "perception_dropped", "perception_rejected"


class PerceptionError(ValueError):
    """A perception message that is not valid; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class PerceptionLimits:
    """What a perceived obstacle may be: its centre inside the box ``lo`` .. ``hi`` ((dim,), m,
    world ENU), its speed at most ``max_speed`` (m/s), its radius below ``max_radius`` (m)."""

    lo: np.ndarray
    hi: np.ndarray
    max_speed: float
    max_radius: float

    @classmethod
    def around(cls, path, margin: float, max_speed: float, max_radius: float) -> PerceptionLimits:
        """The limits of a mission on the reference ``path`` (``.point_at(s)``, ``.length``): the
        bounding box of its points (every AREA_STEP_M m) grown by ``margin`` m on every side."""
        n = max(2, int(math.ceil(path.length / AREA_STEP_M)) + 1)
        pts = np.atleast_2d(path.point_at(np.linspace(0.0, path.length, n)))
        return cls(lo=pts.min(axis=0) - margin, hi=pts.max(axis=0) + margin, max_speed=float(max_speed),
                   max_radius=float(max_radius))

    @property
    def dim(self) -> int:
        return len(self.lo)

    def describe_area(self) -> str:
        """The area as text, e.g. "x in [-50, 250], y in [-50, 50] m"."""
        return ", ".join(f"{axis} in [{a:g}, {b:g}]" for axis, a, b in zip("xyz", self.lo, self.hi)) + " m"


@dataclass(frozen=True)
class PerceptionMessage:
    """A validated message: stamp (UNIX s); ids (n,); shapes (n,); centers, velocities (n, dim)."""

    stamp: float
    ids: tuple[str, ...]
    shapes: tuple[object, ...]
    centers: np.ndarray
    velocities: np.ndarray


def parse_message(payload: bytes, dim: int, now_unix: float, limits: PerceptionLimits) -> PerceptionMessage:
    """Parse and validate one payload against ``limits``; raises PerceptionError naming the
    problem (ValueError for a dim other than 2 or 3, or limits of another dim)."""
    kind, shape_cls = shape_for_dim(dim)
    if limits.dim != dim:
        raise ValueError(f"perception limits of dim {limits.dim} for a dim {dim} input")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise PerceptionError(f"payload too large ({len(payload)} bytes > {MAX_PAYLOAD_BYTES})")
    try:
        msg = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PerceptionError(f"not valid JSON ({exc})") from None
    except RecursionError:
        raise PerceptionError("JSON nested too deeply") from None
    if not isinstance(msg, dict):
        raise PerceptionError(f"payload is not a JSON object (got {type(msg).__name__})")
    stamp = _number(_get(msg, "stamp", ""), "stamp")
    if stamp > now_unix + MAX_FUTURE_S:
        raise PerceptionError(f"stamp is {stamp - now_unix:.3f} s in the future (at most {MAX_FUTURE_S:g} s allowed)")
    items = _get(msg, "obstacles", "")
    if not isinstance(items, list):
        raise PerceptionError(f"obstacles must be a list (got {type(items).__name__})")
    if len(items) > MAX_OBSTACLES:
        raise PerceptionError(f"too many obstacles ({len(items)} > {MAX_OBSTACLES})")
    ids, shapes = [], []
    centers, velocities = np.zeros((len(items), dim)), np.zeros((len(items), dim))
    for i, ob in enumerate(items):
        where = f"obstacles[{i}]"
        if not isinstance(ob, dict):
            raise PerceptionError(f"{where} must be an object (got {type(ob).__name__})")
        oid = _get(ob, "id", where)
        if not isinstance(oid, str) or not oid or len(oid) > MAX_ID_CHARS:
            raise PerceptionError(f"{where}.id must be a non-empty string of at most {MAX_ID_CHARS} characters")
        if oid in ids:
            raise PerceptionError(f"{where}.id {oid!r} is a duplicate id")
        shape = _get(ob, "shape", where)
        if not isinstance(shape, dict):
            raise PerceptionError(f"{where}.shape must be an object (got {type(shape).__name__})")
        if _get(shape, "kind", f"{where}.shape") != kind:
            raise PerceptionError(f"{where}.shape.kind must be {kind!r} for dim {dim} (got {shape['kind']!r})")
        radius = _number(_get(shape, "radius", f"{where}.shape"), f"{where}.shape.radius")
        if not 0.0 < radius < limits.max_radius:
            raise PerceptionError(f"{where}.shape.radius must be > 0 and < {limits.max_radius:g} m "
                                  f"(perception_max_radius; got {radius:g})")
        centers[i] = _vector(_get(ob, "center", where), dim, f"{where}.center")
        velocities[i] = _vector(_get(ob, "velocity", where), dim, f"{where}.velocity")
        ids.append(oid)
        shapes.append(shape_cls(radius))
    _check_magnitudes(centers, velocities, limits)
    centers.flags.writeable = velocities.flags.writeable = False
    return PerceptionMessage(stamp, tuple(ids), tuple(shapes), centers, velocities)


def _check_magnitudes(centers: np.ndarray, velocities: np.ndarray, limits: PerceptionLimits) -> None:
    """Centres (n, dim) inside the area, speeds at most max_speed; PerceptionError naming the first
    obstacle that is not. Components are compared first, so a norm cannot overflow."""
    outside = np.flatnonzero(np.any((centers < limits.lo) | (centers > limits.hi), axis=1))
    if outside.size:
        i = int(outside[0])
        raise PerceptionError(f"obstacles[{i}].center {_fmt(centers[i])} lies outside the perception area "
                              f"{limits.describe_area()} (the route's bounding box grown by perception_area_margin_m)")
    fast = np.any(np.abs(velocities) > limits.max_speed, axis=1)
    fast |= np.linalg.norm(np.where(fast[:, None], 0.0, velocities), axis=1) > limits.max_speed
    if np.any(fast):
        i = int(np.flatnonzero(fast)[0])
        raise PerceptionError(f"obstacles[{i}].velocity {_fmt(velocities[i])} is faster than "
                              f"{limits.max_speed:g} m/s (perception_max_speed)")


def _fmt(v: np.ndarray) -> str:
    return "[" + ", ".join(f"{x:.6g}" for x in v) + "]"


def shape_for_dim(dim: int) -> tuple[str, type]:
    """("circle", Circle) for dim 2, ("sphere", Sphere) for dim 3; ValueError otherwise."""
    if dim not in SHAPE_KINDS:
        raise ValueError(f"perception input needs dim 2 or 3, got {dim!r}")
    return SHAPE_KINDS[dim]


def _get(obj: dict, key: str, where: str) -> Any:
    if key not in obj:
        raise PerceptionError(f"missing field {where + '.' if where else ''}{key}")
    return obj[key]


def _number(value: Any, name: str) -> float:
    try:
        x = float(value) if isinstance(value, (int, float)) and not isinstance(value, bool) else math.nan
    except OverflowError:
        x = math.nan
    if not math.isfinite(x):
        raise PerceptionError(f"{name} must be a finite number (got {str(value)[:40]})")
    return x


def _vector(value: Any, dim: int, name: str) -> list[float]:
    if not isinstance(value, list) or len(value) != dim:
        got = f"{len(value)} values" if isinstance(value, list) else type(value).__name__
        raise PerceptionError(f"{name} must be a list of {dim} numbers for dim {dim} (got {got})")
    return [_number(v, f"{name}[{j}]") for j, v in enumerate(value)]


class MessageBudget:
    """A token bucket: ``rate_hz`` messages a second on average, bursts of up to ``burst`` (default
    a tenth of a second's budget, at least 2) so that a sender at the budget's rate with some
    jitter loses nothing. ``take(now)`` (monotonic s) spends one token; False when none is left."""

    def __init__(self, rate_hz: float, burst: float | None = None) -> None:
        if not rate_hz > 0:
            raise ValueError(f"message budget needs a positive rate, got {rate_hz!r}")
        self.rate_hz = float(rate_hz)
        self.capacity = float(burst) if burst is not None else max(2.0, 0.1 * self.rate_hz)
        self._tokens = self.capacity
        self._last: float | None = None

    def take(self, now: float) -> bool:
        if self._last is not None:
            self._tokens = min(self.capacity, self._tokens + max(0.0, now - self._last) * self.rate_hz)
        self._last = now
        if self._tokens < 1.0:
            return False
        self._tokens -= 1.0
        return True


class PerceptionInput:
    """Subscribes the perception input of ``vehicle_id`` on ``session``.

    dim: 2 (circles) or 3 (spheres); max_age_s: a message older than this is ignored; limits:
    the magnitudes a message must keep to; rate_hz: the message budget (messages a second).
    Counters: ``received`` (every message), ``dropped`` (beyond the budget, not parsed),
    ``accepted``, ``rejected`` (Zenoh thread), ``stale`` (snapshot's thread), ``reported``
    (events passed to ``on_event``); ``last_reject``: the last reason.
    """

    def __init__(self, session, vehicle_id: str, dim: int, max_age_s: float, limits: PerceptionLimits,
                 rate_hz: float, on_event: Callable[[str, dict], None] | None = None,
                 report_period_s: float = REPORT_PERIOD_S) -> None:
        shape_for_dim(dim)
        if limits.dim != dim:
            raise ValueError(f"perception limits of dim {limits.dim} for a dim {dim} input")
        self.key = key_expressions(vehicle_id)["perception"]
        self.dim, self.max_age_s, self.limits, self.on_event = dim, float(max_age_s), limits, on_event
        self.budget = MessageBudget(rate_hz)
        self.report_period_s = float(report_period_s)
        self.received = self.dropped = self.accepted = self.rejected = self.stale = self.reported = 0
        self.last_reject = ""
        self._latest: PerceptionMessage | None = None
        self._told = {DROPPED: 0, REJECTED: 0}              # totals at the last report of each kind
        self._next_report = {DROPPED: -math.inf, REJECTED: -math.inf}
        self._report_lock = threading.Lock()
        self._sub = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample) -> None:
        """Zenoh's thread: spend the budget (else drop), validate, then replace the latest message
        or count the rejection; then any report that is due."""
        self.received += 1
        now = time.monotonic()
        if not self.budget.take(now):
            self.dropped += 1
        else:
            self._handle(sample)
        self._report(now)

    def _handle(self, sample) -> None:
        try:
            size = len(sample.payload)
            if size > MAX_PAYLOAD_BYTES:
                raise PerceptionError(f"payload too large ({size} bytes > {MAX_PAYLOAD_BYTES})")
            self._latest = parse_message(sample.payload.to_bytes(), self.dim, time.time(), self.limits)
            self.accepted += 1
            return
        except PerceptionError as exc:
            reason = str(exc)
        except Exception as exc:  # never raise into Zenoh
            reason = f"unreadable message ({type(exc).__name__}: {exc})"
        self.last_reject = reason
        self.rejected += 1

    def _report(self, now: float, force: bool = False) -> None:
        """Pass the drops and rejections counted since the last report of each kind to ``on_event``,
        once ``report_period_s`` has passed since that report (``force``: whatever is left). Never
        blocks: a report already being made by another thread is left to it."""
        told, due = self._told, self._next_report
        if not force and not ((self.dropped > told[DROPPED] and now >= due[DROPPED])
                              or (self.rejected > told[REJECTED] and now >= due[REJECTED])):
            return
        if not self._report_lock.acquire(blocking=force):
            return
        try:
            for kind, total in ((DROPPED, self.dropped), (REJECTED, self.rejected)):
                count = total - told[kind]
                if count <= 0 or (now < due[kind] and not force):
                    continue
                told[kind], due[kind] = total, now + self.report_period_s
                detail: dict[str, Any] = {"count": count, "total": total}
                if kind == DROPPED:
                    detail["budget_hz"] = self.budget.rate_hz
                else:
                    detail["reason"] = self.last_reject[:200]
                self._emit(kind, detail)
        finally:
            self._report_lock.release()

    def _emit(self, kind: str, detail: dict) -> None:
        self.reported += 1
        callback = self.on_event
        if callback is None:
            log.info("event=%s %s", kind, " ".join(f"{k}={v}" for k, v in detail.items()))
            return
        try:
            callback(kind, detail)
        except Exception:
            log.exception("event=perception_on_event_failed kind=%s", kind)

    def snapshot(self, now_unix: float, t_mission: float) -> list[ObstacleState]:
        """The latest message's obstacles with centres propagated to ``now_unix`` (UNIX s) at
        constant velocity, stamped ``t_mission`` (mission s), ids prefixed "perception:".
        Returns [] (and counts ``stale``) when no message came or it is older than max_age_s.
        Makes any report that is due."""
        self._report(time.monotonic())
        msg = self._latest
        if msg is None or now_unix - msg.stamp > self.max_age_s:
            self.stale += 1
            return []
        centers = msg.centers + msg.velocities * (now_unix - msg.stamp)
        return [ObstacleState(id=ID_PREFIX + oid, shape=shape, center=centers[i], yaw=0.0,
                              velocity=msg.velocities[i], stamp=t_mission)
                for i, (oid, shape) in enumerate(zip(msg.ids, msg.shapes))]

    def close(self) -> None:
        """Undeclare the subscriber, then report what is left (idempotent)."""
        sub, self._sub = self._sub, None
        if sub is None:
            return
        try:
            sub.undeclare()
        except Exception:
            pass
        self._report(time.monotonic(), force=True)
