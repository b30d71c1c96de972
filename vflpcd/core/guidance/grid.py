"""The field precomputed on a grid map G and the discrete-time guidance of eq. (xi_r).

    xi_{k+1} = xi_k + beta chi_c(xi_{k,grid}),  xi_{k,grid} = argmin_{xi_g in G} |xi_k - xi_g|

The grid stores, per cell, chi_P^ and the static actual obstacles' prod cup_Q_i and
sum cap_R_i chi_R_i^ (computed for all cells at once). A step adds the virtual and moving
obstacles' terms at xi_k, normalises, and - the paper's rule against deadlock at singular
points - reuses the previous direction when |chi_c| < epsilon.
"""

from __future__ import annotations

from dataclasses import dataclass

import math

import numpy as np

from vflpcd.core.guidance.field import GuidanceField
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.guidance.primitives import bump, guiding


@dataclass(frozen=True)
class FieldGrid:
    """origin (2,) of cell (0, 0); h cell size; data (nx, ny, 5) = [chi_P^x, chi_P^y, P, V_x, V_y]."""

    origin: np.ndarray
    h: float
    data: np.ndarray

    @classmethod
    def build(cls, field: GuidanceField, bounds: tuple[float, float, float, float], h: float) -> "FieldGrid":
        """Evaluate the static part of ``field`` on every cell of bounds (xmin, xmax, ymin, ymax)."""
        xmin, xmax, ymin, ymax = bounds
        xs = np.arange(xmin, xmax + 0.5 * h, h)
        ys = np.arange(ymin, ymax + 0.5 * h, h)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        pts = np.column_stack([X.ravel(), Y.ravel()])
        data = np.empty((pts.shape[0], 5))
        data[:, 0:2] = field.path_unit(pts)
        P, V = field.actual_terms(field.statics, pts, 0.0)
        data[:, 2], data[:, 3:5] = P, V
        return cls(origin=np.array([xmin, ymin]), h=h, data=data.reshape(len(xs), len(ys), 5))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        nx, ny = self.data.shape[:2]
        return (self.origin[0], self.origin[0] + (nx - 1) * self.h, self.origin[1], self.origin[1] + (ny - 1) * self.h)


@dataclass(frozen=True)
class Integration:
    """xy (K, 2) the planned points; reached: progress reached x_end; inherited: steps that reused
    the previous direction (|chi_c| < epsilon)."""

    xy: np.ndarray
    reached: bool
    inherited: int


def integrate(field: GuidanceField, grid: FieldGrid, start: np.ndarray, x_end: float, beta: float,
              epsilon: float, max_steps: int, t0: float = 0.0, speed: float = 1.0,
              heading: np.ndarray | None = None) -> Integration:
    """Run eq. (xi_r) from start (2,) until the path progress reaches x_end.

    Moving obstacles are placed where they will be when the trajectory gets there, assuming it
    advances at ``speed``; heading (2,) is the direction inherited if the first vector is
    near zero. Raises GuidanceError if the trajectory leaves the grid.
    """
    x, y = float(start[0]), float(start[1])
    ox, oy, h = float(grid.origin[0]), float(grid.origin[1]), grid.h
    nx, ny = grid.data.shape[:2]
    data = grid.data
    prev = None if heading is None else np.asarray(heading, float) / np.linalg.norm(heading)
    enabled = np.ones(len(field.virtuals), bool)
    virt = [(v, v.implicit.center, float(v.implicit.axes[0]), v.parent) for v in field.virtuals]
    if any(v.implicit.p != 2.0 or v.implicit.axes[0] != v.implicit.axes[1] for v in field.virtuals):
        raise GuidanceError("virtual obstacles must be circles")
    k_c, k_r = field.k_c, field.k_r
    po, pd = field.path.progress_frame()  # progress = (xi - po) . pd
    xy = [(x, y)]
    inherited = 0
    reached = False
    for k in range(max_steps):
        i, j = int(round((x - ox) / h)), int(round((y - oy) / h))
        if not (0 <= i < nx and 0 <= j < ny):
            raise GuidanceError(f"the planned path left the grid at ({x:.2f}, {y:.2f}); grid bounds {grid.bounds}")
        cpx, cpy, P, Vx, Vy = data[i, j]
        if field.movers:
            t = t0 + k * beta / max(speed, 1e-3)
            for term in field.movers:
                o = term.implicit
                c = o.center_at(t)
                if (x - c[0]) ** 2 + (y - c[1]) ** 2 > o.reach ** 2:
                    continue
                phi, g = o.value_grad(np.array([[x, y]]), t)
                cup, cap = bump(phi, o.c, field.l1, field.l2)
                chi = guiding(term.gamma, field.k_r, phi, g)[0]
                chi = chi / max(np.hypot(chi[0], chi[1]), 1e-300)
                P *= cup[0]
                Vx, Vy = Vx + cap[0] * chi[0], Vy + cap[0] * chi[1]
        free = P == 1.0  # outside every actual reactive region: where virtual obstacles may act
        for n, (term, c, radius, parent) in enumerate(virt):
            dx, dy = x - c[0], y - c[1]
            r = (dx * dx + dy * dy) ** 0.5
            if not enabled[n] or r >= radius or r == 0.0:
                continue
            if parent.value_at(x, y) <= 0.0:  # inside R_actl: the virtual obstacle stops acting (remark 2)
                enabled[n] = False
                continue
            if not free:
                continue
            # circle virtual obstacle: varphi = r / radius - 1, grad = (dx, dy) / (r radius)
            cv = term.implicit.c
            phi = r / radius - 1.0
            s_i = 0.0 if phi <= cv else math.exp(k_c / (cv - phi))
            gx, gy = dx / (r * radius), dy / (r * radius)
            kx = -term.gamma * gy - k_r * (phi - cv) * gx  # gamma E grad - k_r (varphi - c) grad
            ky = term.gamma * gx - k_r * (phi - cv) * gy
            kn = (kx * kx + ky * ky) ** 0.5
            P *= s_i
            Vx, Vy = Vx + (1.0 - s_i) * kx / kn, Vy + (1.0 - s_i) * ky / kn
        cx, cy = P * cpx + Vx, P * cpy + Vy
        norm = (cx * cx + cy * cy) ** 0.5
        if norm < epsilon:
            if prev is None:
                raise GuidanceError(f"the field vanishes at the start ({x:.2f}, {y:.2f}) and there is no heading to inherit")
            ux, uy = prev
            inherited += 1
        else:
            ux, uy = cx / norm, cy / norm
            prev = (ux, uy)
        x, y = x + beta * ux, y + beta * uy
        xy.append((x, y))
        if (x - po[0]) * pd[0] + (y - po[1]) * pd[1] >= x_end:
            reached = True
            break
    return Integration(xy=np.asarray(xy), reached=reached, inherited=inherited)
