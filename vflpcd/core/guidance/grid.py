"""The field precomputed on grid maps G and the discrete-time guidance of eq. (xi_r).

    xi_{k+1} = xi_k + beta chi_c(xi_{k,grid}),  xi_{k,grid} = argmin_{xi_g in G} |xi_k - xi_g|

A global grid holds chi_P^ (filled block by block where the integration goes); each static
actual obstacle has a local grid over its reactive region's bounding box holding cup_Q_i and
chi_R_i^ for both directions gamma_i = +1 and -1 (all cells computed at once). A step multiplies and adds the terms of the obstacles whose grids
contain xi_k, adds the virtual and moving obstacles' terms evaluated at xi_k, normalises and -
the paper's rule against deadlock at singular points - reuses the previous direction when
|chi_c| < epsilon.

Direction of each obstacle: the planner's side rule (the term's gamma_i), flipped once, when
the trajectory first enters the reactive region, if its circulation there would run against the
path's direction of travel (cos < -0.3). An obstacle entered from the side opposite to the one
planned is thus never circled backwards.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable

import numpy as np

from vflpcd.core.guidance.field import GuidanceField
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.guidance.primitives import bump, cup_at, guiding, guiding_at, unit

BACKWARDS = -0.3  # cos between the planned circulation and the path tangent that flips gamma_i at entry


@dataclass(frozen=True)
class Grid:
    """origin (2,) of cell (0, 0); h cell size; data (nx, ny, channels)."""

    origin: np.ndarray
    h: float
    data: np.ndarray

    @staticmethod
    def axes(bounds: tuple[float, float, float, float], h: float) -> tuple[np.ndarray, np.ndarray]:
        """The cells' x and y coordinates over bounds (xmin, xmax, ymin, ymax) at spacing h."""
        xmin, xmax, ymin, ymax = bounds
        return np.arange(xmin, xmax + 0.5 * h, h), np.arange(ymin, ymax + 0.5 * h, h)

    @staticmethod
    def cells(bounds: tuple[float, float, float, float], h: float) -> tuple[np.ndarray, tuple[int, int]]:
        xs, ys = Grid.axes(bounds, h)
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        return np.column_stack([X.ravel(), Y.ravel()]), (len(xs), len(ys))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        nx, ny = self.data.shape[:2]
        return (float(self.origin[0]), float(self.origin[0] + (nx - 1) * self.h),
                float(self.origin[1]), float(self.origin[1] + (ny - 1) * self.h))


BLOCK = 32  # cells on a side of the blocks in which the path's grid is filled


