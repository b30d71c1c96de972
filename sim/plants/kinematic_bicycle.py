"""Kinematic bicycle for planning comparisons: state [X, Y, psi], control [v, delta_f].

Reference point at the rear axle:
    X_dot = v cos psi,  Y_dot = v sin psi,  psi_dot = v tan(delta_f) / L
with wheelbase L. The turning radius at steering angle delta is L / tan(delta).
"""

from __future__ import annotations

import numpy as np

from sim.plants.base import checked_vector
from sim.plants.integrators import rk4_step, substeps
from vflpcd.core.angles import wrap_angle

STATE_NAMES = ("X", "Y", "psi")
CONTROL_NAMES = ("v", "delta_f")


def kinematic_derivative(x: np.ndarray, u: np.ndarray, wheelbase: float) -> np.ndarray:
    """x: (3,) [X, Y, psi]; u: (2,) [v, delta_f]. Returns x_dot (3,)."""
    v, delta = u
    return np.array([v * np.cos(x[2]), v * np.sin(x[2]), v * np.tan(delta) / wheelbase])


class KinematicBicycle:
    """Kinematic bicycle with steering-angle and speed limits."""

    state_names = STATE_NAMES
    control_names = CONTROL_NAMES

    def __init__(self, wheelbase: float, delta_max: float, v_max: float, x0=None,
                 max_step: float = 0.01) -> None:
        if not (wheelbase > 0 and delta_max > 0 and v_max > 0 and max_step > 0):
            raise ValueError("wheelbase, delta_max, v_max and max_step must be positive")
        self.wheelbase, self.delta_max, self.v_max, self.max_step = wheelbase, delta_max, v_max, max_step
        self._x = np.zeros(3)
        self._u = np.zeros(2)
        self.reset(np.zeros(3) if x0 is None else x0)

    @property
    def state(self) -> np.ndarray:
        return self._x.copy()

    @property
    def applied_control(self) -> np.ndarray:
        return self._u.copy()

    def reset(self, x0) -> None:
        """x0: (3,) [X, Y, psi]."""
        self._x = checked_vector(x0, 3, "kinematic bicycle state [X, Y, psi]")
        self._u = np.zeros(2)

    def position(self) -> np.ndarray:
        return self._x[:2].copy()

    def velocity_world(self) -> np.ndarray:
        return self._u[0] * np.array([np.cos(self._x[2]), np.sin(self._x[2])])

    def heading(self) -> float:
        return float(wrap_angle(self._x[2]))

    def step(self, u_cmd, dt: float) -> np.ndarray:
        """Apply [v, delta_f] (2,), clipped to the limits, for dt seconds. Returns (3,)."""
        u_cmd = checked_vector(u_cmd, 2, "kinematic bicycle command [v, delta_f]")
        self._u = np.array([np.clip(u_cmd[0], -self.v_max, self.v_max),
                            np.clip(u_cmd[1], -self.delta_max, self.delta_max)])
        n, h = substeps(dt, self.max_step)
        x = self._x
        for _ in range(n):
            x = rk4_step(lambda x_, u_: kinematic_derivative(x_, u_, self.wheelbase), x, self._u, h)
        x[2] = wrap_angle(x[2])
        self._x = x
        return self._x.copy()
