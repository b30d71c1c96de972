"""Angle helpers."""

from __future__ import annotations

import numpy as np


def wrap_angle(a):
    """Wrap angles (scalar or array) to (-pi, pi]."""
    w = np.remainder(np.asarray(a, dtype=float) + np.pi, 2.0 * np.pi) - np.pi
    w = np.where(w <= -np.pi, w + 2.0 * np.pi, w)
    return float(w) if np.ndim(w) == 0 else w
