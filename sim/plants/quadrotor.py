"""Simulated quadrotor: rigid-body dynamics under an inner attitude/thrust loop.

The plant's command is the desired world-frame acceleration of the vehicle,
u = [ax, ay, az] in m/s^2, *gravity not included* (u = 0 means hover). An inner
loop, modelled after the flight controller of a real vehicle, turns it into a
collective thrust and body torques that drive the rigid body.

Frames and state
----------------
World frame ENU (x east, y north, z up), e3 = [0, 0, 1]. Body frame FLU (x forward,
y left, z up along the thrust axis). The 13-value state is::

    [X, Y, Z,  vx, vy, vz,  qw, qx, qy, qz,  p, q, r]

position (m) and velocity (m/s) in the world frame, the unit quaternion q
(Hamilton, scalar first) rotating body vectors into the world frame, R = R(q), and
the body angular rates Omega = [p, q, r] (rad/s). Euler angles, where reported,
are Z-Y-X (yaw, pitch, roll): R = Rz(yaw) Ry(pitch) Rx(roll).

Rigid body (m mass, g gravity, c_d linear drag, J = diag(Jxx, Jyy, Jzz))
---------------------------------------------------------------------
::

    [X, Y, Z]_dot = v
    m v_dot   = T R e3 - m g e3 - c_d v
    q_dot     = 0.5 q (x) [0, Omega]
    J Omega_dot = tau - Omega x (J Omega)

with collective thrust T (N) and body torque tau (N m) the inner loop's outputs.

Inner loop (at every RK4 sub-step)
----------------------------------
``step(u, dt)`` splits dt into n = ceil(dt / max_step) equal sub-steps h. At the
start of each sub-step the inner loop is evaluated on the current state and its
outputs (T, tau) are held constant over that sub-step, i.e. the flight controller
runs at 1/h (500 Hz for max_step = 2 ms) with zero-order hold, and each sub-step
is one classical RK4 step; q is renormalised after it. The command u is held for
the whole of dt. The loop is:

1. Clip the command per axis: a = clip(u, -accel_max, accel_max).
2. Desired thrust vector with drag feed-forward: F = m (a + g e3) + c_d v.
3. Limits on F, in this order (altitude has priority over horizontal motion):
   * vertical: F_z >= T_min (the vehicle never asks for downward or zero thrust;
     with a_z <= -g it accelerates downwards at most with g - T_min / m);
   * tilt: if the angle between F and e3 exceeds tilt_max, the horizontal part
     of F is shortened (direction kept) to F_z tan(tilt_max), F_z kept;
   * magnitude: if |F| > T_max the horizontal part is shortened further, and
     if F_z alone exceeds T_max then F = T_max e3.
4. Collective thrust T = clip(F . R e3, T_min, T_max), with T_min =
   thrust_min_fraction m g and T_max = thrust_to_weight m g.
5. Desired attitude, the geometric construction of Lee, Leok & McClamroch (2010)
   from the thrust direction b3d = F / |F| and the desired yaw psi_d, in the form
   that fixes the intermediate *y* axis (as PX4 does):
   b2c = [-sin psi_d, cos psi_d, 0], b1d = (b2c x b3d) / |b2c x b3d|,
   b2d = b3d x b1d, R_d = [b1d b2d b3d]. Then the Z-Y-X yaw of R_d is exactly
   psi_d at any tilt, so ``heading()`` settles on psi_d even while accelerating;
   Lee's original b1c = [cos psi_d, sin psi_d, 0] form yields a yaw that differs
   from psi_d by a term of second order in the tilt (0.005 rad at 0.12 rad tilt
   sideways to the heading). psi_d is the yaw the plant was reset with unless
   ``set_yaw_setpoint`` changed it. (tilt_max < pi/2 keeps b3d away from the
   horizontal plane, so the construction is never singular.)
6. Geometric SO(3) attitude control with zero desired rates:
   e_R = 0.5 vee(R_d^T R - R^T R_d), e_Omega = Omega,
   tau = -k_R e_R - k_Omega e_Omega + Omega x J Omega, each component clipped
   to +-torque_max. (k_R, k_Omega are per-axis diagonal gains; for small errors
   each axis is J_i th'' + k_Omega_i th' + k_R_i th = 0.)

``applied_control`` is the *commanded* acceleration after all limiting,
a_applied = (F_lim - c_d v) / m - g e3, averaged over the sub-steps of the last
``step``. It equals the clipped command clip(u, +-accel_max) whenever none of the
limits of step 3 binds, and it is what the vehicle's
acceleration converges to once the attitude loop has settled. It is not the
realised acceleration, which lags it by the attitude dynamics (~0.2 s).

The model has no random elements; ``seed`` is accepted for the common plant
constructor signature and seeds ``self.rng`` only.
"""

