"""Obstacle shapes with exact Euclidean signed distances.

Each shape is a frozen dataclass defined in its own body frame, centred at the
origin; the pose (``center`` and ``yaw``, a rotation of the body frame about the
world z axis) is passed per call.  Units are SI, arrays float64, world frame ENU.

``signed_distance`` returns the exact Euclidean distance to the boundary,
negative inside and positive outside (inside it is minus the distance to the
nearest boundary point, not a bound):

* circle / sphere: ``|p| - r``;
* box / box3 / cylinder: the exact box distance ``|max(q, 0)| + min(max_i q_i, 0)``
  with ``q = |p| - h`` (for the cylinder in the (radial, z) half plane) [2];
* ellipse / ellipsoid: the robust method of Eberly [1]: reflect into the first
  quadrant/octant, sort the semi-axes ``e_0 >= ... >= e_m``, and solve the
  Lagrange condition ``x_i = e_i^2 y_i / (t + e_i^2)`` for the unique root
  ``t > -e_m^2`` of the strictly decreasing function
  ``F(t) = sum_i (e_i y_i / (t + e_i^2))^2 - 1``, by vectorised bisection.
  We bisect on ``u = (t + e_m^2) / e_m^2`` (Eberly's ``s + 1``) so that the
  closest-point coordinate ``x_m = y_m / u`` keeps full relative precision when
  ``y_m`` is tiny.  Points with ``y_m == 0`` (on the plane of the largest axes)
  use Eberly's closed-form branches.  The same root is the nearest point inside.

``distance_and_normal`` returns the signed distance with its unit gradient (the outward normal
at the nearest boundary point): in closed form for circles, spheres, boxes and box3s, from the
nearest point of the same root for ellipses and ellipsoids, by central differences (step
``NORMAL_FD_STEP``) of the signed distance otherwise (cylinders); where the gradient
vanishes (the centre of a round shape, a point on a medial axis) the direction from the centre
(or body x at the centre) stands in.

References
----------
[1] D. Eberly, "Distance from a Point to an Ellipse, an Ellipsoid, or a
    Hyperellipsoid", Geometric Tools, 2013 (rev. 2020),
    https://www.geometrictools.com/Documentation/DistancePointEllipseEllipsoid.pdf
[2] I. Quilez, "Distance functions", https://iquilezles.org/articles/distfunctions/
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

import numpy as np

__all__ = [
    "Shape", "Shape2D", "Circle", "Ellipse", "Box", "Sphere", "Ellipsoid", "Box3",
    "Cylinder", "SHAPES_2D", "SHAPES_3D", "shape_from_table", "top_view",
]

_ROOT_MAX_ITERS = 100  # Newton steps of the ellipse/ellipsoid distance (it stops once converged)
_MIN_OUTLINE_POINTS = 5


# --------------------------------------------------------------------------- helpers
NORMAL_FD_STEP = 1e-5  # m, central differences of the signed distance for its normal (shapes without a closed form)


def _box_sd(q: np.ndarray) -> np.ndarray:
    """Exact box signed distance from ``q = |p| - half_extent``; q (N, k) -> (N,)."""
    return np.linalg.norm(np.maximum(q, 0.0), axis=-1) + np.minimum(q.max(axis=-1), 0.0)


def _box_sd_normal(p: np.ndarray, half: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Box signed distance and its unit gradient at body points p (N, k) of a box of half extents
    ``half`` (k,): outside along the offset from the nearest boundary point, inside along the
    face axis nearest (the sign of p; + on a medial plane)."""
    sign = np.where(p < 0.0, -1.0, 1.0)
    q = np.abs(p) - half
    out = np.maximum(q, 0.0)
    r = np.linalg.norm(out, axis=-1)
    inner = q.max(axis=-1)
    n = np.zeros_like(p)
    n[np.arange(len(p)), np.argmax(q, axis=-1)] = 1.0           # inside: the nearest face's axis
    outside = r > 0.0
    n[outside] = out[outside] / r[outside, None]
    return r + np.minimum(inner, 0.0), sign * n


