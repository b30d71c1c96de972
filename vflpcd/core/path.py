"""Reference paths: arc-length parametrised polylines in 2-D or 3-D.

A path is stored as a dense polyline (spacing ``ds``) with its arc length, unit tangents and
curvature. It is built from analytic pieces (a line, an arc) or from waypoints through a
twice-differentiable cubic spline (periodic when the path is closed).
"""

from __future__ import annotations

import math

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from vflpcd.core.angles import wrap_angle
from vflpcd.core.norms import row_norms
from vflpcd.core.path_kernel import window_runs


@dataclass(frozen=True)
class Projection:
    """Nearest point on a path.

    s: arc length of the foot point (m); point: (d,); tangent: (d,) unit; heading: yaw of the
    tangent (rad, 2-D: atan2(t_y, t_x)); lateral: signed lateral error by the paper's J_Lat
    convention (X - X_r) sin psi_r - (Y - Y_r) cos psi_r in 2-D (positive right of the path),
    the unsigned distance in 3-D.
    """

    s: float
    point: np.ndarray
    tangent: np.ndarray
    heading: float
    lateral: float


class ReferencePath:
    """Polyline path with arc length ``s`` (N,), ``points`` (N, d), ``tangents`` (N, d), ``curvature`` (N,)."""

    def __init__(self, points: np.ndarray, closed: bool = False) -> None:
        pts = np.asarray(points, dtype=float)
        if pts.ndim != 2 or pts.shape[1] not in (2, 3) or pts.shape[0] < 2:
            raise ValueError(f"path points must have shape (N>=2, 2 or 3), got {pts.shape}")
        if not np.all(np.isfinite(pts)):
            raise ValueError("path points must be finite")
        if closed and np.linalg.norm(pts[-1] - pts[0]) > 1e-9:
            pts = np.vstack([pts, pts[:1]])
        seg = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        if np.any(seg <= 0.0):
            raise ValueError("path points must not repeat consecutively")
        self.closed = closed
        self.points = pts
        self.dim = pts.shape[1]
        self.s = np.concatenate([[0.0], np.cumsum(seg)])
        self.length = float(self.s[-1])
        # tangents by central differences of the dense polyline
        if closed:
            ext = np.vstack([pts[-2:-1], pts, pts[1:2]])
            d = ext[2:] - ext[:-2]
        else:
            d = np.gradient(pts, self.s, axis=0, edge_order=2 if len(pts) > 2 else 1)
        self.tangents = d / np.linalg.norm(d, axis=1, keepdims=True)
        self.headings = np.arctan2(self.tangents[:, 1], self.tangents[:, 0])
        self.curvature = self._curvature()
        self._seg_vec = np.diff(pts, axis=0)
        self._seg_len2 = seg ** 2

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_waypoints(cls, waypoints: np.ndarray, closed: bool = False, ds: float = 0.1) -> "ReferencePath":
        """Cubic spline through waypoints (M, d), sampled every ds metres.

        Centripetal parametrisation (knot spacing sqrt of the chord length) with natural end
        conditions (periodic on a closed path): of the usual choices it overshoots least
        between sparse waypoints and never forms cusps or loops within a segment.
        """
        wp = np.asarray(waypoints, dtype=float)
        if wp.ndim != 2 or wp.shape[1] not in (2, 3) or wp.shape[0] < 2:
            raise ValueError(f"waypoints must have shape (M>=2, 2 or 3), got {wp.shape}")
        if closed and np.linalg.norm(wp[-1] - wp[0]) > 1e-9:
            wp = np.vstack([wp, wp[:1]])
        chord = np.linalg.norm(np.diff(wp, axis=0), axis=1)
        if np.any(chord <= 1e-9):
            raise ValueError("waypoints must not repeat consecutively")
        u = np.concatenate([[0.0], np.cumsum(np.sqrt(chord))])
        if wp.shape[0] == 2:
            spline = lambda q: wp[0] + (q / u[-1])[:, None] * (wp[1] - wp[0])  # noqa: E731
        else:
            spline = CubicSpline(u, wp, axis=0, bc_type="periodic" if closed else "natural")
        q = np.linspace(0.0, u[-1], max(int(np.ceil(np.sum(chord) / (ds / 4))), 8) + 1)
        dense = spline(q)
        # resample at (nearly) uniform arc length
        arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(dense, axis=0), axis=1))])
        n = max(int(np.ceil(arc[-1] / ds)), 2)
        s_new = np.linspace(0.0, arc[-1], n + 1)
        pts = np.column_stack([np.interp(s_new, arc, dense[:, j]) for j in range(wp.shape[1])])
        if closed:
            pts = pts[:-1]
        return cls(pts, closed=closed)

    @classmethod
    def line(cls, start, end, ds: float = 0.1) -> "ReferencePath":
        """Straight segment from start (d,) to end (d,)."""
        start, end = np.asarray(start, float), np.asarray(end, float)
        n = max(int(np.ceil(np.linalg.norm(end - start) / ds)), 1)
        return cls(start + np.linspace(0.0, 1.0, n + 1)[:, None] * (end - start))

    @classmethod
    def arc(cls, center, radius: float, start_angle: float, end_angle: float, ds: float = 0.1) -> "ReferencePath":
        """Planar circular arc, counter-clockwise when end_angle > start_angle. A full turn is closed."""
        full = abs(abs(end_angle - start_angle) - 2 * np.pi) < 1e-9
        n = max(int(np.ceil(radius * abs(end_angle - start_angle) / ds)), 8)
        a = np.linspace(start_angle, end_angle, n + 1)
        pts = np.asarray(center, float) + radius * np.column_stack([np.cos(a), np.sin(a)])
        return cls(pts[:-1] if full else pts, closed=full)

    def run_on(self, length: float, ds: float = 0.1) -> "ReferencePath":
        """This open path followed by a straight of ``length`` m along its end tangent (the road going
        on past its end); the points up to the end are this path's own, so arc lengths there agree."""
        if self.closed:
            raise ValueError("a closed path has no end to run on from")
        if not length > 0.0:
            raise ValueError(f"a run-on is a positive length, got {length!r}")
        n = max(int(np.ceil(length / ds)), 1)
        steps = np.arange(1, n + 1) * (length / n)
        return ReferencePath(np.vstack([self.points, self.points[-1] + steps[:, None] * self.tangents[-1]]))

    # ------------------------------------------------------------------ queries
    def _curvature(self) -> np.ndarray:
        """Curvature from the turn of neighbouring tangents per arc length (signed, left positive, in 2-D)."""
        t, s = self.tangents, self.s
        if self.closed:  # the last point repeats the first
            m = len(s) - 1
            tu = t[:m]
            tp, tn = np.roll(tu, 1, axis=0), np.roll(tu, -1, axis=0)
            ds = np.mod(np.roll(s[:m], -1) - np.roll(s[:m], 1), self.length)
        else:
            if len(s) < 3:
                return np.zeros(len(s))
            tp, tn, ds = t[:-2], t[2:], s[2:] - s[:-2]
        dot = np.einsum("ij,ij->i", tp, tn)
        if self.dim == 2:
            turn = np.arctan2(tp[:, 0] * tn[:, 1] - tp[:, 1] * tn[:, 0], dot)
        else:
            turn = np.arccos(np.clip(dot, -1.0, 1.0))
        k = turn / ds
        if self.closed:
            return np.append(k, k[0])
        return np.concatenate([k[:1], k, k[-1:]])

    def wrap_s(self, s):
        """Arc length mapped into [0, length] (modulo the length on a closed path, clipped otherwise)."""
        if self.closed:
            return np.mod(s, self.length)
        return np.clip(s, 0.0, self.length)

    def point_at(self, s) -> np.ndarray:
        """Points at arc lengths s: scalar -> (d,), (K,) -> (K, d)."""
        s = self.wrap_s(np.asarray(s, dtype=float))
        out = np.stack([np.interp(s, self.s, self.points[:, j]) for j in range(self.dim)], axis=-1)
        return out

    def heading_at(self, s) -> np.ndarray:
        """Yaw of the tangent at arc lengths s (2-D paths)."""
        s = self.wrap_s(np.asarray(s, dtype=float))
        c = np.interp(s, self.s, self.tangents[:, 0])
        si = np.interp(s, self.s, self.tangents[:, 1])
        return np.arctan2(si, c)

    def tangent_at(self, s) -> np.ndarray:
        """Unit tangents at arc lengths s: scalar -> (d,)."""
        s = self.wrap_s(np.asarray(s, dtype=float))
        t = np.stack([np.interp(s, self.s, self.tangents[:, j]) for j in range(self.dim)], axis=-1)
        return t / np.linalg.norm(t, axis=-1, keepdims=True)

    def anchors(self, pts: np.ndarray, s0: float, s1: float, spacing: float = 0.5) -> np.ndarray:
        """The path's points (K, d) nearest to pts (K, d) within the stretch [s0, s1]: found on the
        stretch's chords every ``spacing`` m (cheap), then taken on the path itself at the arc length
        of each foot. A foot on the chords is off the path by up to the chords' sagitta and bends only
        at their vertices, so a point set that follows the feet would bend every ``spacing`` m and run
        straight in between; taken on the path, the anchors bend as smoothly as the path does."""
        s = np.arange(s0, s1, spacing)
        return self.point_at(feet_arc_lengths(pts, self.point_at(s), s))

    def curvature_at(self, s) -> np.ndarray:
        return np.interp(self.wrap_s(np.asarray(s, dtype=float)), self.s, self.curvature)

    def project(self, p, s_hint: float | None = None, back: float = 10.0, ahead: float = 30.0) -> Projection:
        """Nearest point of the path to p (d,).

        With s_hint, only the stretch [s_hint - back, s_hint + ahead] is searched, which keeps
        progress monotone where a path passes near itself (a closed track, a hairpin).
        """
        p = np.asarray(p, dtype=float)
        s, point, d2 = self._nearest(p, s_hint, back, ahead)
        tangent = self.tangent_at(s)  # vertex tangents interpolated: smooth along the path
        heading = float(np.arctan2(tangent[1], tangent[0]))
        if self.dim == 2:
            lateral = float((p[0] - point[0]) * np.sin(heading) - (p[1] - point[1]) * np.cos(heading))
        else:
            lateral = float(np.sqrt(d2))
        return Projection(s=s, point=point, tangent=tangent, heading=heading, lateral=lateral)

    def arc_length_of(self, p, s_hint: float | None = None, back: float = 10.0, ahead: float = 30.0,
                      loop=None) -> float:
        """The arc length s of ``project(p, s_hint, back, ahead)`` alone (no tangent, heading or lateral
        error). ``loop``: ``path_kernel.nearest_arc_length`` compiled (``vflpcd.controllers.loops``), which
        picks and searches the stretch (the same numbers on a planar path, to 1e-12 on a 3-D one); None:
        the numpy search."""
        p = np.asarray(p, dtype=float)
        if loop is None:
            return self._nearest(p, s_hint, back, ahead)[0]
        everything = s_hint is None
        lo, span = (0.0, 0.0) if everything else (s_hint - back, back + ahead)
        return float(loop(p, self.points, self.s, self._seg_vec, self._seg_len2, lo, span, self.closed, everything))

    def _searched(self, s_hint: float | None, back: float, ahead: float) -> slice | np.ndarray:
        """The segments that ``project`` searches: all without s_hint, else those overlapping
        [s_hint - back, s_hint + ahead] (a slice on an open path, indices on a closed one)."""
        if s_hint is None:
            return slice(0, len(self._seg_vec))
        a0, a1, b0, b1 = (int(i) for i in window_runs(self.s, s_hint - back, back + ahead, self.closed))
        if not self.closed:
            return slice(a0, a1)
        if b1 <= b0:
            return np.arange(a0, a1)
        return np.concatenate([np.arange(a0, a1), np.arange(b0, b1)])

    def _nearest(self, p: np.ndarray, s_hint: float | None, back: float, ahead: float
                 ) -> tuple[float, np.ndarray, float]:
        """Arc length, point (d,) and squared distance of the nearest point of the searched stretch (``project``)."""
        idx = self._searched(s_hint, back, ahead)
        a = self.points[idx]
        v = self._seg_vec[idx]
        w = np.minimum(np.maximum(np.einsum("ij,ij->i", p - a, v) / self._seg_len2[idx], 0.0), 1.0)
        foot = a + w[:, None] * v
        e = p - foot
        d2 = np.einsum("ij,ij->i", e, e)
        k = int(np.argmin(d2))
        i = idx.start + k if isinstance(idx, slice) else int(idx[k])
        s = float(self.s[i] + w[k] * np.sqrt(self._seg_len2[i]))
        return s, foot[k], float(d2[k])


