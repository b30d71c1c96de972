"""The known obstacles of one tick as arrays, for the supervisor's distance tests.

``ObstacleArrays.of(obstacles)`` stacks their centres, velocities and stamps, and per shape (cached,
shapes are frozen) the bounding radius, the half-extents of the body-frame bounding box and the
closed form of the signed distance where the shape has one (``Shape.closed_form``: circles and
spheres are round, boxes are boxes). Then:

- ``gap_bound(p)``: a lower bound of each obstacle's signed distance from one point, in one array
  step: the larger of the bounding-circle distance and the distance to the oriented bounding box
  (exact for circles, spheres and boxes; a wall's bounding circle alone says little);
- ``signed_distance(points)``: the exact signed distance of per-obstacle point sets, in closed form
  for round and box shapes, through the shape's own ``signed_distance`` for the others.

Yaw rotates the body frame about the world z axis, as in ``vflpcd.core.shapes``.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from vflpcd.core.obstacles import ObstacleState

_SHAPE_ROWS: dict = {}        # (id(shape), yaw) -> (shape, its row): the shape held, so its id is not reused
ROUND, BOX, OTHER = 0, 1, 2
_FORMS = {"round": ROUND, "box": BOX}


def _shape_row(shape, yaw: float) -> tuple:
    """(bounding radius, cos, sin, form code, *half-extents) of a shape at yaw; kept by the shape
    object's identity (hashing a frozen shape's fields cost more than the lookup)."""
    key = (id(shape), yaw)
    held = _SHAPE_ROWS.get(key)
    if held is not None and held[0] is shape:
        return held[1]
    if len(_SHAPE_ROWS) > 4096:
        _SHAPE_ROWS.clear()
    row = (float(shape.bounding_radius()), math.cos(yaw), math.sin(yaw), _FORMS.get(shape.closed_form, OTHER),
           *(float(h) for h in shape.support_extent()))
    _SHAPE_ROWS[key] = (shape, row)
    return row


class ObstacleArrays:
    """n obstacles of dimension d (``states``, n,), as two arrays whose columns the properties name:
    motion (n, 2d + 1): centre, velocity, stamp; shape (n, 4 + d): bounding radius, cos and sin of
    the yaw, form code (ROUND, BOX, OTHER), bounding-box half-extents."""

    __slots__ = ("states", "motion", "shape", "d", "moving")

    def __init__(self, states: tuple, motion: np.ndarray, shape: np.ndarray, d: int) -> None:
        self.states, self.motion, self.shape, self.d = states, motion, shape, d
        self.moving = (self.velocity != 0.0).any(axis=1)

    @classmethod
    def of(cls, obstacles: Sequence[ObstacleState], d: int) -> ObstacleArrays:
        """The obstacles of a d-dimensional world (their shapes' dimension)."""
        rows = np.array([(*o.center.tolist(), *o.velocity.tolist(), o.stamp, *_shape_row(o.shape, float(o.yaw)))
                         for o in obstacles], float).reshape(-1, 3 * d + 5)
        return cls(tuple(obstacles), np.ascontiguousarray(rows[:, :2 * d + 1]), np.ascontiguousarray(rows[:, 2 * d + 1:]),
                   d)

    def __len__(self) -> int:
        return len(self.states)

    def subset(self, keep: np.ndarray) -> ObstacleArrays:
        """The obstacles where keep (n,) bool is true."""
        return ObstacleArrays(tuple(o for o, k in zip(self.states, keep) if k), self.motion[keep], self.shape[keep],
                              self.d)

    centers = property(lambda self: self.motion[:, :self.d])
    velocity = property(lambda self: self.motion[:, self.d:2 * self.d])
    stamps = property(lambda self: self.motion[:, 2 * self.d])
    bound = property(lambda self: self.shape[:, 0])
    form = property(lambda self: self.shape[:, 3])

    def stand_as(self, other: ObstacleArrays | None) -> bool:
        """Whether ``other`` holds the same obstacles (ids and shapes) with the same centres, velocities
        and yaws (their stamps aside)."""
        d2 = 2 * self.d
        return (other is not None and len(self.states) == len(other.states)
                and np.array_equal(self.motion[:, :d2], other.motion[:, :d2])
                and np.array_equal(self.shape, other.shape)
                and all(a.id == b.id and a.shape == b.shape for a, b in zip(self.states, other.states)))

    @property
    def closed(self) -> bool:
        """Whether every shape has a closed form here (round or box)."""
        return not (self.shape[:, 3] == OTHER).any()

    def _box(self, rel: np.ndarray) -> np.ndarray:
        """Signed distance of offsets rel (n, ..., d) from the centres to each obstacle's oriented
        bounding box, shape (n, ...)."""
        extra = (slice(None),) + (None,) * (rel.ndim - 2)
        c, s, hx, hy = (self.shape[:, j][extra] for j in (1, 2, 4, 5))
        x, y = rel[..., 0], rel[..., 1]
        qx = np.abs(c * x + s * y) - hx            # body frame: R(yaw)^T rel
        qy = np.abs(c * y - s * x) - hy
        inside = np.maximum(qx, qy)
        outside = np.square(np.maximum(qx, 0.0)) + np.square(np.maximum(qy, 0.0))
        if self.d == 3:
            qz = np.abs(rel[..., 2]) - self.shape[:, 6][extra]
            inside = np.maximum(inside, qz)
            outside += np.square(np.maximum(qz, 0.0))
        return np.sqrt(outside) + np.minimum(inside, 0.0)

    def gap_bound(self, p: np.ndarray) -> np.ndarray:
        """A lower bound (n,) of each obstacle's signed distance from point p (d,), at its stamp."""
        rel = p - self.centers
        return np.maximum(np.sqrt((rel * rel).sum(axis=1)) - self.bound, self._box(rel))

    def signed_distance(self, points: np.ndarray) -> np.ndarray:
        """Exact signed distance (n, M) of points (n, M, d), row i to obstacle i at its stamp."""
        rel = points - self.centers[:, None, :]
        form = self.form
        if (form == ROUND).all():
            return np.sqrt((rel * rel).sum(axis=-1)) - self.bound[:, None]
        out = self._box(rel)
        for i in np.flatnonzero(form != BOX):
            o = self.states[i]
            out[i] = (np.sqrt((rel[i] * rel[i]).sum(axis=-1)) - self.bound[i] if form[i] == ROUND else
                      o.shape.signed_distance(points[i], self.centers[i], o.yaw))
        return out