def _unit_or_radial(g: np.ndarray, p: np.ndarray) -> np.ndarray:
    """The rows of g (N, k) made unit; where a row vanishes, the direction of p from the centre
    (body x at the centre)."""
    norm = np.linalg.norm(g, axis=1, keepdims=True)
    radial = np.linalg.norm(p, axis=1, keepdims=True)
    centre = np.zeros_like(p)
    centre[:, 0] = 1.0
    fallback = np.where(radial > 1e-12, p / np.maximum(radial, 1e-12), centre)
    return np.where(norm > 1e-9, g / np.maximum(norm, 1e-300), fallback)


def _ellipsoid_root(e: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest points of an ellipse/ellipsoid, generic case of [1].

    e: (k,) semi-axes sorted descending; y: (N, k) with y >= 0 and y[:, -1] > 0.
    Returns the nearest boundary points (N, k).  Solves G(u) = sum_i (w_i / (u + q_i))^2 - 1 = 0
    with w_i = e_i y_i / e_m^2, q_i = (e_i^2 - e_m^2) / e_m^2 (so q_m = 0); G is
    strictly decreasing and convex on u > 0 with G(z_m) >= 0 and G(|w|) <= 0, z_m = y_m / e_m.
    Newton's method from u = |w|: its first step lands left of the root (G convex), and from
    there its iterates rise monotonically to it (quadratically), kept in [z_m, |w|]; it stops
    once no iterate moves by more than a few ulp.
    The closest point is x_i = (e_i / e_m)^2 y_i / (u + q_i).
    """
    em2 = e[-1] ** 2
    q = (e**2 - em2) / em2
    w = e * y / em2
    lo = y[:, -1] / e[-1]
    hi = np.maximum(np.sqrt((w * w).sum(axis=1)), lo)
    u = hi
    for _ in range(_ROOT_MAX_ITERS):
        r = w / (u[:, None] + q)
        r2 = r * r
        g = r2.sum(axis=1) - 1.0
        dg = -2.0 * (r2 / (u[:, None] + q)).sum(axis=1)
        u_new = np.minimum(np.maximum(u - g / dg, lo), hi)
        done = (np.abs(u_new - u) <= 4.0 * np.finfo(float).eps * u_new).all()
        u = u_new
        if done:
            break
    return (e**2 / em2) * y / (u[:, None] + q)


def _ellipse_nearest(e: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest points (N, 2) of an ellipse; e (2,) with e0 >= e1 > 0, y (N, 2) >= 0."""
    e0, e1 = float(e[0]), float(e[1])
    x = np.empty_like(y)
    gen = y[:, 1] > 0.0
    x[gen] = _ellipsoid_root(e, y[gen])
    # y1 == 0 (on the major axis): the nearest point leaves the axis iff
    # y0 < (e0^2 - e1^2) / e0, then x0 = e0^2 y0 / (e0^2 - e1^2) [1, sec. 2]; else it is the vertex.
    y0 = y[~gen, 0]
    den = e0 * e0 - e1 * e1
    axis = np.column_stack([np.full(len(y0), e0), np.zeros(len(y0))])
    if den > 0.0:
        off = y0 < den / e0
        x0 = e0 * e0 * y0[off] / den
        axis[off] = np.column_stack([x0, e1 * np.sqrt(np.clip(1.0 - (x0 / e0) ** 2, 0.0, None))])
    x[~gen] = axis
    return x


def _ellipsoid_nearest(e: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Nearest points (N, 3) of an ellipsoid; e (3,) descending > 0, y (N, 3) >= 0."""
    x = np.empty_like(y)
    gen = y[:, 2] > 0.0
    x[gen] = _ellipsoid_root(e, y[gen])
    # y2 == 0 [1, sec. 3]: the nearest point leaves the plane z = 0 iff
    # x_i = e_i^2 y_i / (e_i^2 - e2^2) (i = 0, 1) lies strictly inside the ellipse.
    yz = y[~gen, :2]
    den = e[:2] ** 2 - e[2] ** 2
    num = e[:2] * yz
    xde = num / np.where(den > 0.0, den, 1.0)
    discr = 1.0 - np.sum(xde**2, axis=1)
    off = np.all(num < den, axis=1) & (discr > 0.0)
    plane = np.zeros((len(yz), 3))
    plane[off, :2] = e[:2] * xde[off]
    plane[off, 2] = e[2] * np.sqrt(discr[off])
    plane[~off, :2] = _ellipse_nearest(e[:2], yz[~off])
    x[~gen] = plane
    return x


def _ellipsoidal_nearest(p: np.ndarray, axes: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """An axis-aligned ellipse/ellipsoid at the origin, for body points p (N, k): the semi-axes e
    sorted descending, the points y reflected into the first quadrant/octant in that order, their
    nearest boundary points x (N, k) there, and the order (``argsort`` of -axes)."""
    e = np.asarray(axes, dtype=float)
    order = np.argsort(-e, kind="stable")
    e = e[order]
    y = np.abs(p[:, order])
    return e, y, (_ellipse_nearest(e, y) if len(e) == 2 else _ellipsoid_nearest(e, y)), order


def _ellipsoidal_signed(e: np.ndarray, y: np.ndarray, x: np.ndarray) -> np.ndarray:
    """The signed distance (N,) of the reflected points y (N, k) whose nearest points are x."""
    d = np.sqrt(((x - y) ** 2).sum(axis=1))
    return np.where(np.sum((y / e) ** 2, axis=1) < 1.0, -d, d)


def _ellipsoidal_sd(p: np.ndarray, axes: tuple[float, ...]) -> np.ndarray:
    """Signed distance to an axis-aligned ellipse/ellipsoid at the origin; p (N, k) -> (N,)."""
    e, y, x, _ = _ellipsoidal_nearest(p, axes)
    return _ellipsoidal_signed(e, y, x)


def _ellipsoidal_sd_normal(p: np.ndarray, axes: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Signed distance (N,) and its unit gradient (N, k) for an axis-aligned ellipse/ellipsoid at
    the origin: the outward normal at the nearest boundary point x, along the gradient x_i / e_i^2
    of sum_i (x_i / e_i)^2, reflected back to p's quadrant/octant (+ on a coordinate plane)."""
    e, y, x, order = _ellipsoidal_nearest(p, axes)
    g = x / (e * e)
    body = np.empty_like(p)
    body[:, order] = g / np.linalg.norm(g, axis=1, keepdims=True) * np.where(p[:, order] < 0.0, -1.0, 1.0)
    return _ellipsoidal_signed(e, y, x), body


# --------------------------------------------------------------------------- base classes
class Shape:
    """Base class of all shapes: size validation and the world -> body transform.

    Subclasses are frozen dataclasses whose fields are all sizes in metres; they
    define ``dim``, ``kind`` and ``_sd_body(p)`` (body-frame points (N, dim) -> (N,)).
    """

    dim: ClassVar[int]
    kind: ClassVar[str]
    #: "round" where the signed distance is |p| - bounding_radius(), "box" where it is the box
    #: distance to support_extent(), "" otherwise (array code may then evaluate it in closed form)
    closed_form: ClassVar[str] = ""

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            try:
                x = float(v)
            except (TypeError, ValueError):
                x = math.nan
            if isinstance(v, bool) or not (math.isfinite(x) and x > 0.0):
                raise ValueError(f"{type(self).__name__}.{f.name} must be positive and finite, got {v!r}")
            object.__setattr__(self, f.name, x)

    def _sd_body(self, p: np.ndarray) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def _to_body(self, points, center, yaw: float) -> tuple[np.ndarray, tuple[int, ...]]:
        """World points (..., dim) -> body-frame points (N, dim) and the leading shape (...)."""
        pts = np.asarray(points, dtype=float)
        c = np.asarray(center, dtype=float)
        if pts.ndim < 1 or pts.shape[-1] != self.dim:
            raise ValueError(f"{self.kind}: points must have shape (..., {self.dim}), got {pts.shape}")
        if c.shape != (self.dim,):
            raise ValueError(f"{self.kind}: center must have shape ({self.dim},), got {c.shape}")
        d = (pts - c).reshape(-1, self.dim)
        cy, sy = math.cos(float(yaw)), math.sin(float(yaw))
        body = d.copy()
        body[:, 0] = cy * d[:, 0] + sy * d[:, 1]  # R(yaw)^T (p - c)
        body[:, 1] = -sy * d[:, 0] + cy * d[:, 1]
        return body, pts.shape[:-1]

    def signed_distance(self, points, center, yaw: float = 0.0) -> np.ndarray:
        """Exact signed distance to the boundary (negative inside).

        points: (..., dim) world frame [m]; center: (dim,) [m]; yaw: rotation of
        the body frame about world z [rad].  Returns (...) [m].
        """
        body, lead = self._to_body(points, center, yaw)
        return self._sd_body(body).reshape(lead)

    def distance_and_normal(self, points, center, yaw: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (...) [m] as ``signed_distance``, and its unit gradient (..., dim), world
        frame (module docstring)."""
        body, lead = self._to_body(points, center, yaw)
        sd, n = self._sd_normal_body(body)
        cy, sy = math.cos(float(yaw)), math.sin(float(yaw))
        world = n.copy()
        world[:, 0] = cy * n[:, 0] - sy * n[:, 1]             # R(yaw) n
        world[:, 1] = sy * n[:, 0] + cy * n[:, 1]
        return sd.reshape(lead), world.reshape(lead + (self.dim,))

    def _sd_normal_body(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Signed distance (N,) and unit gradient (N, dim) at body points p (N, dim): central
        differences; a shape with a closed form overrides it."""
        n = np.empty_like(p)
        for j in range(self.dim):
            e = np.zeros(self.dim)
            e[j] = NORMAL_FD_STEP
            n[:, j] = self._sd_body(p + e) - self._sd_body(p - e)     # 2 h times the gradient: made unit below
        return self._sd_body(p), _unit_or_radial(n, p)

    def bounding_radius(self) -> float:
        """Radius [m] of the smallest origin-centred circle/sphere enclosing the shape."""
        raise NotImplementedError  # pragma: no cover

    def support_extent(self) -> np.ndarray:
        """Half-extents (dim,) [m] of the body-frame axis-aligned bounding box."""
        raise NotImplementedError  # pragma: no cover


class Shape2D(Shape):
    """Planar shape (dim = 2) with a boundary polyline for plots."""

    dim: ClassVar[int] = 2

    def _outline_body(self, n: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def outline(self, center, yaw: float = 0.0, n: int = 128) -> np.ndarray:
        """Closed boundary polyline (n, 2) in the world frame (last point == first).

        center: (2,) [m]; yaw [rad]; n >= 5 points.
        """
        n = int(n)
        if n < _MIN_OUTLINE_POINTS:
            raise ValueError(f"outline needs n >= {_MIN_OUTLINE_POINTS}, got {n}")
        c = np.asarray(center, dtype=float)
        if c.shape != (2,):
            raise ValueError(f"{self.kind}: center must have shape (2,), got {c.shape}")
        body = self._outline_body(n)
        body[-1] = body[0]
        cy, sy = math.cos(float(yaw)), math.sin(float(yaw))
        rot = np.array([[cy, -sy], [sy, cy]])
        return body @ rot.T + c


def _ellipse_outline(a: float, b: float, n: int) -> np.ndarray:
    th = np.linspace(0.0, 2.0 * np.pi, n)
    return np.column_stack([a * np.cos(th), b * np.sin(th)])


# --------------------------------------------------------------------------- 2-D shapes
@dataclass(frozen=True)
class Circle(Shape2D):
    """Disc of the given radius [m]."""

    radius: float
    kind: ClassVar[str] = "circle"
    closed_form: ClassVar[str] = "round"

    def _sd_body(self, p):
        return np.hypot(p[:, 0], p[:, 1]) - self.radius

    def _sd_normal_body(self, p):
        return np.hypot(p[:, 0], p[:, 1]) - self.radius, _unit_or_radial(p, p)

    def bounding_radius(self) -> float:
        return self.radius

    def support_extent(self) -> np.ndarray:
        return np.array([self.radius, self.radius])

    def _outline_body(self, n):
        return _ellipse_outline(self.radius, self.radius, n)

    def inflated(self, margin: float) -> Circle:
        """Circle grown by ``margin`` [m] (exact: the Minkowski sum with a disc)."""
        return Circle(self.radius + float(margin))


@dataclass(frozen=True)
class Ellipse(Shape2D):
    """Ellipse with semi-axes ``a`` (body x) and ``b`` (body y) [m]."""

    a: float
    b: float
    kind: ClassVar[str] = "ellipse"

    def _sd_body(self, p):
        return _ellipsoidal_sd(p, (self.a, self.b))

    def _sd_normal_body(self, p):
        return _ellipsoidal_sd_normal(p, (self.a, self.b))

    def bounding_radius(self) -> float:
        return max(self.a, self.b)

    def support_extent(self) -> np.ndarray:
        return np.array([self.a, self.b])

    def _outline_body(self, n):
        return _ellipse_outline(self.a, self.b, n)


@dataclass(frozen=True)
class Box(Shape2D):
    """Rectangle with full side lengths ``length`` (body x) and ``width`` (body y) [m]."""

    length: float
    width: float
    kind: ClassVar[str] = "box"
    closed_form: ClassVar[str] = "box"

    def _sd_body(self, p):
        return _box_sd(np.abs(p) - self.support_extent())

    def _sd_normal_body(self, p):
        return _box_sd_normal(p, self.support_extent())

    def bounding_radius(self) -> float:
        return 0.5 * math.hypot(self.length, self.width)

    def support_extent(self) -> np.ndarray:
        return 0.5 * np.array([self.length, self.width])

    def _outline_body(self, n):
        # Arc-length samples that always include the 4 corners (and the closing point).
        hx, hy = self.support_extent()
        L, W = self.length, self.width
        perim = 2.0 * (L + W)
        corners = np.array([0.0, W, W + L, 2.0 * W + L, perim])
        s = np.sort(np.concatenate([corners, np.linspace(0.0, perim, n - 3)[1:-1]]))
        x = np.interp(s, corners, [hx, hx, -hx, -hx, hx])
        y = np.interp(s, corners, [-hy, hy, hy, -hy, -hy])
        return np.column_stack([x, y])


# --------------------------------------------------------------------------- 3-D shapes
@dataclass(frozen=True)
class Sphere(Shape):
    """Ball of the given radius [m]."""

    radius: float
    dim: ClassVar[int] = 3
    kind: ClassVar[str] = "sphere"
    closed_form: ClassVar[str] = "round"

    def _sd_body(self, p):
        return np.linalg.norm(p, axis=1) - self.radius

    def _sd_normal_body(self, p):
        return np.linalg.norm(p, axis=1) - self.radius, _unit_or_radial(p, p)

    def bounding_radius(self) -> float:
        return self.radius

    def support_extent(self) -> np.ndarray:
        return np.full(3, self.radius)

    def inflated(self, margin: float) -> Sphere:
        """Sphere grown by ``margin`` [m] (exact: the Minkowski sum with a ball)."""
        return Sphere(self.radius + float(margin))


@dataclass(frozen=True)
class Ellipsoid(Shape):
    """Ellipsoid with semi-axes ``a``, ``b``, ``c`` along body x, y, z [m]."""

    a: float
    b: float
    c: float
    dim: ClassVar[int] = 3
    kind: ClassVar[str] = "ellipsoid"

    def _sd_body(self, p):
        return _ellipsoidal_sd(p, (self.a, self.b, self.c))

    def _sd_normal_body(self, p):
        return _ellipsoidal_sd_normal(p, (self.a, self.b, self.c))

    def bounding_radius(self) -> float:
        return max(self.a, self.b, self.c)

    def support_extent(self) -> np.ndarray:
        return np.array([self.a, self.b, self.c])


@dataclass(frozen=True)
class Box3(Shape):
    """Cuboid with full side lengths ``length`` (x), ``width`` (y), ``height`` (z) [m]."""

    length: float
    width: float
    height: float
    dim: ClassVar[int] = 3
    kind: ClassVar[str] = "box3"
    closed_form: ClassVar[str] = "box"

    def _sd_body(self, p):
        return _box_sd(np.abs(p) - self.support_extent())

    def _sd_normal_body(self, p):
        return _box_sd_normal(p, self.support_extent())

    def bounding_radius(self) -> float:
        return 0.5 * math.sqrt(self.length**2 + self.width**2 + self.height**2)

    def support_extent(self) -> np.ndarray:
        return 0.5 * np.array([self.length, self.width, self.height])


@dataclass(frozen=True)
class Cylinder(Shape):
    """Solid cylinder, axis along body z, spanning z in [-height/2, height/2] [m]."""

    radius: float
    height: float
    dim: ClassVar[int] = 3
    kind: ClassVar[str] = "cylinder"

    def _sd_body(self, p):
        q = np.column_stack([np.hypot(p[:, 0], p[:, 1]) - self.radius, np.abs(p[:, 2]) - 0.5 * self.height])
        return _box_sd(q)

    def bounding_radius(self) -> float:
        return math.hypot(self.radius, 0.5 * self.height)

    def support_extent(self) -> np.ndarray:
        return np.array([self.radius, self.radius, 0.5 * self.height])


# --------------------------------------------------------------------------- registry
SHAPES_2D: dict[str, type[Shape]] = {cls.kind: cls for cls in (Circle, Ellipse, Box)}
SHAPES_3D: dict[str, type[Shape]] = {cls.kind: cls for cls in (Sphere, Ellipsoid, Box3, Cylinder)}


def top_view(shape: Shape) -> Shape2D:
    """The 2-D outline shape of an obstacle seen from above."""
    if isinstance(shape, (Circle, Ellipse, Box)):
        return shape
    if isinstance(shape, (Sphere, Cylinder)):
        return Circle(shape.radius)
    if isinstance(shape, Box3):
        return Box(shape.length, shape.width)
    if isinstance(shape, Ellipsoid):
        return Ellipse(shape.a, shape.b)
    raise TypeError(f"no top view for {type(shape).__name__}")


def shape_from_table(kind: str, sizes: dict[str, float]) -> Shape:
    """Build a shape from its ``kind`` string and a dict of its size fields [m].

    e.g. ``shape_from_table("box", {"length": 4.5, "width": 1.9})``.  Raises
    ValueError for an unknown kind, a missing or an unexpected size key, or a bad size.
    """
    registry = {**SHAPES_2D, **SHAPES_3D}
    if kind not in registry:
        raise ValueError(f"unknown shape kind {kind!r}; expected one of {sorted(registry)}")
    cls = registry[kind]
    names = [f.name for f in fields(cls)]
    missing = [k for k in names if k not in sizes]
    extra = sorted(str(k) for k in sizes if k not in names)
    if missing:
        raise ValueError(f"shape {kind!r} is missing size key(s) {missing}; expected {names}")
    if extra:
        raise ValueError(f"shape {kind!r} got unexpected size key(s) {extra}; expected {names}")
    return cls(**{k: sizes[k] for k in names})
