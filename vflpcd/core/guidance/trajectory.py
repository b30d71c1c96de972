"""The timed reference that guidance hands to the learning predictive controller."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vflpcd.core.guidance.speed import (CURVATURE_WINDOW, arrival_times, menger_curvature, path_heading,
                                       windowed_curvature)


SERIES = ("psi", "kappa", "s", "v", "omega", "accel", "pos")   # what ``Trajectory.sample`` interpolates
STOPPED = ("v", "omega", "accel")                               # 0 after the end: the reference stands


@dataclass(frozen=True)
class Trajectory:
    """Reference sampled at a fixed period.

    t (M,) s; pos (M, d) m; psi (M,) heading of the path tangent in the horizontal plane (rad,
    unwrapped); v (M,) speed m/s; omega (M,) = v kappa yaw rate rad/s; accel (M,) dv/dt m/s^2;
    kappa (M,) curvature 1/m (signed, left positive, in 2-D; unsigned in 3-D); s (M,) arc length m.
    """

    t: np.ndarray
    pos: np.ndarray
    psi: np.ndarray
    v: np.ndarray
    omega: np.ndarray
    accel: np.ndarray
    kappa: np.ndarray
    s: np.ndarray

    @property
    def duration(self) -> float:
        return float(self.t[-1] - self.t[0])

    def vehicle_states(self) -> np.ndarray:
        """[X_r, Y_r, psi_r, v_x^r, v_y^r = 0, omega_r] rows (M, 6): the paper's reference x_r."""
        return np.column_stack([self.pos[:, 0], self.pos[:, 1], self.psi, self.v, np.zeros_like(self.v), self.omega])

    def sample(self, t, names: tuple[str, ...] = SERIES) -> dict[str, np.ndarray]:
        """Linear interpolation of the series ``names`` (default all) at times t (scalar or (K,)),
        clamped to the ends; after the end the reference stands at its last point: speed, yaw rate
        and acceleration 0."""
        t = np.asarray(t, float)
        out = {}
        for name in names:
            if name == "pos":
                out["pos"] = np.stack([np.interp(t, self.t, self.pos[:, j]) for j in range(self.pos.shape[1])], axis=-1)
            elif name in STOPPED:
                out[name] = np.interp(t, self.t, getattr(self, name), right=0.0)
            else:
                out[name] = np.interp(t, self.t, getattr(self, name))
        return out


def timed_trajectory(xy: np.ndarray, s: np.ndarray, v: np.ndarray, t0: float, dt: float) -> Trajectory:
    """Sample a speed-planned path (points xy (K, d), arc lengths s (K,), speeds v (K,)) every dt
    seconds from t0 (points that are never reached, after a stop, are dropped)."""
    t_s = arrival_times(s, v)
    finite = np.isfinite(t_s)
    xy, s, v, t_s = xy[finite], s[finite], v[finite], t_s[finite]
    t = np.arange(0.0, t_s[-1] + 1e-9, dt)
    heading = path_heading(xy)
    kappa = windowed_curvature(heading, s, CURVATURE_WINDOW) if xy.shape[1] == 2 else menger_curvature(xy)
    vt, kt = np.interp(t, t_s, v), np.interp(t, t_s, kappa)
    pos = np.column_stack([np.interp(t, t_s, xy[:, j]) for j in range(xy.shape[1])])
    return Trajectory(t=t + t0, pos=pos, psi=np.interp(t, t_s, heading), v=vt, omega=vt * kt,
                      accel=np.gradient(vt, t) if len(t) > 1 else np.zeros_like(t), kappa=kt,
                      s=np.interp(t, t_s, s))