def progress_delta(path: ReferencePath, s_new: float, s_old: float) -> float:
    """Signed arc-length advance from s_old to s_new, unwrapped across the seam of a closed path."""
    d = s_new - s_old
    if path.closed:
        d = (d + 0.5 * path.length) % path.length - 0.5 * path.length
    return d


__all__ = ["Projection", "ReferencePath", "nearest_on_polyline", "progress_delta", "wrap_angle"]


def nearest_on_polyline(p: np.ndarray, xy: np.ndarray, loop=None) -> tuple[float, int]:
    """Distance (m) from point p (d,) to the polyline through xy (K, d), and the index of the
    segment's first vertex that is nearest; ``loop``: ``path_kernel.polyline_nearest`` compiled (the
    same numbers, for a p and xy of floats)."""
    xy = np.asarray(xy, float)
    if len(xy) == 1:
        return float(np.linalg.norm(p - xy[0])), 0
    if loop is not None:
        d2, i = loop(np.ascontiguousarray(p, dtype=float), np.ascontiguousarray(xy))
        return math.sqrt(d2), i
    a, ab = xy[:-1], np.diff(xy, axis=0)
    w = np.einsum("kd,kd->k", ab, ab)
    h = np.clip(np.einsum("kd,kd->k", p - a, ab) / np.maximum(w, 1e-12), 0.0, 1.0)
    e = a + h[:, None] * ab - p
    d2 = (e * e).sum(axis=1)
    i = int(np.argmin(d2))
    return float(np.sqrt(d2[i])), i


