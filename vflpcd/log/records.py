"""What the daemon produces each tick and at each event: the one data contract of the flight log
(``recorder``), the telemetry (``telemetry``) and the summary.

Every record is a frozen dataclass of plain values (floats, ints, strings, tuples) so that it
can cross threads without copying and ``to_json()`` gives the JSON object that the MCAP log and
the Zenoh payloads carry (schemas in ``docs/telemetry.md``), encoded by ``json_bytes`` as strict
JSON (NaN and infinities become null, which readers turn back into NaN). Times: ``t`` is mission time in
seconds since the control loop started; ``stamp_ns`` is ``time.monotonic_ns()``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass, field
from typing import Any


def json_bytes(obj: Any) -> bytes:
    """Compact UTF-8 JSON; NaN/inf become null, numpy scalars/arrays plain numbers/lists; any other
    value JSON cannot hold raises TypeError (a record carrying one is a bug, not data)."""
    try:
        text = json.dumps(obj, separators=(",", ":"), allow_nan=False, default=_default)
    except ValueError:
        text = json.dumps(_finite(obj), separators=(",", ":"), allow_nan=False, default=_default)
    return text.encode()


def _default(value: Any) -> Any:
    if hasattr(value, "tolist"):  # numpy scalars and arrays
        return _finite(value.tolist())
    raise TypeError(f"{type(value).__name__} is not JSON serializable")


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _plain(value: Any) -> Any:
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    return value


class _Json:
    def to_json(self) -> dict[str, Any]:
        """The record as a JSON-ready dict (tuples become lists)."""
        return _plain(asdict(self))


@dataclass(frozen=True)
class ObstacleRecord(_Json):
    """One obstacle as the controller saw it at the tick: centre (d,), velocity (d,) in the world
    frame (ENU), bounding radius (m), and where it came from ("mission" or "perception")."""

    id: str
    center: tuple[float, ...]
    velocity: tuple[float, ...]
    radius: float
    source: str


@dataclass(frozen=True)
class TickRecord(_Json):
    """One control tick.

    k: tick index; t: mission time (s) of the tick's deadline; stamp_ns: monotonic time at which
    the tick started; mode: "running" | "failsafe" | "stopping"; state: the platform state used
    (its ``state_names`` order), () when there was none; state_age_s: age of that state at the tick
    start; reference: the reference position (d,) of the current plan at t, () without one;
    command: the command sent (``control_names`` order), () when none was sent; lateness_s: tick
    start minus its deadline; compute_s: the controller step's wall time; overrun: the tick's
    work (start to command handed over) ended after the next deadline; threats: ids of the moving
    obstacles whose barrier is on; plan_version: guidance plans installed; model_version: GP
    models installed; obstacles: what the controller was given.
    """

    k: int
    t: float
    stamp_ns: int
    mode: str
    state: tuple[float, ...]
    state_age_s: float
    reference: tuple[float, ...]
    command: tuple[float, ...]
    lateness_s: float
    compute_s: float
    overrun: bool
    threats: tuple[str, ...] = ()
    plan_version: int = 0
    model_version: int = 0
    obstacles: tuple[ObstacleRecord, ...] = ()


@dataclass(frozen=True)
class Event(_Json):
    """Something that happened once: kind is one of ``EVENT_KINDS``; detail holds JSON values."""

    t: float
    stamp_ns: int
    kind: str
    detail: dict[str, Any] = field(default_factory=dict)


EVENT_KINDS = (
    "started",            # the control loop started (detail: rate_hz, controller)
    "ready",              # platform connected and enabled, first state received
    "failsafe",           # detail: reason, action
    "replan_failed",      # detail: reason
    "worker_error",       # detail: job, reason
    "perception_rejected",  # detail: count, total, reason (aggregated, at most once a second)
    "perception_dropped",   # detail: count, total, budget_hz (over the message budget; at most once a second)
    "supervisor_brake",   # the safety supervisor overrode the command (detail: reason, obstacle, clearance_m)
    "supervisor_release",  # ... and handed it back (detail: obstacle, clearance_m)
    "mission_complete",   # detail: progress_m
    "stopping",           # detail: reason (signal name, mission_complete, failsafe)
    "link_stats",         # the platform link's counters at the end (frames, bad frames by kind, setpoints, ...)
    "log_stopped",        # the flight log only: a write error stopped the recorder (detail: reason, errno)
)


@dataclass(frozen=True)
class MissionHeader(_Json):
    """Written once at the start of a log and published on ``events`` at start-up.

    path: reference-path points (K, d); obstacles: the mission's obstacles with their top-view
    outline polygon ((n, 2) points, closed) for plots, initial centre, velocity, radius.
    """

    vehicle_id: str
    platform: str
    controller: str
    dim: int
    rate_hz: float
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    path: tuple[tuple[float, ...], ...]
    obstacles: tuple[dict, ...]
    mission_file: str
    model_file: str = ""
