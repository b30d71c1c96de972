"""Dynamic bicycle of the paper (eq. vehicle_dynamics), with a safe low-speed treatment.

State x = [X, Y, psi, v_x, v_y, omega] (world position of the CoG, yaw, body-frame
longitudinal and lateral velocity, yaw rate); control u = [a_x, delta_f].

    X_dot     = v_x cos psi - v_y sin psi
    Y_dot     = v_x sin psi + v_y cos psi
    psi_dot   = omega
    v_x_dot   = v_y omega + a_x
    v_y_dot   = 2 C_af (delta_f / m - (v_y + l_f omega) / (m v_x)) + 2 C_ar (l_r omega - v_y) / (m v_x) - v_x omega
    omega_dot = 2 / I_z [ l_f C_af (delta_f - (v_y + l_f omega) / v_x) - l_r C_ar (l_r omega - v_y) / v_x ]

Low speed. The tyre-slip terms divide by v_x: the model is singular at v_x -> 0 and its
lateral/yaw modes get stiff (eigenvalues ~ 2(C_af + C_ar) / (m v_x)), so at standstill a
steered wheel would push the car sideways and RK4 would blow up. Below ``v_dynamic`` the
lateral states are therefore blended with a kinematic bicycle (as blended racing-car models
do): weight lam = smoothstep((v_x - v_kin) / (v_dyn - v_kin)) on the dynamic model, whose
1/v_x terms use max(v_x, v_kin), and 1 - lam on first-order relaxation of v_y, omega towards
the kinematic values omega_kin = v_x tan(delta_f) / (l_f + l_r), v_y_kin = l_r omega_kin
with time constant ``tau_kinematic``. Above ``v_dynamic`` the model is exactly the paper's.
The vehicle does not reverse: braking stops it at v_x = 0.

Actuators. a_x is clipped to [a_min, a_max]; the commanded delta_f is clipped to
±delta_max and the applied angle follows it at no more than delta_rate_max (a first-order
rate limiter, the steering motor), held constant over the step (zero-order hold).
Optional i.i.d. Gaussian process noise w_k (std ``process_noise_std``) is added to the
state after every step, as in the paper's model-uncertainty experiment.
"""

from __future__ import annotations


import numpy as np

from sim.plants.base import checked_vector
from sim.plants.integrators import rk4_step, substeps
from vflpcd.config.vehicles import CONTROL_NAMES, STATE_NAMES, BicycleConfig, BicycleParams
from vflpcd.core.angles import wrap_angle

def bicycle_derivative(x: np.ndarray, u: np.ndarray, p: BicycleParams,
                       v_kin: float, v_dyn: float, tau_kin: float) -> np.ndarray:
    """Time derivative of the blended dynamic bicycle. x: (6,), u: (2,) applied [a_x, delta_f]."""
    _, _, psi, vx, vy, om = x
    a_x, delta = u
    c, s = np.cos(psi), np.sin(psi)
    vxd = max(vx, v_kin)  # the 1/v_x terms never divide by less than v_kin
    # paper eq. (vehicle_dynamics), lateral and yaw rows
    vy_dot_dyn = (2.0 * p.Caf * (delta / p.m - (vy + p.lf * om) / (p.m * vxd))
                  + 2.0 * p.Car * (p.lr * om - vy) / (p.m * vxd) - vx * om)
    om_dot_dyn = (2.0 / p.Iz) * (p.lf * p.Caf * (delta - (vy + p.lf * om) / vxd)
                                 - p.lr * p.Car * (p.lr * om - vy) / vxd)
    r = min(max((vx - v_kin) / (v_dyn - v_kin), 0.0), 1.0)
    lam = r * r * (3.0 - 2.0 * r)  # smoothstep weight on the dynamic model
    if lam < 1.0:
        om_kin = vx * np.tan(delta) / (p.lf + p.lr)
        vy_dot = lam * vy_dot_dyn + (1.0 - lam) * (p.lr * om_kin - vy) / tau_kin
        om_dot = lam * om_dot_dyn + (1.0 - lam) * (om_kin - om) / tau_kin
    else:
        vy_dot, om_dot = vy_dot_dyn, om_dot_dyn
    vx_dot = vy * om + a_x
    if vx <= 0.0 and vx_dot < 0.0:  # brakes hold a stopped car; it never reverses
        vx_dot = 0.0
    return np.array([vx * c - vy * s, vx * s + vy * c, om, vx_dot, vy_dot, om_dot])


