"""The plan's reference states over the horizon, read from one table built when the plan arrives.

A plan's trajectory is sampled every h seconds from t_0 (``guidance.trajectory.timed_trajectory``,
h the control period), and the horizon asks for it at t + tau dt, tau = 0 .. N, dt the model step:
when dt is a whole number m of h, those times are the table's rows i + m tau moved by one common
fraction w of a row (w = 0 when the tick falls on the plan's grid, as it does between replans),

    x_r(t + tau dt) = (1 - w) row_{i + m tau} + w row_{i + m tau + 1},   i + w = (t - t_0) / h,

two strided slices of the table instead of a linear interpolation per series and per tick. The
table's rows are the reference states in the model's state order, computed once per plan
(``VFLPC._reference_rows``); after its last row it holds N m + 1 rows of the plan standing at its
end (position and heading kept, the velocity columns zero), so a horizon point within a row of the
end is read between the two. A trajectory that is not sampled so
(times not uniform, or dt not a multiple of their step) is read by ``np.interp`` per column, the
same rows and the same standing end (a plan of a single point too). ``loop``: ``strided_rows``
compiled (``vflpcd.controllers.loops``), the same numbers in one call.
"""

from __future__ import annotations

import math

import numpy as np

GRID_TOLERANCE = 1e-9   # relative: how uniform the plan's times must be, and how whole dt / h


class HorizonReference:
    """``rows`` (M, n_x): the reference states at the plan's times ``t`` (M,); ``stopped`` (n_x,) bool:
    the columns that are zero once the plan has ended (velocities); ``dt`` the horizon step, N its
    steps (module docstring)."""

    def __init__(self, t: np.ndarray, rows: np.ndarray, stopped: np.ndarray, dt: float, N: int, loop=None) -> None:
        t = np.asarray(t, float)
        rows = np.asarray(rows, float)
        if t.ndim != 1 or len(t) < 1 or rows.shape[0] != len(t):
            raise ValueError(f"the reference needs one row per time, got {rows.shape} rows for {t.shape} times")
        self.N, self.dt = int(N), float(dt)
        self._t = t
        self._offsets = self.dt * np.arange(self.N + 1)
        end = rows[-1].copy()
        end[np.asarray(stopped, bool)] = 0.0
        self._stride = self._grid_stride(t, self.dt)
        pad = self.N * (self._stride or 1) + 1
        self._rows = np.vstack([rows, np.broadcast_to(end, (pad, rows.shape[1]))])
        self._last = len(t) - 1
        self._out = np.empty((self.N + 1, rows.shape[1]))
        self._gap = np.empty_like(self._out)
        self._loop = loop

    @staticmethod
    def _grid_stride(t: np.ndarray, dt: float) -> int | None:
        """m when t is uniform with a step h and dt = m h; else (a single time too) None."""
        if len(t) < 2:
            return None
        h = (t[-1] - t[0]) / (len(t) - 1)
        m = round(dt / h) if h > 0.0 else 0
        if m < 1 or abs(dt - m * h) > GRID_TOLERANCE * dt:
            return None
        if np.max(np.abs(np.diff(t) - h)) > GRID_TOLERANCE * h:
            return None
        return m

    def at(self, t: float) -> np.ndarray:
        """The reference states (N + 1, n_x) at t + tau dt (a buffer rewritten by the next call)."""
        m = self._stride
        if m is None:
            return self._interpolated(t)
        t0 = self._t[0]
        h = self.dt / m
        x = (t - t0) / h
        if x <= 0.0:                          # before the plan: its first row
            i, w = 0, 0.0
        elif x > self._last:                  # past its end: the plan stands
            i, w = self._last + 1, 0.0
        else:
            i = math.floor(x)
            w = x - i
        if self._loop is not None:            # the same numbers, compiled
            self._loop(self._rows, i, m, w, self._out)
            return self._out
        stop = i + m * self.N + 1
        a = self._rows[i:stop:m]
        if w == 0.0:
            self._out[:] = a
            return self._out
        np.subtract(self._rows[i + 1:stop + 1:m], a, out=self._gap)
        np.multiply(self._gap, w, out=self._out)
        self._out += a
        return self._out

    def _interpolated(self, t: float) -> np.ndarray:
        times = t + self._offsets
        rows = self._rows
        standing = rows[self._last + 1]
        for j in range(rows.shape[1]):
            self._out[:, j] = np.interp(times, self._t, rows[: self._last + 1, j], right=standing[j])
        return self._out


def strided_rows(rows, i, m, w, out):
    """``HorizonReference.at`` on the grid as a loop to compile: out[tau] = rows[i + m tau] + w
    (rows[i + m tau + 1] - rows[i + m tau]) in numpy's order of operations ((b - a) w + a), rows[i +
    m tau] itself where w = 0."""
    for k in range(out.shape[0]):
        r = i + m * k
        for c in range(out.shape[1]):
            a = rows[r, c]
            out[k, c] = a if w == 0.0 else (rows[r + 1, c] - a) * w + a
