"""Perception input: obstacles detected by an external perception stack, received over Zenoh.

Key expression: ``vflpc/<vehicle_id>/perception/obstacles``. Payload: one UTF-8 JSON object
(at most 64 KiB)::

    {"stamp": 1718000000.25,                  # UNIX time (s) at which the positions hold
     "obstacles": [                           # at most 64
        {"id": "ped-3",                       # non-empty string (<= 64 chars), unique
         "shape": {"kind": "circle", "radius": 0.6},   # "circle" (dim 2) | "sphere" (dim 3),
                                                         # 0 < radius < 100 m
         "center": [12.0, 3.5],               # (dim,) world ENU position, m
         "velocity": [0.0, -1.2]}]}           # (dim,) world ENU velocity, m/s

Extra fields are ignored. Numbers must be finite; ``stamp`` may lie at most 1 s in the future
of the receiver's clock. The Zenoh callback validates the message; a valid one replaces the
latest (one assignment), an invalid one is counted in ``rejected`` and reported through
``on_reject(reason)`` (read at call time, so it may be set after construction; it must not
block). ``snapshot`` returns the latest message's obstacles propagated at constant velocity,
or nothing when the message is older than ``max_age_s``.
"""

from __future__ import annotations

import json
import logging
import math
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
MAX_RADIUS_M = 100.0
MAX_FUTURE_S = 1.0
ID_PREFIX = "perception:"
SHAPE_KINDS = {2: ("circle", Circle), 3: ("sphere", Sphere)}


class PerceptionError(ValueError):
    """A perception message that is not valid; ``str(err)`` is the reason."""


@dataclass(frozen=True)
class PerceptionMessage:
    """A validated message: stamp (UNIX s); ids (n,); shapes (n,); centers, velocities (n, dim)."""

    stamp: float
    ids: tuple[str, ...]
    shapes: tuple[object, ...]
    centers: np.ndarray
    velocities: np.ndarray


def parse_message(payload: bytes, dim: int, now_unix: float) -> PerceptionMessage:
    """Parse and validate one payload; raises PerceptionError naming the problem (ValueError
    for a dim other than 2 or 3)."""
    kind, shape_cls = shape_for_dim(dim)
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise PerceptionError(f"payload too large ({len(payload)} bytes > {MAX_PAYLOAD_BYTES})")
    try:
        msg = json.loads(payload)
    except (ValueError, UnicodeDecodeError) as exc:
        raise PerceptionError(f"not valid JSON ({exc})") from None
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
        if not 0.0 < radius < MAX_RADIUS_M:
            raise PerceptionError(f"{where}.shape.radius must be > 0 and < {MAX_RADIUS_M:g} m (got {radius:g})")
        centers[i] = _vector(_get(ob, "center", where), dim, f"{where}.center")
        velocities[i] = _vector(_get(ob, "velocity", where), dim, f"{where}.velocity")
        ids.append(oid)
        shapes.append(shape_cls(radius))
    centers.flags.writeable = velocities.flags.writeable = False
    return PerceptionMessage(stamp, tuple(ids), tuple(shapes), centers, velocities)


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


class PerceptionInput:
    """Subscribes the perception input of ``vehicle_id`` on ``session``.

    dim: 2 (circles) or 3 (spheres); max_age_s: a message older than this is ignored.
    Counters: ``received``, ``accepted``, ``rejected`` (Zenoh thread), ``stale`` (snapshot's
    thread); ``last_reject``: the last reason.
    """

    def __init__(self, session, vehicle_id: str, dim: int, max_age_s: float,
                 on_reject: Callable[[str], None] | None = None) -> None:
        shape_for_dim(dim)
        self.key = key_expressions(vehicle_id)["perception"]
        self.dim, self.max_age_s, self.on_reject = dim, float(max_age_s), on_reject
        self.received = self.accepted = self.rejected = self.stale = 0
        self.last_reject = ""
        self._latest: PerceptionMessage | None = None
        self._sub = session.declare_subscriber(self.key, self._on_sample)

    def _on_sample(self, sample) -> None:
        """Zenoh's thread: validate, then replace the latest message or report the rejection."""
        self.received += 1
        try:
            size = len(sample.payload)
            if size > MAX_PAYLOAD_BYTES:
                raise PerceptionError(f"payload too large ({size} bytes > {MAX_PAYLOAD_BYTES})")
            self._latest = parse_message(sample.payload.to_bytes(), self.dim, time.time())
            self.accepted += 1
            return
        except PerceptionError as exc:
            reason = str(exc)
        except Exception as exc:  # never raise into Zenoh
            reason = f"unreadable message ({type(exc).__name__}: {exc})"
        self.rejected += 1
        self.last_reject = reason
        log.debug("event=perception_rejected reason=%s", reason)
        callback = self.on_reject
        if callback is not None:
            try:
                callback(reason)
            except Exception:
                log.exception("event=perception_on_reject_failed")

    def snapshot(self, now_unix: float, t_mission: float) -> list[ObstacleState]:
        """The latest message's obstacles with centres propagated to ``now_unix`` (UNIX s) at
        constant velocity, stamped ``t_mission`` (mission s), ids prefixed "perception:".
        Returns [] (and counts ``stale``) when no message came or it is older than max_age_s."""
        msg = self._latest
        if msg is None or now_unix - msg.stamp > self.max_age_s:
            self.stale += 1
            return []
        centers = msg.centers + msg.velocities * (now_unix - msg.stamp)
        return [ObstacleState(id=ID_PREFIX + oid, shape=shape, center=centers[i], yaw=0.0,
                              velocity=msg.velocities[i], stamp=t_mission)
                for i, (oid, shape) in enumerate(zip(msg.ids, msg.shapes))]

    def close(self) -> None:
        """Undeclare the subscriber (idempotent)."""
        sub, self._sub = self._sub, None
        if sub is not None:
            try:
                sub.undeclare()
            except Exception:
                pass
