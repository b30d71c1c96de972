"""Tunable numbers of the guidance level, read from an in-memory TOML table (no file I/O here)."""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from vflpcd.tomlread import Table

_POSITIVE = ("k_p", "k_r", "l1", "l2", "k_c", "beta", "grid_resolution", "corridor", "epsilon", "reactive_margin",
             "horizon", "a_accel", "a_decel", "virtual_buffer", "curvature_use")


@dataclass(frozen=True)
class VirtualObstacleSpec:
    """A hand-placed virtual obstacle (circle): centre (2,), reactive radius, repulsive level c in (-1, 0),
    the actual obstacle it serves (``parent`` id) and its direction gamma (+1 / -1, 0: automatic)."""

    center: np.ndarray
    radius: float
    c: float
    parent: str
    gamma: int


@dataclass(frozen=True)
class GuidanceParams:
    k_p: float
    k_r: float
    l1: float
    l2: float
    k_c: float
    beta: float
    grid_resolution: float
    corridor: float
    epsilon: float
    safety_margin: float
    reactive_margin: float
    horizon: float
    smoothing: float
    a_accel: float
    a_decel: float
    virtual: str
    virtual_buffer: float
    curvature_use: float
    virtual_obstacles: tuple[VirtualObstacleSpec, ...] = ()

    @classmethod
    def from_table(cls, t: Table, base: "GuidanceParams | None" = None) -> "GuidanceParams":
        """Every field from table t, or, with ``base``, only the fields t sets (an override)."""
        names = {f.name for f in fields(cls)}
        t.check_known(names)
        values = {}
        for name in names - {"virtual", "virtual_obstacles"}:
            if base is None or t.has(name):
                values[name] = t.number(name, positive=name in _POSITIVE, min=0.0)
        if base is None or t.has("virtual"):
            values["virtual"] = t.string("virtual", choices=("auto", "off"))
        if t.has("virtual_obstacles"):
            values["virtual_obstacles"] = tuple(_virtual(v) for v in t.tables("virtual_obstacles"))
        return replace(base, **values) if base is not None else cls(**values)


def _virtual(t: Table) -> VirtualObstacleSpec:
    t.check_known({"center", "radius", "c", "parent", "gamma"})
    c = t.number("c")
    if not -1.0 < c < 0.0:
        raise t.error("c", f"expected a repulsive level -1 < c < 0 (c_i < 0), got {c:g}")
    gamma = t.integer("gamma", 0)
    if gamma not in (-1, 0, 1):
        raise t.error("gamma", f"expected -1, 1 or 0 (automatic), got {gamma}")
    return VirtualObstacleSpec(center=t.vector("center", 2), radius=t.number("radius", positive=True), c=c,
                               parent=t.string("parent"), gamma=gamma)
