"""Tunable numbers of the guidance level (``vflpcd.config.params`` reads them from config/guidance.toml)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np



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
    margin_per_speed: float = 0.0
    mover_margin_time: float = 0.0
    reactive_per_speed: float = 0.0
    recovery_margin: float = 0.1
    recovery_reactive_margin: float = 0.5
    recovery_tight_margin: float = 0.3
    least_tight_margin: float = 0.15
    tight_length: float = 0.0
    tight_margin: float = 0.4
    tight_mover_window: float = 0.0
    a_yield: float = 4.0
    virtual_obstacles: tuple[VirtualObstacleSpec, ...] = ()
