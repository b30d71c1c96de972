"""What a controller knows about an obstacle at one instant."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ObstacleState:
    """A perceived obstacle at time ``stamp``.

    shape: a shape from ``vflpcd.core.shapes`` (its physical boundary, body frame);
    center: (d,) world position; yaw: body-frame rotation about z (rad);
    velocity: (d,) world velocity (zero for a static obstacle), so that the centre at
    time t is ``center + velocity * (t - stamp)``.
    """

    id: str
    shape: object
    center: np.ndarray
    yaw: float
    velocity: np.ndarray
    stamp: float

    def center_at(self, t: float) -> np.ndarray:
        """Constant-velocity prediction of the centre at time t, shape (d,)."""
        return self.center + self.velocity * (t - self.stamp)

    def signed_distance(self, points: np.ndarray, t: float | None = None) -> np.ndarray:
        """Signed distance of points (..., d) to the physical boundary at time t (default: stamp)."""
        c = self.center if t is None else self.center_at(t)
        return self.shape.signed_distance(points, c, self.yaw)

    def distance_and_normal(self, points: np.ndarray, t: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (...) of points (..., d) at time t (default: stamp) and its unit gradient
        (..., d), the outward normal at the nearest boundary point (``Shape.distance_and_normal``)."""
        c = self.center if t is None else self.center_at(t)
        return self.shape.distance_and_normal(points, c, self.yaw)

    @property
    def moving(self) -> bool:
        """Whether any velocity component is non-zero."""
        return any(self.velocity.tolist())
