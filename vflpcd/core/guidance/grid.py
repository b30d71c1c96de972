"""The field precomputed on grid maps G and the discrete-time guidance of eq. (xi_r).

    xi_{k+1} = xi_k + beta chi_c(xi_{k,grid}),  xi_{k,grid} = argmin_{xi_g in G} |xi_k - xi_g|

A global grid holds chi_P^ (filled block by block where the integration goes); each static
actual obstacle has a local grid over its reactive region's bounding box holding cup_Q_i and
chi_R_i^ for both directions gamma_i = +1 and -1 (all cells computed at once). A step takes the
path's chi_P^ interpolated between the four nodes around xi_k, multiplies and adds the terms of
the obstacles whose grids contain xi_k (their nearest cells, as the equation says), adds the
virtual and moving obstacles' terms evaluated at xi_k, normalises and - the paper's rule against
deadlock at singular points - reuses the previous direction when |chi_c| < epsilon.

The path's term is interpolated, not read at the nearest node: within h / 2 of the path the nearest
node is one of the path's own row, where chi_P^ is the path's tangent, so a trajectory started in
that band (a robot 1-5 cm off its route, at every replan) ran parallel to the path at its offset
for the whole plan, and the robot's tracking error at each replan was added to the next plan's
(a car on a straight road with no obstacle drifted 12 mm further off at every replan, 42 mm after
four). Interpolated, chi_P^ turns towards the path in proportion to the offset (k_p phi) down to it.

Direction of each obstacle: the planner's side rule (the term's gamma_i), flipped once, when
the trajectory first enters the reactive region, if its circulation there would run against the
path's direction of travel (cos < -0.3). An obstacle entered from the side opposite to the one
planned is thus never circled backwards.
"""

from __future__ import annotations

import functools
from collections import OrderedDict
from dataclasses import dataclass
from typing import Callable

import numpy as np

