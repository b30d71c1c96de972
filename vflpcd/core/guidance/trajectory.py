"""The timed reference that guidance hands to the learning predictive controller."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Trajectory:
    """Reference sampled at a fixed period.

    t (M,) s; pos (M, d) m; psi (M,) heading of the path tangent (rad, unwrapped);
    v (M,) speed m/s; omega (M,) = v kappa yaw rate rad/s; accel (M,) dv/dt m/s^2;
    kappa (M,) signed curvature 1/m (2-D); s (M,) arc length m.
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

    def sample(self, t) -> dict[str, np.ndarray]:
        """Linear interpolation of every series at times t (scalar or (K,)), clamped to the ends."""
        t = np.asarray(t, float)
        out = {name: np.interp(t, self.t, getattr(self, name)) for name in ("psi", "v", "omega", "accel", "kappa", "s")}
        out["pos"] = np.stack([np.interp(t, self.t, self.pos[:, j]) for j in range(self.pos.shape[1])], axis=-1)
        return out
