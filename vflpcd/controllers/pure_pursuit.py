"""Pure pursuit steering with a PID speed loop, for the dynamic bicycle.

Steering (Coulter 1992): the rear axle chases the path point a lookahead distance L_d ahead,
    delta_f = atan(2 L sin(alpha) / l_d),
with wheelbase L, alpha the bearing of the target point from the heading and l_d its
distance. L_d = clip(L_min + t_la * v_x, L_min, L_max).
Speed: v_ref = min(v_d, min over the preview of sqrt(a_lat_max / |kappa|)); a PID on
v_ref - v_x gives a_x, with the integral clamped and frozen while a_x saturates.
It does not see obstacles: it is the "no planning" baseline.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from vflpcd.config.vehicles import BicycleConfig
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.ports import ControllerBase
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table


@dataclass(frozen=True)
class PurePursuitGains:
    la_time: float
    la_min: float
    la_max: float
    preview: float
    kp: float
    ki: float
    kd: float
    integral_limit: float

    @classmethod
    def load(cls, path: str | Path | None = None) -> "PurePursuitGains":
        path = Path(path) if path is not None else config_dir() / "controllers" / "pure_pursuit.toml"
        root = load_table(path)
        root.check_known({"lookahead", "speed", "pid"})
        la, spd, pid = root.table("lookahead"), root.table("speed"), root.table("pid")
        la.check_known({"time", "min", "max"})
        spd.check_known({"preview"})
        pid.check_known({"kp", "ki", "kd", "integral_limit"})
        return cls(la_time=la.number("time", min=0.0), la_min=la.number("min", positive=True),
                   la_max=la.number("max", positive=True), preview=spd.number("preview", min=0.0),
                   kp=pid.number("kp", min=0.0), ki=pid.number("ki", min=0.0), kd=pid.number("kd", min=0.0),
                   integral_limit=pid.number("integral_limit", min=0.0))


class PurePursuit(ControllerBase):
    """Controller protocol: state [X, Y, psi, vx, vy, omega] -> command [a_x, delta_f]."""

    name = "pure_pursuit"

    def __init__(self, path: ReferencePath, v_desired: float, a_lat_max: float,
                 vehicle: BicycleConfig, gains: PurePursuitGains) -> None:
        self.path, self.v_desired, self.a_lat_max = path, v_desired, a_lat_max
        self.vehicle, self.gains = vehicle, gains
        self.reset()

    def reset(self) -> None:
        self._s: float | None = None
        self._integral = 0.0
        self._prev_err: float | None = None
        self._prev_t: float | None = None

    def speed_target(self, s: float) -> float:
        """min(v_d, sqrt(a_lat_max / |kappa|)) over [s, s + preview]."""
        ahead = s + np.linspace(0.0, self.gains.preview, 26)
        kappa = np.max(np.abs(self.path.curvature_at(ahead)))
        return float(min(self.v_desired, np.sqrt(self.a_lat_max / max(kappa, 1e-9))))

    def step(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> np.ndarray:
        X, Y, psi, vx = state[0], state[1], state[2], state[3]
        p, lim, g = self.vehicle.params, self.vehicle.limits, self.gains
        heading = np.array([np.cos(psi), np.sin(psi)])
        rear = np.array([X, Y]) - p.lr * heading
        proj = self.path.project(rear, self._s)
        self._s = proj.s
        ld = float(np.clip(g.la_min + g.la_time * vx, g.la_min, g.la_max))
        target = self.path.point_at(proj.s + ld)
        to_target = target - rear
        alpha = np.arctan2(to_target[1], to_target[0]) - psi
        l_d = max(float(np.linalg.norm(to_target)), 1e-3)
        delta = float(np.clip(np.arctan2(2.0 * p.wheelbase * np.sin(alpha), l_d), -lim.delta_max, lim.delta_max))

        err = self.speed_target(proj.s) - vx
        dt = 0.0 if self._prev_t is None else max(t - self._prev_t, 0.0)
        derr = 0.0 if (self._prev_err is None or dt == 0.0) else (err - self._prev_err) / dt
        a_unsat = g.kp * err + g.ki * self._integral + g.kd * derr
        a_x = float(np.clip(a_unsat, lim.a_min, lim.a_max))
        if a_x == a_unsat or np.sign(err) != np.sign(a_unsat):  # conditional integration (anti-windup)
            self._integral = float(np.clip(self._integral + err * dt, -g.integral_limit, g.integral_limit))
        self._prev_err, self._prev_t = err, t
        return np.array([a_x, delta])


def make_pure_pursuit(scenario, **_) -> PurePursuit:
    """Pure pursuit for ``scenario``'s car and route with the shipped gains."""
    from vflpcd.config.vehicles import BicycleConfig

    return PurePursuit(scenario.path, scenario.v_desired, scenario.a_lat_max, BicycleConfig.load(scenario.params),
                       PurePursuitGains.load())
