"""Fixed-step Runge–Kutta 4 integration with zero-order-hold inputs."""

from __future__ import annotations

import math
from typing import Callable

import numpy as np

Dynamics = Callable[[np.ndarray, np.ndarray], np.ndarray]


def rk4_step(f: Dynamics, x: np.ndarray, u: np.ndarray, h: float) -> np.ndarray:
    """One classical RK4 step of x' = f(x, u) with u held constant.

    x: (n,), u: (m,), h: step in seconds. Returns x after h, shape (n,).
    """
    k1 = f(x, u)
    k2 = f(x + 0.5 * h * k1, u)
    k3 = f(x + 0.5 * h * k2, u)
    k4 = f(x + h * k3, u)
    return x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def substeps(dt: float, max_step: float) -> tuple[int, float]:
    """Split an interval dt into n equal RK4 steps no longer than max_step: (n, dt / n)."""
    if not (dt > 0.0 and math.isfinite(dt)):
        raise ValueError(f"integration interval must be positive and finite, got {dt!r}")
    n = max(1, math.ceil(dt / max_step - 1e-9))
    return n, dt / n
