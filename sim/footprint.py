"""The robot's collision body, as covering discs (2-D) or a sphere (3-D).

A rectangle L x W is covered by n discs whose centres lie on the body's long axis at the
middle of n equal slices, each of radius sqrt((L / 2n)^2 + (W / 2)^2). This is the usual
conservative cover used in motion planning: clearance computed with it is never larger
than the true clearance of the rectangle (it is smaller by at most r - W / 2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Footprint:
    """offsets: (n,) disc centres along body x from the reference point (m); radius: disc radius (m)."""

    offsets: np.ndarray
    radius: float
    dim: int

    @classmethod
    def rectangle(cls, length: float, width: float, rear_to_reference: float, n: int = 3) -> "Footprint":
        """Cover of a car body whose rear bumper lies rear_to_reference metres behind the reference point."""
        half = length / (2 * n)
        offsets = -rear_to_reference + half * (2 * np.arange(n) + 1)
        return cls(offsets=offsets, radius=float(np.hypot(half, width / 2)), dim=2)

    @classmethod
    def sphere(cls, radius: float) -> "Footprint":
        return cls(offsets=np.zeros(1), radius=float(radius), dim=3)

    def centers(self, position: np.ndarray, yaw: float) -> np.ndarray:
        """Disc centres in the world, shape (n, dim), for a reference point position (dim,) and yaw."""
        axis = np.zeros(self.dim)
        axis[0], axis[1] = np.cos(yaw), np.sin(yaw)
        return np.asarray(position, float)[None, :] + self.offsets[:, None] * axis[None, :]

    def clearance(self, shape, center: np.ndarray, shape_yaw: float, position: np.ndarray, yaw: float) -> float:
        """Gap between the body and an obstacle's physical boundary (negative: overlap), metres."""
        return float(np.min(shape.signed_distance(self.centers(position, yaw), center, shape_yaw)) - self.radius)
