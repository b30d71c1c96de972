"""The robot's collision body: a rectangle (car) or a sphere (quadrotor).

Clearance to an obstacle is the smallest signed distance from the body's outline to the
obstacle's physical boundary: for the car, points every 5 cm along the rectangle's perimeter
(exact to within the sampling, about 1 mm, for the convex obstacles of the scenarios; a
negative value means overlap, and an obstacle wholly inside the outline counts minus the
shortest push that moves it out through a side), for the quadrotor the sphere's centre
distance minus its radius.

Planners that need a quick, conservative test use the covering discs instead: n discs whose
centres lie on the body's long axis at the middle of n equal slices, each of radius
sqrt((L / 2n)^2 + (W / 2)^2); they contain the rectangle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Footprint:
    """offsets: (n,) covering-disc centres along body x from the reference point (m); radius: their
    radius (m); outline: (K, dim) body-frame points of the collision body's boundary (2-D), empty for a sphere."""

    offsets: np.ndarray
    radius: float
    dim: int
    outline: np.ndarray

    @classmethod
    def rectangle(cls, length: float, width: float, rear_to_reference: float, n: int = 3,
                  spacing: float = 0.05) -> "Footprint":
        """A car body whose rear bumper lies rear_to_reference metres behind the reference point."""
        half = length / (2 * n)
        offsets = -rear_to_reference + half * (2 * np.arange(n) + 1)
        x0, x1, w = -rear_to_reference, length - rear_to_reference, width / 2
        corners = np.array([[x0, -w], [x1, -w], [x1, w], [x0, w], [x0, -w]])
        pts = []
        for a, b in zip(corners[:-1], corners[1:]):
            k = max(int(np.ceil(np.linalg.norm(b - a) / spacing)), 1)
            pts.append(a + np.linspace(0.0, 1.0, k, endpoint=False)[:, None] * (b - a))
        return cls(offsets=offsets, radius=float(np.hypot(half, w)), dim=2, outline=np.vstack(pts))

    def with_discs(self, n: int) -> "Footprint":
        """The same body covered by n discs (a tighter cover for larger n); a sphere is returned as it is."""
        if self.dim == 3:
            return self
        lo, hi = self.outline.min(axis=0), self.outline.max(axis=0)
        return Footprint.rectangle(float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(-lo[0]), n)

    @classmethod
    def sphere(cls, radius: float) -> "Footprint":
        return cls(offsets=np.zeros(1), radius=float(radius), dim=3, outline=np.zeros((0, 3)))

    def _axis(self, yaw: float) -> np.ndarray:
        axis = np.zeros(self.dim)
        axis[0], axis[1] = np.cos(yaw), np.sin(yaw)
        return axis

    def centers(self, position: np.ndarray, yaw: float) -> np.ndarray:
        """Covering-disc centres in the world, shape (n, dim), for a reference point position (dim,) and yaw."""
        return np.asarray(position, float)[None, :] + self.offsets[:, None] * self._axis(yaw)[None, :]

    def body_points(self, position: np.ndarray, yaw: float) -> np.ndarray:
        """The rectangle's outline in the world, shape (K, 2)."""
        c, s = np.cos(yaw), np.sin(yaw)
        return np.asarray(position, float)[None, :] + self.outline @ np.array([[c, s], [-s, c]])

    def clearance(self, shape, center: np.ndarray, shape_yaw: float, position: np.ndarray, yaw: float) -> float:
        """Gap between the body and an obstacle's physical boundary (negative: overlap), metres."""
        if self.dim == 3:
            return float(shape.signed_distance(np.asarray(position, float)[None, :], center, shape_yaw)[0] - self.radius)
        gap = float(np.min(shape.signed_distance(self.body_points(position, yaw), center, shape_yaw)))
        if gap <= 0.0:
            return gap
        c, s = np.cos(yaw), np.sin(yaw)
        local = (shape.outline(center, shape_yaw) - np.asarray(position, float)) @ np.array([[c, -s], [s, c]])
        lo, hi = self.outline.min(axis=0), self.outline.max(axis=0)
        if np.all(local >= lo) and np.all(local <= hi):
            # the obstacle lies wholly inside the body: minus the shortest push out through a side
            return -float(min(np.max(local[:, 0]) - lo[0], hi[0] - np.min(local[:, 0]),
                              np.max(local[:, 1]) - lo[1], hi[1] - np.min(local[:, 1])))
        return gap