def feet_on_polyline(pts: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """The nearest point of the polyline through xy (M, d) to each of pts (K, d): (K, d); the batch
    form of ``nearest_on_polyline`` (which stays single-point: the tracking monitor calls it every
    tick, and the batch form costs it 1.7 us more a call)."""
    i, h = _feet(pts, xy)
    xy = np.asarray(xy, float)
    return xy[i] + h[:, None] * (xy[i + 1] - xy[i])


def feet_arc_lengths(pts: np.ndarray, xy: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The parameter s (K,) of the nearest point of the polyline through xy (M, d) to each of pts
    (K, d), where the polyline's vertices have the parameters s (M,) (interpolated along a segment)."""
    i, h = _feet(pts, xy)
    s = np.asarray(s, float)
    return s[i] + h * (s[i + 1] - s[i])


def _feet(pts: np.ndarray, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """For each of pts (K, d): the segment i (K,) of the polyline through xy (M, d) that holds the
    nearest point and its fraction h (K,) along that segment."""
    pts, xy = np.asarray(pts, float), np.asarray(xy, float)
    a, ab = xy[:-1], np.diff(xy, axis=0)
    w = np.maximum(np.einsum("md,md->m", ab, ab), 1e-12)
    h = np.clip(np.einsum("kmd,md->km", pts[:, None, :] - a[None], ab) / w, 0.0, 1.0)
    feet = a[None] + h[..., None] * ab[None]
    i = np.argmin(((feet - pts[:, None, :]) ** 2).sum(axis=2), axis=1)
    return i, h[np.arange(len(pts)), i]


def unit_differences(points: np.ndarray) -> np.ndarray:
    """The unit directions (T, d) along points (T >= 2, d): central differences inside, one-sided at the
    ends (``np.gradient(points, axis=0)``, the same numbers), normalised (a zero difference stays ~0)."""
    diff = np.empty_like(points)
    diff[1:-1] = (points[2:] - points[:-2]) / 2.0
    diff[0] = points[1] - points[0]
    diff[-1] = points[-1] - points[-2]
    return diff / np.maximum(row_norms(diff, keepdims=True), 1e-9)