from __future__ import annotations

import math

import numpy as np

from sim.plants.base import checked_vector
from sim.plants.integrators import rk4_step, substeps
from vflpcd.config.vehicles import QUAD_CONTROL_NAMES, QUAD_STATE_NAMES, QuadrotorParams
from vflpcd.core.angles import wrap_angle

def quat_to_rot(qv: np.ndarray) -> np.ndarray:
    """Rotation matrix (3, 3) of a unit quaternion [qw, qx, qy, qz] (4,), body -> world."""
    w, x, y, z = (float(c) for c in qv)
    return np.array([
        [1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y)],
        [2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x)],
        [2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y)],
    ])


def rot_to_euler(R: np.ndarray) -> tuple[float, float, float]:
    """Z-Y-X Euler angles (roll, pitch, yaw) in rad of a rotation matrix (3, 3)."""
    roll = math.atan2(R[2, 1], R[2, 2])
    pitch = -math.asin(min(1.0, max(-1.0, R[2, 0])))
    yaw = math.atan2(R[1, 0], R[0, 0])
    return roll, pitch, yaw


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """a x b for (3,) arrays (np.cross is slow on tiny arrays)."""
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


class Quadrotor:
    """Quadrotor plant commanded in world-frame acceleration (module docstring has the model)."""

    state_names = QUAD_STATE_NAMES
    control_names = QUAD_CONTROL_NAMES

    def __init__(self, params: QuadrotorParams, x0: np.ndarray | None = None, seed: int | None = None) -> None:
        """params: the vehicle; x0: initial state (13,), (6,) or (7,) as for ``reset``
        (default: at rest at the origin, level, yaw 0); seed: seeds ``self.rng`` (the model is deterministic)."""
        self.params = params
        self.rng = np.random.default_rng(seed)
        p = params
        self._m = float(p.mass)
        self._g = float(p.gravity)
        self._cd = float(p.drag_coefficient)
        self._J = np.asarray(p.inertia, dtype=float)
        self._Jx, self._Jy, self._Jz = (float(j) for j in p.inertia)
        self._kR = np.asarray(p.k_R, dtype=float)
        self._kW = np.asarray(p.k_Omega, dtype=float)
        self._tau_max = np.asarray(p.torque_max, dtype=float)
        self._tmin = p.thrust_min
        self._tmax = p.thrust_max
        self._tan_tilt = math.tan(p.tilt_max)
        self._x = np.zeros(13)
        self._applied = np.zeros(3)
        self._actuators = np.array([self._m * self._g, 0.0, 0.0, 0.0])
        self._yaw_sp = 0.0
        self.reset(np.zeros(6) if x0 is None else x0)

    # ------------------------------------------------------------------ state
    def reset(self, x0: np.ndarray) -> None:
        """Set the state. x0: (13,) full state (quaternion renormalised), or (6,)
        [X, Y, Z, vx, vy, vz] (level, yaw 0, zero rates), or (7,) [X, Y, Z, vx, vy, vz, yaw].
        The yaw setpoint becomes the yaw of x0. ValueError on another shape or non-finite values."""
        x0 = np.asarray(x0, dtype=float)
        if x0.shape not in ((13,), (6,), (7,)):
            raise ValueError(f"quadrotor x0 must have shape (13,), (6,) or (7,), got {x0.shape}")
        if not np.all(np.isfinite(x0)):
            raise ValueError("quadrotor x0 must be finite")
        x = np.zeros(13)
        x[0:6] = x0[0:6]
        if x0.shape == (13,):
            qn = np.linalg.norm(x0[6:10])
            if qn < 1e-9:
                raise ValueError("quadrotor x0 quaternion must be non-zero")
            x[6:10] = x0[6:10] / qn
            x[10:13] = x0[10:13]
        else:
            yaw = float(x0[6]) if x0.shape == (7,) else 0.0
            x[6] = math.cos(0.5 * yaw)
            x[9] = math.sin(0.5 * yaw)
        self._x = x
        self._yaw_sp = self.heading()
        self._applied = np.zeros(3)
        self._actuators = np.array([self._m * self._g, 0.0, 0.0, 0.0])

    @property
    def state(self) -> np.ndarray:
        """Copy of the full state, shape (13,) (``state_names``)."""
        return self._x.copy()

    @property
    def applied_control(self) -> np.ndarray:
        """Commanded acceleration after clipping and thrust/tilt limiting, world frame, shape (3,):
        (F_lim - c_d v) / m - g e3 averaged over the sub-steps of the last ``step`` (zeros before it)."""
        return self._applied.copy()

    @property
    def actuators(self) -> np.ndarray:
        """Inner-loop outputs of the last sub-step, shape (4,): [T (N), tau_x, tau_y, tau_z (N m)]."""
        return self._actuators.copy()

    def set_yaw_setpoint(self, psi: float) -> None:
        """Desired yaw psi (rad, scalar) for the inner loop, held until changed or ``reset``."""
        psi = float(psi)
        if not math.isfinite(psi):
            raise ValueError(f"yaw setpoint must be finite, got {psi!r}")
        self._yaw_sp = wrap_angle(psi)

    @property
    def yaw_setpoint(self) -> float:
        """Current desired yaw, rad, wrapped to (-pi, pi]."""
        return self._yaw_sp

    # ------------------------------------------------------------------ stepping
    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """Advance dt seconds with the command u = [ax, ay, az] (3,) held; returns the new state (13,).

        ValueError on a command of another shape or with non-finite values, or a bad dt.
        """
        u = checked_vector(u, 3, "quadrotor command [ax, ay, az]")
        n, h = substeps(dt, self.params.max_step)
        a_cmd = np.clip(u, -self.params.accel_max, self.params.accel_max)
        x = self._x
        applied_sum = np.zeros(3)
        for _ in range(n):
            w, applied = self._inner_loop(x, a_cmd)
            x = rk4_step(self._derivative, x, w, h)
            x[6:10] /= math.sqrt(float(x[6:10] @ x[6:10]))
            applied_sum += applied
        self._x = x
        self._applied = applied_sum / n
        self._actuators = w
        return x.copy()

    def _inner_loop(self, x: np.ndarray, a_cmd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Flight controller: state (13,) and clipped command (3,) -> ([T, tau] (4,), applied accel (3,))."""
        m, g, cd = self._m, self._g, self._cd
        v = x[3:6]
        omega = x[10:13]
        R = quat_to_rot(x[6:10])

        # Desired thrust vector with drag feed-forward, then vertical / tilt / magnitude limits.
        fx, fy, fz = (m * a_cmd + cd * v).tolist()
        fz = max(fz + m * g, self._tmin)
        fh = math.hypot(fx, fy)
        fh_max = fz * self._tan_tilt
        if fz > self._tmax:
            fz, fh_max = self._tmax, 0.0
        else:
            fh_max = min(fh_max, math.sqrt(self._tmax * self._tmax - fz * fz))
        if fh > fh_max:
            s = fh_max / fh
            fx, fy = fx * s, fy * s
        F = np.array([fx, fy, fz])
        applied = (F - cd * v) / m
        applied[2] -= g

        # Collective thrust along the current body z axis.
        thrust = min(max(float(F @ R[:, 2]), self._tmin), self._tmax)

        # Desired attitude from the thrust direction and the yaw setpoint (b2c form, see step 5).
        b3 = F / math.sqrt(float(F @ F))
        b2c = np.array([-math.sin(self._yaw_sp), math.cos(self._yaw_sp), 0.0])
        b1 = _cross(b2c, b3)
        b1 /= math.sqrt(float(b1 @ b1))
        b2 = _cross(b3, b1)
        Rd = np.column_stack((b1, b2, b3))

        # Geometric attitude control on SO(3), zero desired rates.
        E = Rd.T @ R
        E = E - E.T                                  # R_d^T R - R^T R_d
        e_R = 0.5 * np.array([E[2, 1], E[0, 2], E[1, 0]])
        tau = -self._kR * e_R - self._kW * omega + _cross(omega, self._J * omega)
        tau = np.clip(tau, -self._tau_max, self._tau_max)
        return np.array([thrust, tau[0], tau[1], tau[2]]), applied

    def _derivative(self, x: np.ndarray, w: np.ndarray) -> np.ndarray:
        """Rigid-body x_dot (13,) for state x (13,) and held actuators w = [T, tau_x, tau_y, tau_z] (4,)."""
        _, _, _, vx, vy, vz, qw, qx, qy, qz, p, q, r = x.tolist()
        thrust, tx, ty, tz = w.tolist()
        m, g, cd = self._m, self._g, self._cd
        jx, jy, jz = self._Jx, self._Jy, self._Jz
        # Body z axis in the world frame: third column of R(q).
        b3x = 2.0 * (qx * qz + qw * qy)
        b3y = 2.0 * (qy * qz - qw * qx)
        b3z = 1.0 - 2.0 * (qx * qx + qy * qy)
        a = thrust / m
        k = cd / m
        return np.array([
            vx, vy, vz,
            a * b3x - k * vx,
            a * b3y - k * vy,
            a * b3z - g - k * vz,
            # q_dot = 0.5 q (x) [0, Omega]
            0.5 * (-qx * p - qy * q - qz * r),
            0.5 * (qw * p + qy * r - qz * q),
            0.5 * (qw * q + qz * p - qx * r),
            0.5 * (qw * r + qx * q - qy * p),
            # J Omega_dot = tau - Omega x J Omega, J diagonal
            (tx - (jz - jy) * q * r) / jx,
            (ty - (jx - jz) * r * p) / jy,
            (tz - (jy - jx) * p * q) / jz,
        ])

    # ------------------------------------------------------------------ outputs
    def position(self) -> np.ndarray:
        """World position [X, Y, Z] in m, shape (3,)."""
        return self._x[0:3].copy()

    def velocity_world(self) -> np.ndarray:
        """World velocity [vx, vy, vz] in m/s, shape (3,)."""
        return self._x[3:6].copy()

    def rotation(self) -> np.ndarray:
        """Body -> world rotation matrix R(q), shape (3, 3)."""
        return quat_to_rot(self._x[6:10])

    def euler(self) -> tuple[float, float, float]:
        """Z-Y-X Euler angles (roll, pitch, yaw) in rad; yaw wrapped to (-pi, pi]."""
        roll, pitch, yaw = rot_to_euler(self.rotation())
        return roll, pitch, wrap_angle(yaw)

    def tilt(self) -> float:
        """Angle between the body z axis and world up, rad (scalar)."""
        R = self.rotation()
        return math.acos(min(1.0, max(-1.0, float(R[2, 2]))))

    def heading(self) -> float:
        """Yaw angle in rad, wrapped to (-pi, pi]."""
        return self.euler()[2]
