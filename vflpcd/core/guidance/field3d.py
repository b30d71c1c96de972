"""The composite guiding vector field in 3-D, for the quadrotor (beyond the paper, which is planar).

The path is the intersection of two surfaces phi_1 = phi_2 = 0 (Yao's higher-dimensional
guiding vector field):
    chi_P = grad phi_1 x grad phi_2 - k_p phi_1 grad phi_1 - k_p phi_2 grad phi_2.
``GraphPath3D`` fits the path as a graph in a frame turned about z to the chord's heading:
phi_1 = y' - f(x'), phi_2 = z' - g(x') (C2 cubic splines, extended linearly), so that
grad phi_1 x grad phi_2 = R [1, f', g'] points forwards and never vanishes.

An obstacle i (a 3-D superquadric varphi_i, ``ObstacleImplicit``) is passed in a detour plane
through its centre spanned by the path tangent t and a side direction e (left, right, up or
down, the one that leaves the path least); with the plane normal m = t x e,
    chi_R_i = gamma_i grad varphi_i x m - k_r varphi_i grad varphi_i,
which circulates in the detour plane around the reactive boundary. The same bump functions
blend them: chi = (prod_i cup_Q_i) chi_P^ + sum_i cap_R_i chi_R_i^.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import CubicSpline

from vflpcd.core.guidance.implicit import GuidanceError, ObstacleImplicit, chord_frame
from vflpcd.core.guidance.primitives import bump, unit
from vflpcd.core.path import ReferencePath


def _rot_z(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class GraphPath3D:
    """The path as y' = f(x'), z' = g(x') in the frame (origin, rotation about z by theta)."""

    def __init__(self, origin: np.ndarray, theta: float, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> None:
        if np.any(np.diff(xs) <= 0.0):
            raise GuidanceError("path portion is not a graph in its local frame (x' must increase)")
        self.origin, self.R = np.asarray(origin, float), _rot_z(theta)
        self.f, self.g = CubicSpline(xs, ys, bc_type="natural"), CubicSpline(xs, zs, bc_type="natural")
        self.df, self.dg = self.f.derivative(), self.g.derivative()
        self.x0, self.x1 = float(xs[0]), float(xs[-1])
        # the compiled steps' form (``integrate3d_kernel``): the breakpoints (m,) and the pieces'
        # coefficients of f, f', g, g', highest power first, (4, m - 1, 4) (the derivatives' led by 0)
        self.knots = np.ascontiguousarray(self.f.x, dtype=float)
        self.pieces = np.ascontiguousarray(np.stack([np.vstack([np.zeros((4 - len(sp.c), sp.c.shape[1])), sp.c]).T
                                                     for sp in (self.f, self.df, self.g, self.dg)]))

    @classmethod
    def from_reference(cls, path: ReferencePath, s0: float, s1: float, spacing: float = 1.0) -> "GraphPath3D":
        """Fit the stretch [s0, s1] of a 3-D reference path in the frame of its horizontal chord."""
        origin, theta, local = chord_frame(path, s0, s1, spacing)
        return cls(origin, theta, local[:, 0], local[:, 1], local[:, 2])

    def _eval(self, spline, deriv, x):
        xc = np.clip(x, self.x0, self.x1)
        d = deriv(xc)
        return spline(xc) + d * (x - xc), d

    def value_grad(self, p: np.ndarray):
        """p (N, 3) -> phi_1, phi_2 (N,), grad phi_1, grad phi_2 (N, 3)."""
        q = (p - self.origin) @ self.R
        f, df = self._eval(self.f, self.df, q[:, 0])
        g, dg = self._eval(self.g, self.dg, q[:, 0])
        one, zero = np.ones_like(df), np.zeros_like(df)
        g1 = np.column_stack([-df, one, zero]) @ self.R.T
        g2 = np.column_stack([-dg, zero, one]) @ self.R.T
        return q[:, 1] - f, q[:, 2] - g, g1, g2

    def progress_frame(self) -> tuple[np.ndarray, np.ndarray]:
        return self.origin, self.R[:, 0]

    def straighten(self, p: np.ndarray) -> np.ndarray:
        """World points (K, 3) -> (x', y' - f(x'), z' - g(x')): the path becomes the x' axis."""
        q = (np.asarray(p, float) - self.origin) @ self.R
        q[:, 1] -= self._eval(self.f, self.df, q[:, 0])[0]
        q[:, 2] -= self._eval(self.g, self.dg, q[:, 0])[0]
        return q

    def bend(self, q: np.ndarray) -> np.ndarray:
        """The inverse of ``straighten``: (x', offsets) (K, 3) -> world points."""
        q = np.array(q, float)
        q[:, 1] += self._eval(self.f, self.df, q[:, 0])[0]
        q[:, 2] += self._eval(self.g, self.dg, q[:, 0])[0]
        return self.origin + q @ self.R.T

    def progress(self, p: np.ndarray) -> np.ndarray:
        return (p - self.origin) @ self.R[:, 0]

    def tangent(self, p: np.ndarray) -> np.ndarray:
        """Unit forward tangent (3,) at the abscissa of p (3,)."""
        x = float((p - self.origin) @ self.R[:, 0])
        x = min(max(x, self.x0), self.x1)
        t = self.R @ np.array([1.0, float(self.df(x)), float(self.dg(x))])
        return t / np.linalg.norm(t)


@dataclass(frozen=True)
class Obstacle3D:
    """An actual obstacle in 3-D: its implicit, side direction e (3,), detour-plane normal m (3,), gamma."""

    implicit: ObstacleImplicit
    side: np.ndarray
    normal: np.ndarray
    gamma: float


@dataclass
class GuidanceField3D:
    path: GraphPath3D
    k_p: float
    k_r: float
    l1: float
    l2: float
    statics: list[Obstacle3D] = field(default_factory=list)
    movers: list[Obstacle3D] = field(default_factory=list)

    def path_unit(self, pts: np.ndarray) -> np.ndarray:
        """chi_P^ (N, 3)."""
        p1, p2, g1, g2 = self.path.value_grad(pts)
        chi = np.cross(g1, g2) - self.k_p * p1[:, None] * g1 - self.k_p * p2[:, None] * g2
        return unit(chi)[0]

    def repulsive_unit(self, ob: Obstacle3D, gamma: float, pts: np.ndarray, t: float = 0.0):
        """(varphi (N,), chi_R_i^ (N, 3)) with direction gamma."""
        phi, g = ob.implicit.value_grad(pts, t)
        chi = gamma * np.cross(g, ob.normal) - self.k_r * phi[:, None] * g
        return phi, unit(chi)[0]

    def composite(self, pts: np.ndarray, t: float = 0.0) -> np.ndarray:
        """chi (N, 3) with every obstacle's planned gamma."""
        P = np.ones(len(pts))
        V = np.zeros((len(pts), 3))
        for ob in self.statics + self.movers:
            phi, chi = self.repulsive_unit(ob, ob.gamma, pts, t)
            cup, cap = bump(phi, ob.implicit.c, self.l1, self.l2)
            P *= cup
            V += cap[:, None] * chi
        return P[:, None] * self.path_unit(pts) + V
