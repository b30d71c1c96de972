"""Implicit functions of the composite guiding vector field (paper section II-A).

A desired path is P = {xi : phi(xi) = 0}; an obstacle i has a reactive boundary
R_i = {varphi_i = 0} and a repulsive boundary Q_i = {varphi_i = c_i}, c_i < 0, with
varphi_i increasing outwards. Every class here returns values and gradients, vectorised
over points (N, d); obstacles also take the time t (they translate with their velocity).

Paths (2-D):
- ``LinePath``: phi = n . (xi - a), n the left normal of the direction (signed distance);
- ``CirclePath``: phi = |xi - c| - R (signed distance; singular at the centre);
- ``GraphPath``: the paper's fit of recorded path points in a local frame,
  phi = y' - f(x') with f a C2 cubic spline (extended linearly beyond its ends), so that
  grad phi = R(theta) [-f'(x'), 1] never vanishes (no singular points).

Obstacles (2-D and 3-D): superquadrics
    varphi(xi, t) = N(z) - 1,  z = R(yaw)^T (xi - c(t)) / axes,  c(t) = c_0 + v (t - t_0),
    N(z) = (|z_1|^p + |z_2|^p)^(1/p)                                    in 2-D,
    N(z) = (((|z_1|^p + |z_2|^p)^(q/p)) + |z_3|^q)^(1/q)                  in 3-D,
with p = 2 for circles, ellipses, spheres, ellipsoids and cylinders (in xy), p = 4 (a
rounded box) for boxes, q = 2 for spheres and ellipsoids and q = 4 for cylinders and boxes.
``ObstacleImplicit.around`` sizes the axes so that the reactive boundary encloses every point
within ``reactive_distance`` of the physical shape and picks c so that the repulsive boundary
encloses every point within ``repulsive_distance`` (both checked by ray casting against the
shape's exact signed distance).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from vflpcd.core.path import ReferencePath

E = np.array([[0.0, -1.0], [1.0, 0.0]])  # rotation by +90 deg


class GuidanceError(ValueError):
    """A guidance problem that cannot be solved as posed (names the obstacle or parameter)."""


def _rot(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s], [s, c]])


# ---------------------------------------------------------------------------- paths
@dataclass(frozen=True)
class LinePath:
    """Straight line through a (2,) with unit direction d (2,); forward travel needs gamma_0 = -1."""

    a: np.ndarray
    d: np.ndarray

    def value_grad(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """p: (N, 2) -> phi (N,), grad phi (N, 2)."""
        n = np.array([-self.d[1], self.d[0]])
        return (p - self.a) @ n, np.broadcast_to(n, p.shape).copy()

    def progress(self, p: np.ndarray) -> np.ndarray:
        """Arc length of the foot point along the direction, (N,)."""
        return (p - self.a) @ self.d

    def progress_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin, unit direction): progress = (xi - origin) . direction."""
        return self.a, self.d

    def tangent(self, x: float, y: float) -> tuple[float, float]:
        """Unit forward tangent of the path at the foot of (x, y)."""
        return float(self.d[0]), float(self.d[1])


