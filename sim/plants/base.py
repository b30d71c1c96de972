"""Input checking shared by the simulated plants."""

from __future__ import annotations

import numpy as np


def checked_vector(value, n: int, what: str) -> np.ndarray:
    """value as a float array of shape (n,); ValueError naming ``what`` if the shape is wrong or a value is not finite."""
    arr = np.asarray(value, dtype=float).ravel()
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be {n} finite numbers, got {np.asarray(value).tolist()!r}")
    return arr
