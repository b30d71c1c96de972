"""What every simulated plant offers the runner, the SITL processes and the in-process driver."""

from __future__ import annotations

from typing import Protocol

import numpy as np


class Plant(Protocol):
    """A simulated robot stepped at a fixed RK4 step with zero-order-hold commands.

    ``state`` is the plant's full state (its ``state_names``); ``step`` saturates the
    command to the actuator limits, records what was applied in ``applied_control`` and
    advances the state by ``dt`` seconds.
    """

    state_names: tuple[str, ...]
    control_names: tuple[str, ...]

    @property
    def state(self) -> np.ndarray: ...

    @property
    def applied_control(self) -> np.ndarray: ...

    def reset(self, x0: np.ndarray) -> None: ...

    def step(self, u: np.ndarray, dt: float) -> np.ndarray: ...

    def position(self) -> np.ndarray:
        """World position of the reference point, shape (2,) or (3,)."""
        ...

    def velocity_world(self) -> np.ndarray:
        """World-frame velocity of the reference point, shape (2,) or (3,)."""
        ...

    def heading(self) -> float:
        """Yaw angle in radians, wrapped to (-pi, pi]."""
        ...


def checked_vector(value, n: int, what: str) -> np.ndarray:
    """value as a float array of shape (n,); ValueError naming ``what`` if the shape is wrong or a value is not finite."""
    arr = np.asarray(value, dtype=float).ravel()
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise ValueError(f"{what} must be {n} finite numbers, got {np.asarray(value).tolist()!r}")
    return arr