@dataclass(frozen=True)
class CirclePath:
    """Circle of radius R about c (2,); counter-clockwise travel needs gamma_0 = +1."""

    c: np.ndarray
    R: float

    def value_grad(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r = p - self.c
        dist = np.linalg.norm(r, axis=-1)
        with np.errstate(invalid="ignore", divide="ignore"):
            g = np.where(dist[:, None] > 0.0, r / dist[:, None], 0.0)
        return dist - self.R, g


class GraphPath:
    """The path as a graph y' = f(x') in a local frame (origin o, heading theta).

    Forward travel (increasing x') needs gamma_0 = -1: gamma_0 E grad phi = [1, f'] / ... in
    the local frame. ``progress`` is x', which increases along the path.
    """

    def __init__(self, origin: np.ndarray, theta: float, xs: np.ndarray, ys: np.ndarray) -> None:
        if np.any(np.diff(xs) <= 0.0):
            raise GuidanceError("path portion is not a graph in its local frame (x' must increase)")
        self.origin, self.theta = np.asarray(origin, float), float(theta)
        self.R = _rot(self.theta)
        self.f = CubicSpline(xs, ys, bc_type="natural")
        self.df = self.f.derivative()
        self.x0, self.x1 = float(xs[0]), float(xs[-1])

    @classmethod
    def from_reference(cls, path: ReferencePath, s0: float, s1: float, spacing: float = 1.0) -> "GraphPath":
        """Fit the stretch [s0, s1] of a 2-D reference path in the frame of its chord."""
        origin, theta, local = chord_frame(path, s0, s1, spacing)
        return cls(origin, theta, local[:, 0], local[:, 1])

    def to_local(self, p: np.ndarray) -> np.ndarray:
        return (p - self.origin) @ self.R

    def pieces(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(origin, R, breakpoints (n + 1,), coefficients (4, n)) of f: what the compiled path grid
        fill (``path_grid_kernel.fill_loop``) evaluates ``value_grad`` from."""
        return self.origin, self.R, self.f.x, self.f.c

    def _f(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xc = np.clip(x, self.x0, self.x1)
        f, df = self.f(xc), self.df(xc)
        return f + df * (x - xc), df  # linear beyond the ends

    def value_grad(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        q = self.to_local(p)
        f, df = self._f(q[:, 0])
        g_local = np.column_stack([-df, np.ones_like(df)])
        return q[:, 1] - f, g_local @ self.R.T

    def progress(self, p: np.ndarray) -> np.ndarray:
        return self.to_local(p)[:, 0]

    def progress_frame(self) -> tuple[np.ndarray, np.ndarray]:
        """(origin, unit direction): progress x' = (xi - origin) . direction."""
        return self.origin, self.R[:, 0]

    def tangent(self, x: float, y: float) -> tuple[float, float]:
        """Unit forward tangent of the graph at the abscissa x' of (x, y)."""
        xl = float(self.to_local(np.array([[x, y]]))[0, 0])
        slope = float(self.df(min(max(xl, self.x0), self.x1)))
        t = self.R @ np.array([1.0, slope])
        return tuple(t / np.linalg.norm(t))

    def point(self, x: np.ndarray) -> np.ndarray:
        """World points of the graph at local abscissae x (K,) -> (K, 2)."""
        f, _ = self._f(np.asarray(x, float))
        return self.origin + np.column_stack([x, f]) @ self.R.T

    def straighten(self, p: np.ndarray) -> np.ndarray:
        """World points (K, 2) -> (x', y' - f(x')): the path becomes the x' axis."""
        q = self.to_local(np.asarray(p, float))
        q[:, 1] -= self._f(q[:, 0])[0]
        return q

    def bend(self, q: np.ndarray) -> np.ndarray:
        """The inverse of ``straighten``: (x', offset) (K, 2) -> world points."""
        q = np.array(q, float)
        q[:, 1] += self._f(q[:, 0])[0]
        return self.origin + q @ self.R.T


def chord_frame(path: ReferencePath, s0: float, s1: float, spacing: float = 1.0):
    """Points of the stretch [s0, s1] every ~spacing m in the frame of its chord, turned about z:
    (origin (d,), heading theta of the chord, local points (K, d))."""
    n = max(int(np.ceil((s1 - s0) / spacing)), 3)
    pts = path.point_at(np.linspace(s0, s1, n + 1))
    chord = pts[-1] - pts[0]
    theta = float(np.arctan2(chord[1], chord[0]))
    rot = np.eye(path.dim)
    rot[:2, :2] = _rot(theta)
    return pts[0], theta, (pts - pts[0]) @ rot


def graph_horizon(path: ReferencePath, s0: float, length: float, max_turn: float = np.radians(70.0)) -> float:
    """The longest stretch from s0 (at most ``length``) whose tangents stay within max_turn of
    its chord, so that it is a graph in the chord frame. Returns its end arc length."""
    s_end = s0 + length if path.closed else min(s0 + length, path.length)
    for _ in range(40):
        s = np.linspace(s0, s_end, 64)
        chord = path.point_at(s_end) - path.point_at(s0)
        ang = np.arctan2(chord[1], chord[0])
        dev = np.abs(np.angle(np.exp(1j * (path.heading_at(s) - ang))))
        if np.max(dev) <= max_turn:
            return float(s_end)
        s_end = s0 + 0.8 * (s_end - s0)
    raise GuidanceError(f"no stretch of the path from s = {s0:.1f} m is a graph; the path turns too sharply")


# ---------------------------------------------------------------------------- obstacles
_EXPONENTS = {  # kind -> (p, q, half-extents of the physical shape)
    "circle": (2.0, None, lambda s: np.array([s.radius, s.radius])),
    "ellipse": (2.0, None, lambda s: np.array([s.a, s.b])),
    "box": (4.0, None, lambda s: np.array([s.length, s.width]) / 2),
    "sphere": (2.0, 2.0, lambda s: np.array([s.radius] * 3)),
    "ellipsoid": (2.0, 2.0, lambda s: np.array([s.a, s.b, s.c])),
    "cylinder": (2.0, 4.0, lambda s: np.array([s.radius, s.radius, s.height / 2])),
    "box3": (4.0, 4.0, lambda s: np.array([s.length, s.width, s.height]) / 2),
}


def _sphere_directions(dim: int, n: int) -> np.ndarray:
    if dim == 2:
        a = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
        return np.column_stack([np.cos(a), np.sin(a)])
    k = np.arange(n) + 0.5  # Fibonacci sphere
    z = 1 - 2 * k / n
    r = np.sqrt(1 - z * z)
    phi = np.pi * (1 + 5 ** 0.5) * k
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def _inflated_boundary(shape, distance: float, n: int, tol: float = 1e-12) -> np.ndarray:
    """Points (n, d), in the body frame, on {sd = distance} of a convex shape, found along rays from
    the centre by the Illinois variant of regula falsi (sd along a ray is convex and increasing
    past the shape, so the bracket [inside, outside] shrinks superlinearly); each point returned is
    on the outer side, within ``tol`` m.

    The search is for sd = distance + tol / 2, and a ray is done at the first point whose sd is
    within tol / 2 of that, so in [distance, distance + tol]: outside a convex shape sd is the
    distance to it, so such a point lies within tol m of {sd = distance}, on its outer side. (Waiting
    for the bracket itself to close, a round shape, on which sd is linear along a ray and the first
    secant lands on the root, took 40 more iterations: Illinois then walks the far end in.)"""
    dirs = _sphere_directions(shape.dim, n)
    zero = np.zeros(shape.dim)
    target = distance + 0.5 * tol

    def f(t):
        return shape.signed_distance(dirs * t[:, None], zero, 0.0) - target

    found = np.full(len(dirs), np.nan)         # a point within tol / 2 of the target, per ray
    a, b = np.zeros(len(dirs)), np.full(len(dirs), shape.bounding_radius() + distance + 1.0)
    near = _offset_radii(shape, dirs, target)
    if near is None:
        fa, fb = f(a), f(b)
    else:                         # the offset curve's points where they hold, else a bracket round them
        fn = f(near)
        found = np.where(np.abs(fn) <= 0.5 * tol, near, found)
        if not np.isnan(found).any():
            return dirs * found[:, None]
        a_near, b_near = near - OFFSET_BRACKET, near + OFFSET_BRACKET
        fa_near, fb_near = f(a_near), f(b_near)
        held = (fa_near < 0.0) & (fb_near > 0.0)
        a, b = np.where(held, a_near, a), np.where(held, b_near, b)
        fa, fb = np.where(held, fa_near, f(a)), np.where(held, fb_near, f(b))
    side = np.zeros(len(dirs))                 # which end was kept last time: -1 a, +1 b
    for _ in range(100):
        with np.errstate(invalid="ignore", divide="ignore"):       # a closed bracket: 0 / 0
            c = b - fb * (b - a) / (fb - fa)
        c = np.where((c > a) & (c < b), c, 0.5 * (a + b))
        fc = f(c)
        found = np.where(np.isnan(found) & (np.abs(fc) <= 0.5 * tol), c, found)
        out = fc > 0.0
        # Illinois: halve the value at an end kept twice in a row, so both ends move
        fa = np.where(out & (side == -1), 0.5 * fa, fa)
        fb = np.where(~out & (side == 1), 0.5 * fb, fb)
        a, fa = np.where(out, a, c), np.where(out, fa, fc)
        closes = out | (fc == 0.0)                 # an exact root closes the bracket
        b, fb = np.where(closes, c, b), np.where(closes, fc, fb)
        side = np.where(out, -1.0, 1.0)
        if (~np.isnan(found) | (b - a < tol)).all():
            break
    return dirs * np.where(np.isnan(found), b, found)[:, None]


#: half-width (m) of the bracket that ``_inflated_boundary`` starts from round ``_offset_radii``
OFFSET_BRACKET = 1e-4
#: samples of the offset curve per ray, and Newton steps, in ``_offset_radii``
OFFSET_SAMPLES = 8
OFFSET_NEWTON = 3


def _offset_radii(shape, dirs: np.ndarray, distance: float) -> np.ndarray | None:
    """Where the rays ``dirs`` (n, 2) from a planar shape's centre meet {sd = distance}, in closed
    form round a circle (radius + distance) and a box (its sides pushed out by distance, joined by
    quarter circles of that radius round its corners), by Newton's method round an ellipse; None for
    the other shapes. The ellipse's offset curve P(th) = E(th) + distance n(th), E(th) = (a cos th,
    b sin th), n the unit outward normal, is a closed convex curve round the centre whose polar
    angle grows with th, and P'(th) = (1 + distance kappa(th)) E'(th), kappa = ab / h^3,
    h = |E'(th)|: the ray's th is interpolated in the polar angle of P sampled at OFFSET_SAMPLES
    times the rays, then OFFSET_NEWTON Newton steps on u x P(th) = 0 take it to rounding."""
    if shape.kind == "circle":
        return np.full(len(dirs), shape.radius + distance)
    if shape.kind == "box":
        (hx, hy), u = shape.support_extent(), np.abs(dirs)
        with np.errstate(divide="ignore", invalid="ignore"):
            side_x, side_y = (hx + distance) / u[:, 0], (hy + distance) / u[:, 1]
        p = u[:, 0] * hx + u[:, 1] * hy
        corner = p + np.sqrt(np.maximum(p * p - hx * hx - hy * hy + distance * distance, 0.0))
        return np.where(side_x * u[:, 1] <= hy, side_x, np.where(side_y * u[:, 0] <= hx, side_y, corner))
    if shape.kind != "ellipse":
        return None
    a, b = shape.a, shape.b

    def offset(th):
        c, s = np.cos(th), np.sin(th)
        h = np.hypot(a * s, b * c)
        return c, s, h, a * c + distance * b * c / h, b * s + distance * a * s / h

    th = np.linspace(0.0, 2.0 * np.pi, OFFSET_SAMPLES * len(dirs) + 1)
    x, y = offset(th)[3:]
    phi = np.unwrap(np.arctan2(y, x))                           # rising from 0 to 2 pi with th
    th = np.interp(np.mod(np.arctan2(dirs[:, 1], dirs[:, 0]), 2.0 * np.pi), phi, th)
    for _ in range(OFFSET_NEWTON):
        c, s, h, x, y = offset(th)
        stretch = 1.0 + distance * a * b / h ** 3
        th = th - (dirs[:, 0] * y - dirs[:, 1] * x) / (stretch * (dirs[:, 0] * b * c + dirs[:, 1] * a * s))
    x, y = offset(th)[3:]
    return dirs[:, 0] * x + dirs[:, 1] * y


class ObstacleImplicit:
    """varphi_i(xi, t) of one obstacle (see the module docstring), with its repulsive level c."""

    def __init__(self, name: str, center: np.ndarray, yaw: float, velocity: np.ndarray, stamp: float,
                 axes: np.ndarray, p: float, q: float | None, c: float) -> None:
        self.name, self.center, self.yaw = name, np.asarray(center, float), float(yaw)
        self.velocity, self.stamp = np.asarray(velocity, float), float(stamp)
        self.axes, self.p, self.q, self.c = np.asarray(axes, float), p, q, float(c)
        self.dim = len(self.center)
        cy, sy = np.cos(self.yaw), np.sin(self.yaw)
        self.Rz = np.eye(self.dim)
        self.Rz[:2, :2] = [[cy, -sy], [sy, cy]]
        if not (np.all(np.isfinite(self.axes)) and np.all(self.axes > 0)):
            raise GuidanceError(f"obstacle {name!r}: axes must be positive and finite, got {self.axes}")
        if not (np.isfinite(self.c) and self.c < 0.0):
            raise GuidanceError(f"obstacle {name!r}: c must be negative and finite (c_i < 0), got {self.c}")

    @classmethod
    def around(cls, name: str, shape, center, yaw: float, velocity, stamp: float,
               reactive_distance: float, repulsive_distance: float, rays: int | None = None) -> "ObstacleImplicit":
        """Implicit function whose R encloses the shape grown by reactive_distance and whose Q
        encloses it grown by repulsive_distance (0 < repulsive_distance < reactive_distance)."""
        for label, value in (("reactive_distance", reactive_distance), ("repulsive_distance", repulsive_distance)):
            if not np.isfinite(value) or value < 0:
                raise GuidanceError(f"obstacle {name!r}: {label} must be finite and >= 0, got {value}")
        if repulsive_distance >= reactive_distance:
            raise GuidanceError(f"obstacle {name!r}: repulsive_distance ({repulsive_distance}) must be smaller "
                                f"than reactive_distance ({reactive_distance})")
        levels = _levels(shape, float(reactive_distance), float(repulsive_distance),
                         rays or (720 if shape.dim == 2 else 2500))
        if levels is None:
            raise GuidanceError(f"obstacle {name!r}: the reactive boundary does not leave room for the repulsive "
                                "one; increase reactive_distance")
        axes, p, q, c = levels
        return cls(name, center, yaw, velocity, stamp, np.array(axes), p, q, c)

    def center_at(self, t: float) -> np.ndarray:
        return self.center + self.velocity * (t - self.stamp)

    def _scaled(self, pts: np.ndarray, t: float) -> np.ndarray:
        return ((pts - self.center_at(t)) @ self.Rz) / self.axes

    def norm(self, pts_body: np.ndarray) -> np.ndarray:
        """N(z) for body-frame points (N, d) (centre at the origin, no rotation)."""
        return self._norm_grad(pts_body / self.axes)[0]

    def _norm_grad(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        a = np.abs(z)
        p = self.p
        S = a[:, 0] ** p + a[:, 1] ** p
        tiny = 1e-300
        if self.dim == 2:
            N = S ** (1.0 / p)
            coef = np.maximum(S, tiny) ** (1.0 / p - 1.0)
            g = coef[:, None] * np.sign(z) * a ** (p - 1.0)
            return N, g
        q = self.q
        T = S ** (q / p) + a[:, 2] ** q
        N = T ** (1.0 / q)
        tq = np.maximum(T, tiny) ** (1.0 / q - 1.0)
        sq = np.maximum(S, tiny) ** (q / p - 1.0)
        g = np.empty_like(z)
        g[:, :2] = (tq * sq)[:, None] * np.sign(z[:, :2]) * a[:, :2] ** (p - 1.0)
        g[:, 2] = tq * np.sign(z[:, 2]) * a[:, 2] ** (q - 1.0)
        return N, g

    def value_grad(self, pts: np.ndarray, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """pts (N, d) -> varphi (N,), grad varphi (N, d) at time t (zero gradient at the centre)."""
        N, gz = self._norm_grad(self._scaled(pts, t))
        return N - 1.0, (gz / self.axes) @ self.Rz.T

    def value(self, pts: np.ndarray, t: float = 0.0) -> np.ndarray:
        return self._norm_grad(self._scaled(pts, t))[0] - 1.0

    @functools.cached_property
    def reach(self) -> float:
        """Radius about the centre outside which every point is outside the reactive boundary
        (N >= max |z_j|, and N = |z| for p = q = 2)."""
        if self.p == 2.0 and self.q in (None, 2.0):
            return float(np.max(self.axes))
        return float(np.linalg.norm(self.axes))

    def row(self) -> list[float]:
        """A planar obstacle in the compiled loops' layout (``integrate_kernel``,
        ``half_plane_kernel``): centre x, y at the stamp, velocity x, y, stamp, squared reach, cos and
        sin of the yaw, the two axes, p and c."""
        return [self.center[0], self.center[1], self.velocity[0], self.velocity[1], self.stamp, self.reach ** 2,
                self.Rz[0, 0], self.Rz[1, 0], self.axes[0], self.axes[1], self.p, self.c]

    def row3d(self) -> list[float]:
        """A 3-D obstacle in the compiled 3-D steps' layout (``integrate3d_kernel``): centre x, y, z
        at the stamp, velocity x, y, z, stamp, squared reach, cos and sin of the yaw, the three
        axes, p, q and c."""
        return [*self.center.tolist(), *self.velocity.tolist(), self.stamp, self.reach ** 2, self.Rz[0, 0],
                self.Rz[1, 0], *self.axes.tolist(), self.p, self.q, self.c]


@functools.lru_cache(maxsize=1024)
def _levels(shape, reactive_distance: float, repulsive_distance: float, rays: int):
    """(axes, p, q, c) of the implicit function around ``shape`` (body frame): the superellipse
    N(z) = 1 encloses the shape grown by reactive_distance (R) and N(z) = 1 + c the shape grown by
    repulsive_distance (Q); None when Q does not fit inside R. A shape's levels depend on its
    sizes alone, so a replan with the same obstacles finds them here."""
    p, q, halfs = _EXPONENTS[shape.kind]
    base = halfs(shape) + reactive_distance
    zero = np.zeros(shape.dim)
    unit = ObstacleImplicit("levels", zero, 0.0, zero, 0.0, base, p, q, -0.5)
    axes = base * (1.005 * np.max(unit.norm(_inflated_boundary(shape, reactive_distance, rays))))
    inner = ObstacleImplicit("levels", zero, 0.0, zero, 0.0, axes, p, q, -0.5)
    c = 1.005 * np.max(inner.norm(_inflated_boundary(shape, repulsive_distance, rays))) - 1.0
    return None if c >= 0.0 else (tuple(axes.tolist()), p, q, float(c))