@dataclass(frozen=True)
class PathGrid(Grid):
    """The global chi_P^ grid (2 channels), filled a block of ``BLOCK`` x ``BLOCK`` cells at a time
    when the integration first reaches the block (``fill``, called by ``integrate``): the corridor
    is wide (8 m beside the path, the obstacles' reactive regions) and a plan visits a small part of
    it. A block's cells are those of the whole grid (``xs``, ``ys``), evaluated by the same
    vectorised ``unit_at``; ``filled[bi][bj]``: whether block (bi, bj) is."""

    xs: np.ndarray
    ys: np.ndarray
    unit_at: Callable[[np.ndarray], np.ndarray]
    filled: list

    @classmethod
    def lazy(cls, bounds: tuple[float, float, float, float], h: float, unit_at) -> "PathGrid":
        xs, ys = Grid.axes(bounds, h)
        filled = [[False] * -(-len(ys) // BLOCK) for _ in range(-(-len(xs) // BLOCK))]
        return cls(np.array([xs[0], ys[0]]), h, np.empty((len(xs), len(ys), 2)), xs, ys, unit_at, filled)

    def fill(self, bi: int, bj: int) -> None:
        """Compute block (bi, bj)."""
        xs, ys = self.xs[bi * BLOCK:(bi + 1) * BLOCK], self.ys[bj * BLOCK:(bj + 1) * BLOCK]
        X, Y = np.meshgrid(xs, ys, indexing="ij")
        self.data[bi * BLOCK:(bi + 1) * BLOCK, bj * BLOCK:(bj + 1) * BLOCK] = \
            self.unit_at(np.column_stack([X.ravel(), Y.ravel()])).reshape(len(xs), len(ys), 2)
        self.filled[bi][bj] = True


@dataclass(frozen=True)
class FieldGrid:
    """The global chi_P^ grid (2 channels, filled as the integration reaches it) and one local grid
    per static obstacle (5 channels: cup_Q, chi_R^ for gamma = +1, chi_R^ for gamma = -1)."""

    path: PathGrid
    obstacles: tuple[Grid, ...]

    @classmethod
    def build(cls, field: GuidanceField, bounds: tuple[float, float, float, float], h: float) -> "FieldGrid":
        path = PathGrid.lazy(bounds, h, field.path_unit)
        local = []
        for term in field.statics:
            o = term.implicit
            r = o.reach + h
            b = (o.center[0] - r, o.center[0] + r, o.center[1] - r, o.center[1] + r)
            q, qshape = Grid.cells(b, h)
            phi, g = o.value_grad(q)
            cup, _ = bump(phi, o.c, field.l1, field.l2)
            data = np.column_stack([cup, unit(guiding(1.0, field.k_r, phi, g))[0],
                                    unit(guiding(-1.0, field.k_r, phi, g))[0]])
            local.append(Grid(np.array([b[0], b[2]]), h, data.reshape(*qshape, 5)))
        return cls(path=path, obstacles=tuple(local))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return self.path.bounds


def step_time(k: int, t0: float, beta: float, speed: float, step_times) -> float:
    """When the trajectory reaches step k: from step_times (K,) (an array or a list) where known,
    else at ``speed``."""
    if step_times is not None and len(step_times):
        if k < len(step_times):
            return float(step_times[k])
        return float(step_times[-1]) + (k - len(step_times) + 1) * beta / max(speed, 1e-3)
    return t0 + k * beta / max(speed, 1e-3)


@dataclass(frozen=True)
class Integration:
    """xy (K, 2) the planned points; reached: progress reached x_end; inherited: steps that reused
    the previous direction (|chi_c| < epsilon); gammas: the direction fixed for each static obstacle
    (None if never entered); virtual_off: the step at which each virtual obstacle stopped acting."""

    xy: np.ndarray
    reached: bool
    inherited: int
    gammas: tuple
    virtual_off: tuple


def integrate(field: GuidanceField, grid: FieldGrid, start: np.ndarray, x_end: float, beta: float,
              epsilon: float, max_steps: int, t0: float = 0.0, speed: float = 1.0,
              heading: np.ndarray | None = None, step_times: np.ndarray | None = None) -> Integration:
    """Run eq. (xi_r) from start (2,) until the path progress reaches x_end.

    Moving obstacles are placed where they will be when the trajectory gets there: at
    step_times[k] for step k (from an earlier pass's speed plan) or, beyond them, advancing at
    ``speed``; heading (2,) is the direction inherited if the first vector is near zero. Raises
    GuidanceError if the trajectory leaves the grid.
    """
    x, y = float(start[0]), float(start[1])
    pg = grid.path
    ox, oy, h = float(pg.origin[0]), float(pg.origin[1]), pg.h
    nx, ny = pg.data.shape[:2]
    pdata, filled = pg.data, pg.filled
    inv_h = 1.0 / h
    # per obstacle: origin, the float cell-index limits (nx - 0.5, ny - 0.5), data, the side rule's gamma
    local = [(float(g.origin[0]), float(g.origin[1]), g.data.shape[0] - 0.5, g.data.shape[1] - 0.5, g.data, term.gamma)
             for g, term in zip(grid.obstacles, field.statics)]
    gammas: list[float | None] = [None] * len(local)
    prev = None if heading is None else tuple(np.asarray(heading, float) / np.linalg.norm(heading))
    virtual_off: list[int | None] = [None] * len(field.virtuals)
    virt = [(v, v.implicit.center, float(v.implicit.axes[0])) for v in field.virtuals]
    if any(v.implicit.p != 2.0 or v.implicit.axes[0] != v.implicit.axes[1] for v in field.virtuals):
        raise GuidanceError("virtual obstacles must be circles")
    k_c, k_r = field.k_c, field.k_r
    # per mover, in plain floats: its centre at its stamp, velocity, stamp and squared reach
    movers = [(term, term.implicit, float(term.implicit.center[0]), float(term.implicit.center[1]),
               float(term.implicit.velocity[0]), float(term.implicit.velocity[1]), term.implicit.stamp,
               term.implicit.reach ** 2) for term in field.movers]
    po, pd = field.path.progress_frame()  # progress = (xi - po) . pd
    if step_times is not None:
        step_times = step_times.tolist()      # plain floats, indexed every step
    xy = [(x, y)]
    inherited = 0
    reached = False
    for k in range(max_steps):
        fi, fj = (x - ox) * inv_h + 0.5, (y - oy) * inv_h + 0.5  # nearest cell: floor(index + 0.5)
        if not (0.0 <= fi < nx and 0.0 <= fj < ny):
            raise GuidanceError(f"the planned path left the grid at ({x:.2f}, {y:.2f}); grid bounds {pg.bounds}")
        i, j = int(fi), int(fj)
        if not filled[i // BLOCK][j // BLOCK]:
            pg.fill(i // BLOCK, j // BLOCK)
        cpx, cpy = pdata.item(i, j, 0), pdata.item(i, j, 1)
        P, Vx, Vy = 1.0, 0.0, 0.0
        for n, (gx0, gy0, gnx, gny, gdata, gamma_side) in enumerate(local):
            fa, fb = (x - gx0) * inv_h, (y - gy0) * inv_h
            if not (-0.5 <= fa < gnx and -0.5 <= fb < gny):
                continue
            a, b = int(fa + 0.5), int(fb + 0.5)
            cup = gdata.item(a, b, 0)
            if cup == 1.0:
                continue
            rpx, rpy, rmx, rmy = gdata.item(a, b, 1), gdata.item(a, b, 2), gdata.item(a, b, 3), gdata.item(a, b, 4)
            if gammas[n] is None:  # first entry into R_i: keep the side rule's gamma_i unless it runs backwards
                tx, ty = field.path.tangent(x, y)
                rx, ry = (rpx, rpy) if gamma_side > 0 else (rmx, rmy)
                gammas[n] = -gamma_side if rx * tx + ry * ty < BACKWARDS else gamma_side
            rx, ry = (rpx, rpy) if gammas[n] > 0 else (rmx, rmy)
            P *= cup
            Vx, Vy = Vx + (1.0 - cup) * rx, Vy + (1.0 - cup) * ry
        if movers:
            t = step_time(k, t0, beta, speed, step_times)
            for term, o, cx, cy, vx, vy, stamp, reach2 in movers:
                if (x - cx - vx * (t - stamp)) ** 2 + (y - cy - vy * (t - stamp)) ** 2 > reach2:
                    continue
                phi, gx, gy = o.value_grad_at(x, y, t)
                cup = cup_at(phi, o.c, field.l1, field.l2)
                chx, chy = guiding_at(term.gamma, field.k_r, phi, gx, gy)
                chn = max(math.hypot(chx, chy), 1e-300)
                P *= cup
                Vx, Vy = Vx + (1.0 - cup) * chx / chn, Vy + (1.0 - cup) * chy / chn
        free = P == 1.0  # outside every actual reactive region: where virtual obstacles may act
        progress = (x - po[0]) * pd[0] + (y - po[1]) * pd[1]
        for n, (term, c, radius) in enumerate(virt):
            if virtual_off[n] is not None:
                continue
            dx, dy = x - c[0], y - c[1]
            r = (dx * dx + dy * dy) ** 0.5
            if r >= radius or r == 0.0:
                continue
            if progress >= term.x_stop or term.parent.value_at(x, y) <= 0.0:
                virtual_off[n] = k  # past the entry into R_actl, or inside it (remark 2): stop acting
                continue
            if not free:
                continue
            # circle virtual obstacle: varphi = r / radius - 1, grad = (dx, dy) / (r radius)
            cv = term.implicit.c
            phi = r / radius - 1.0
            s_i = 0.0 if phi <= cv else math.exp(k_c / (cv - phi))
            gx, gy = dx / (r * radius), dy / (r * radius)
            kx, ky = guiding_at(term.gamma, k_r, phi - cv, gx, gy)  # gamma E grad - k_r (varphi - c) grad
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
    return Integration(xy=np.asarray(xy), reached=reached, inherited=inherited, gammas=tuple(gammas),
                       virtual_off=tuple(virtual_off))