class DynamicBicycle:
    """The dynamic bicycle plant (see the module docstring for model and limits)."""

    state_names = STATE_NAMES
    control_names = CONTROL_NAMES

    def __init__(self, config: BicycleConfig, x0=None, *, process_noise: bool = False,
                 seed: int | None = None) -> None:
        self.config = config
        self.process_noise = process_noise
        self._rng = np.random.default_rng(seed)
        self._x = np.zeros(6)
        self._u = np.zeros(2)
        self.reset(np.zeros(6) if x0 is None else x0)

    # ------------------------------------------------------------------ state
    @property
    def state(self) -> np.ndarray:
        """Copy of x = [X, Y, psi, vx, vy, omega], shape (6,)."""
        return self._x.copy()

    @property
    def applied_control(self) -> np.ndarray:
        """[a_x, delta_f] actually applied over the last step (after limits), shape (2,)."""
        return self._u.copy()

    def reset(self, x0) -> None:
        """x0: (6,) full state, or (4,) [X, Y, psi, vx] with vy = omega = 0. Steering starts at 0."""
        x0 = np.asarray(x0, dtype=float).ravel()
        if x0.shape == (4,):
            x0 = np.concatenate([x0, [0.0, 0.0]])
        if x0.shape != (6,) or not np.all(np.isfinite(x0)):
            raise ValueError(f"bicycle initial state must be 4 or 6 finite numbers, got {x0!r}")
        if x0[3] < 0.0:
            raise ValueError(f"bicycle initial speed vx must be >= 0, got {x0[3]}")
        self._x = x0.copy()
        self._x[2] = wrap_angle(self._x[2])
        self._u = np.zeros(2)

    def position(self) -> np.ndarray:
        return self._x[:2].copy()

    def velocity_world(self) -> np.ndarray:
        _, _, psi, vx, vy, _ = self._x
        c, s = np.cos(psi), np.sin(psi)
        return np.array([vx * c - vy * s, vx * s + vy * c])

    def heading(self) -> float:
        return float(self._x[2])

    # ------------------------------------------------------------------ stepping
    def saturate(self, u_cmd: np.ndarray, dt: float) -> np.ndarray:
        """The command the actuators realise over the next dt: limits and steering rate. (2,)."""
        lim = self.config.limits
        a_x = min(max(float(u_cmd[0]), lim.a_min), lim.a_max)
        delta_cmd = min(max(float(u_cmd[1]), -lim.delta_max), lim.delta_max)
        max_change = lim.delta_rate_max * dt
        delta = self._u[1] + min(max(delta_cmd - self._u[1], -max_change), max_change)
        return np.array([a_x, delta])

    def step(self, u_cmd, dt: float) -> np.ndarray:
        """Apply u_cmd = [a_x, delta_f] (2,) for dt seconds; returns the new state (6,)."""
        u_cmd = checked_vector(u_cmd, 2, "bicycle command [a_x, delta_f]")
        self._u = self.saturate(u_cmd, dt)
        cfg = self.config
        n, h = substeps(dt, cfg.max_step)

        def f(x, u):
            return bicycle_derivative(x, u, cfg.params, cfg.v_kinematic, cfg.v_dynamic, cfg.tau_kinematic)

        x = self._x
        for _ in range(n):
            x = rk4_step(f, x, self._u, h)
            x[3] = max(x[3], 0.0)
        if self.process_noise and cfg.process_noise_std > 0.0:
            x = x + self._rng.normal(0.0, cfg.process_noise_std, size=6)
            x[3] = max(x[3], 0.0)
        x[2] = wrap_angle(x[2])
        self._x = x
        return self._x.copy()