from vflpcd.core.guidance.field import GuidanceField
from vflpcd.core.guidance.implicit import GuidanceError
from vflpcd.core.guidance.integrate_kernel import ENTERED, FILL, LEFT_GRID, REACHED, VANISHED, step_loop
from vflpcd.core.guidance.primitives import bump, guiding, unit

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
    vectorised ``unit_at``, or by ``loop`` (``path_grid_kernel.fill_loop`` compiled) with the
    path's ``pieces`` (``GraphPath.pieces``, gamma_0, k_p) where it is given: the same numbers to
    rounding, a block in tens of microseconds where numpy took about 0.3 ms (a quarter of a
    replan's time); ``filled[bi][bj]``: whether block (bi, bj) is."""

    xs: np.ndarray
    ys: np.ndarray
    unit_at: Callable[[np.ndarray], np.ndarray]
    filled: list
    loop: Callable | None = None
    pieces: tuple = ()

    @classmethod
    def lazy(cls, bounds: tuple[float, float, float, float], h: float, unit_at, loop: Callable | None = None,
             pieces: tuple = ()) -> "PathGrid":
        xs, ys = Grid.axes(bounds, h)
        filled = [[False] * -(-len(ys) // BLOCK) for _ in range(-(-len(xs) // BLOCK))]
        return cls(np.array([xs[0], ys[0]]), h, np.empty((len(xs), len(ys), 2)), xs, ys, unit_at, filled,
                   loop, pieces)

    def fill(self, bi: int, bj: int) -> None:
        """Compute block (bi, bj)."""
        xs, ys = self.xs[bi * BLOCK:(bi + 1) * BLOCK], self.ys[bj * BLOCK:(bj + 1) * BLOCK]
        block = self.data[bi * BLOCK:(bi + 1) * BLOCK, bj * BLOCK:(bj + 1) * BLOCK]
        if self.loop is not None:       # into a buffer of its own: a block's view is strided or not, a type each
            out = np.empty(block.shape)
            self.loop(xs, ys, *self.pieces, out)
            block[...] = out
        else:
            X, Y = np.meshgrid(xs, ys, indexing="ij")
            block[...] = self.unit_at(np.column_stack([X.ravel(), Y.ravel()])).reshape(len(xs), len(ys), 2)
        self.filled[bi][bj] = True


@dataclass(frozen=True)
class FieldGrid:
    """The global chi_P^ grid (2 channels, filled as the integration reaches it) and one local grid
    per static obstacle (5 channels: cup_Q, chi_R^ for gamma = +1, chi_R^ for gamma = -1)."""

    path: PathGrid
    obstacles: tuple[Grid, ...]

    @classmethod
    def build(cls, field: GuidanceField, bounds: tuple[float, float, float, float], h: float,
              fill: Callable | None = None) -> "FieldGrid":
        """The grids of ``field`` over ``bounds`` at spacing h; ``fill``: ``path_grid_kernel.fill_loop``
        compiled, for a field whose path is a ``GraphPath`` (None: numpy fills the path's blocks)."""
        pieces = () if fill is None else (*field.path.pieces(), field.gamma0, field.k_p)
        path = PathGrid.lazy(bounds, h, field.path_unit, fill, pieces)
        return cls(path=path, obstacles=tuple(_local_grid(term.implicit, field, h) for term in field.statics))

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        return self.path.bounds

    @functools.cached_property
    def packed(self) -> tuple[np.ndarray, np.ndarray]:
        """The local grids in ``integrate_kernel.step_loop``'s layout: per grid its origin x, y,
        cells nx, ny and offset into the second array, their data flattened one after another."""
        cells = [g.data.shape[:2] for g in self.obstacles]
        offsets = np.cumsum([0] + [5 * nx * ny for nx, ny in cells])
        table = np.array([[g.origin[0], g.origin[1], nx, ny, off]
                          for g, (nx, ny), off in zip(self.obstacles, cells, offsets)], dtype=float).reshape(-1, 5)
        return table, np.concatenate([g.data.ravel() for g in self.obstacles] + [np.zeros(0)])


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


LOCAL_GRID_BYTES = 32 * 2**20  # static obstacles' local grids kept for the next replans, in bytes of
_local_grids: OrderedDict = OrderedDict()  # data at most (the least recently used dropped first)


def _local_grid(o, field: GuidanceField, h: float) -> Grid:
    """The local grid of static obstacle o (5 channels over its reactive region's bounding box),
    computed once for o's numbers, the field's k_r, l1, l2 and h: a static obstacle is the same
    at the next replan (perception stamps it anew: the stamp is not in the key), and computing
    the grids was most of a replan's preparation."""
    key = (*o.center_at(0.0), *o.velocity, o.yaw, *o.axes, o.p, o.c, h, field.k_r, field.l1, field.l2)   # not the stamp
    grid = _local_grids.get(key)
    if grid is None:
        r = o.reach + h
        b = (o.center[0] - r, o.center[0] + r, o.center[1] - r, o.center[1] + r)
        q, qshape = Grid.cells(b, h)
        phi, g = o.value_grad(q)
        cup, _ = bump(phi, o.c, field.l1, field.l2)
        data = np.column_stack([cup, unit(guiding(1.0, field.k_r, phi, g))[0], unit(guiding(-1.0, field.k_r, phi, g))[0]])
        grid = Grid(np.array([b[0], b[2]]), h, data.reshape(*qshape, 5))
        grid.data.flags.writeable = False
        _local_grids[key] = grid
        while len(_local_grids) > 1 and sum(g.data.nbytes for g in _local_grids.values()) > LOCAL_GRID_BYTES:
            _local_grids.popitem(last=False)
    else:
        _local_grids.move_to_end(key)
    return grid


def forget_local_grids() -> None:
    """Drop the kept local grids (``_local_grid``): the next field grid computes every one again."""
    _local_grids.clear()


def integrate(field: GuidanceField, grid: FieldGrid, start: np.ndarray, x_end: float, beta: float,
              epsilon: float, max_steps: int, t0: float = 0.0, speed: float = 1.0,
              heading: np.ndarray | None = None, step_times: np.ndarray | None = None, loop=None) -> Integration:
    """Run eq. (xi_r) from start (2,) until the path progress reaches x_end.

    Moving obstacles are placed where they will be when the trajectory gets there: at
    step_times[k] for step k (from an earlier pass's speed plan) or, beyond them, advancing at
    ``speed``; heading (2,) is the direction inherited if the first vector is near zero. Raises
    GuidanceError if the trajectory leaves the grid. The steps are ``integrate_kernel.step_loop``'s:
    ``loop`` is it compiled (``vflpcd.controllers.loops.integrate_loop``), None runs it interpreted.
    """
    step = step_loop if loop is None else loop
    pg = grid.path
    if any(v.implicit.p != 2.0 or v.implicit.axes[0] != v.implicit.axes[1] for v in field.virtuals):
        raise GuidanceError("virtual obstacles must be circles")
    state = np.zeros(7)
    state[:2] = start[:2]
    if heading is not None:
        state[2:5] = *(np.asarray(heading, float) / np.linalg.norm(heading)), 1.0
    xy = np.empty((max_steps + 1, 2))
    xy[0] = state[:2]
    filled = np.array(pg.filled, dtype=bool)
    pgrid = np.array([pg.origin[0], pg.origin[1], 1.0 / pg.h, BLOCK])
    table, sdata = grid.packed
    statics = np.column_stack([table, [term.gamma for term in field.statics]]) if len(table) else np.zeros((0, 6))
    gammas = np.zeros(len(field.statics))
    movers = np.array([term.implicit.row() + [term.gamma] for term in field.movers]).reshape(-1, 13)
    virtuals = np.array([_virtual_row(v) for v in field.virtuals]).reshape(-1, 18)
    virtual_off = np.full(len(field.virtuals), -1, dtype=np.int64)
    po, pd = field.path.progress_frame()  # progress = (xi - po) . pd
    params = np.array([field.l1, field.l2, field.k_c, field.k_r, epsilon, beta, x_end, max_steps,
                       po[0], po[1], pd[0], pd[1], t0, speed], dtype=float)
    times = np.zeros(0) if step_times is None else np.asarray(step_times, float)
    aux = np.zeros(3, dtype=np.int64)
    for _ in range(len(field.statics) + filled.size + 1):   # each resumption fills a block or decides a gamma_i
        status = step(state, xy, pg.data, filled, pgrid, statics, sdata, gammas, movers, virtuals, virtual_off,
                      params, times, aux)
        if status == FILL:
            pg.fill(int(aux[0]), int(aux[1]))
            filled[aux[0], aux[1]] = True
        elif status == ENTERED:  # first entry into R_i: keep the side rule's gamma_i unless it runs backwards
            n, a, b = (int(v) for v in aux)
            side = field.statics[n].gamma
            if side not in (1.0, -1.0):        # 0 would leave gamma_i undecided and the steps asking again
                raise GuidanceError(f"obstacle {field.statics[n].implicit.name!r}: gamma must be +1 or -1, got {side}")
            cell = grid.obstacles[n].data[a, b]
            tx, ty = field.path.tangent(float(state[0]), float(state[1]))
            rx, ry = (cell[1], cell[2]) if side > 0 else (cell[3], cell[4])
            gammas[n] = -side if rx * tx + ry * ty < BACKWARDS else side
        elif status == LEFT_GRID:
            raise GuidanceError(f"the planned path left the grid at ({state[0]:.2f}, {state[1]:.2f}); "
                                f"grid bounds {pg.bounds}")
        elif status == VANISHED:
            raise GuidanceError(f"the field vanishes at the start ({state[0]:.2f}, {state[1]:.2f}) and there is "
                                "no heading to inherit")
        else:
            break
    else:
        raise GuidanceError("the integration's steps kept asking for blocks or directions they had been given")
    k = int(state[6])
    return Integration(xy=xy[:k + 1].copy(), reached=status == REACHED, inherited=int(state[5]),
                       gammas=tuple(None if g == 0.0 else float(g) for g in gammas),
                       virtual_off=tuple(None if v < 0 else int(v) for v in virtual_off))


def _virtual_row(term) -> list[float]:
    """A virtual obstacle's row of ``step_loop``'s ``virtuals``."""
    o = term.implicit
    return [o.center[0], o.center[1], o.axes[0], o.c, term.gamma, term.x_stop] + term.parent.row()
