"""Vehicle parameters and limits, one set of types for the plants, the drivers and the controllers.

``BicycleConfig.load(param_set)`` reads ``config/plants/dynamic_bicycle.toml`` (the car: inertia and
tyres, actuator limits, low-speed blending, body size); ``QuadrotorParams.from_toml()`` reads
``config/plants/quadrotor.toml``. Errors name the file and the field (``ConfigError``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table

STATE_NAMES = ("X", "Y", "psi", "vx", "vy", "omega")      # the car: CoG position, yaw, body velocities, yaw rate
CONTROL_NAMES = ("a_x", "delta_f")


@dataclass(frozen=True)
class BicycleParams:
    """Inertial and tyre parameters (TABLE Vehicle Dynamic Parameters)."""

    m: float
    Iz: float
    lf: float
    lr: float
    Caf: float
    Car: float

    @property
    def wheelbase(self) -> float:
        return self.lf + self.lr


@dataclass(frozen=True)
class BicycleLimits:
    a_min: float
    a_max: float
    delta_max: float
    delta_rate_max: float


@dataclass(frozen=True)
class BodySize:
    """Outer dimensions; the CoG lies ``rear_overhang + lr`` behind the front bumper."""

    length: float
    width: float
    rear_overhang: float


@dataclass(frozen=True)
class BicycleConfig:
    """Everything the plant needs, read from ``config/plants/dynamic_bicycle.toml``."""

    name: str
    params: BicycleParams
    limits: BicycleLimits
    body: BodySize
    v_kinematic: float
    v_dynamic: float
    tau_kinematic: float
    max_step: float
    process_noise_std: float

    @classmethod
    def load(cls, param_set: str = "nominal", path: str | Path | None = None) -> "BicycleConfig":
        """Read parameter set ``param_set`` (e.g. "nominal", "exact") and the shared limits."""
        path = Path(path) if path is not None else config_dir() / "plants" / "dynamic_bicycle.toml"
        root = load_table(path)
        root.check_known({"params", "limits", "low_speed", "integration", "body"})
        sets = root.table("params")
        if not sets.has(param_set):
            raise sets.error(param_set, f"no such parameter set (have: {', '.join(sorted(sets.data))})")
        p = sets.table(param_set)
        p.check_known({"m", "Iz", "lf", "lr", "Caf", "Car"})
        params = BicycleParams(**{k: p.number(k, positive=True) for k in ("m", "Iz", "lf", "lr", "Caf", "Car")})
        lim = root.table("limits")
        lim.check_known({"a_min", "a_max", "delta_max", "delta_rate_max"})
        limits = BicycleLimits(
            a_min=lim.number("a_min", max=0.0), a_max=lim.number("a_max", positive=True),
            delta_max=lim.number("delta_max", positive=True, max=1.2),
            delta_rate_max=lim.number("delta_rate_max", positive=True))
        low = root.table("low_speed")
        low.check_known({"v_kinematic", "v_dynamic", "tau_kinematic"})
        v_kin = low.number("v_kinematic", positive=True)
        v_dyn = low.number("v_dynamic", positive=True)
        if v_dyn <= v_kin:
            raise low.error("v_dynamic", f"expected a speed above v_kinematic ({v_kin:g}), got {v_dyn:g}")
        integ = root.table("integration")
        integ.check_known({"max_step", "process_noise_std"})
        body = root.table("body")
        body.check_known({"length", "width", "rear_overhang"})
        return cls(
            name=param_set, params=params, limits=limits,
            body=BodySize(**{k: body.number(k, positive=True) for k in ("length", "width", "rear_overhang")}),
            v_kinematic=v_kin, v_dynamic=v_dyn, tau_kinematic=low.number("tau_kinematic", positive=True),
            max_step=integ.number("max_step", positive=True, max=0.05),
            process_noise_std=integ.number("process_noise_std", min=0.0))


QUAD_STATE_NAMES = ("X", "Y", "Z", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "p", "q", "r")
QUAD_CONTROL_NAMES = ("ax", "ay", "az")

Vec3 = tuple[float, float, float]

_TABLE = "quadrotor"
_FIELDS = {
    "mass", "gravity", "inertia", "drag_coefficient", "thrust_to_weight",
    "thrust_min_fraction", "tilt_max", "accel_max", "torque_max", "k_R", "k_Omega",
    "max_step",
}


@dataclass(frozen=True)
class QuadrotorParams:
    """Physical parameters, limits and inner-loop gains (SI units, see the TOML file)."""

    mass: float                   # kg
    gravity: float                # m/s^2
    inertia: Vec3                 # kg m^2, [Jxx, Jyy, Jzz]
    drag_coefficient: float       # N s/m
    thrust_to_weight: float       # max thrust / (m g)
    thrust_min_fraction: float    # min thrust / (m g)
    tilt_max: float               # rad
    accel_max: float              # m/s^2, per axis
    torque_max: Vec3              # N m, per axis
    k_R: Vec3                     # N m / rad, per axis
    k_Omega: Vec3                 # N m s / rad, per axis
    max_step: float               # s, inner RK4 step

    @property
    def thrust_max(self) -> float:
        """Maximum collective thrust, N."""
        return self.thrust_to_weight * self.mass * self.gravity

    @property
    def thrust_min(self) -> float:
        """Minimum collective thrust, N."""
        return self.thrust_min_fraction * self.mass * self.gravity

    @classmethod
    def from_toml(cls, path: str | Path | None = None) -> "QuadrotorParams":
        """Read the ``[quadrotor]`` table of ``path`` (default ``config_dir()/plants/quadrotor.toml``).

        Raises ConfigError naming the file and the field on a missing, unknown or bad value.
        """
        path = Path(path) if path is not None else config_dir() / "plants" / "quadrotor.toml"
        root = load_table(path)
        root.check_known({_TABLE})
        t = root.table(_TABLE)
        t.check_known(_FIELDS)

        def vec3(key: str) -> Vec3:
            v = t.vector(key, 3)
            if np.any(v <= 0.0):
                raise t.error(key, f"expected 3 positive numbers, got {v.tolist()}")
            return (float(v[0]), float(v[1]), float(v[2]))

        ttw = t.number("thrust_to_weight", positive=True)
        if ttw <= 1.0:
            raise t.error("thrust_to_weight", f"expected a number > 1 (the vehicle must be able to hover), got {ttw:g}")
        tmin = t.number("thrust_min_fraction", positive=True)
        if tmin >= 1.0:
            raise t.error("thrust_min_fraction", f"expected a number in (0, 1), got {tmin:g}")
        tilt = t.number("tilt_max", positive=True)
        if tilt >= 0.5 * math.pi:
            raise t.error("tilt_max", f"expected an angle in (0, pi/2) rad, got {tilt:g}")
        return cls(
            mass=t.number("mass", positive=True),
            gravity=t.number("gravity", positive=True),
            inertia=vec3("inertia"),
            drag_coefficient=t.number("drag_coefficient", min=0.0),
            thrust_to_weight=ttw,
            thrust_min_fraction=tmin,
            tilt_max=tilt,
            accel_max=t.number("accel_max", positive=True),
            torque_max=vec3("torque_max"),
            k_R=vec3("k_R"),
            k_Omega=vec3("k_Omega"),
            max_step=t.number("max_step", positive=True),
        )


def state_names(platform: str) -> tuple[str, ...]:
    """The state vector's names of a ground (car) or aerial (quadrotor) platform."""
    return STATE_NAMES if platform == "ground" else QUAD_STATE_NAMES
