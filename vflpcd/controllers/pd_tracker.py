"""PD acceleration tracker for the quadrotor: a = kp * e_perp + kd * (v_ref - v).

e_perp is the vector from the robot to the nearest path point (cross-track error) and
v_ref = v_s t_hat the path tangent scaled by the speed target
v_s = min(v_d, sqrt(a_lat_max / kappa), sqrt(2 a_brake * distance left)) (the last on open
paths only, to stop at the end). The command is clipped to |a| <= accel_max. It does not see
obstacles: it is the "no planning" baseline.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.ports import ControllerBase
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table


@dataclass(frozen=True)
class PDGains:
    kp: float
    kd: float
    accel_max: float
    brake: float

    @classmethod
    def load(cls, path: str | Path | None = None) -> "PDGains":
        path = Path(path) if path is not None else config_dir() / "controllers" / "pd_tracker.toml"
        root = load_table(path)
        root.check_known({"kp", "kd", "accel_max", "brake"})
        return cls(**{k: root.number(k, positive=True) for k in ("kp", "kd", "accel_max", "brake")})


class PDTracker(ControllerBase):
    """Controller protocol: state [X, Y, Z, vx, vy, vz, ...] -> command [ax, ay, az] (world, gravity excluded)."""

    name = "pd_tracker"

    def __init__(self, path: ReferencePath, v_desired: float, a_lat_max: float, gains: PDGains) -> None:
        self.path, self.v_desired, self.a_lat_max, self.gains = path, v_desired, a_lat_max, gains
        self.reset()

    def reset(self) -> None:
        self._s: float | None = None

    def step(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> np.ndarray:
        p, v = np.asarray(state[:3], float), np.asarray(state[3:6], float)
        proj = self.path.project(p, self._s)
        self._s = proj.s
        g = self.gains
        kappa = abs(float(self.path.curvature_at(proj.s)))
        v_s = min(self.v_desired, np.sqrt(self.a_lat_max / max(kappa, 1e-9)))
        if not self.path.closed:
            v_s = min(v_s, np.sqrt(2.0 * g.brake * max(self.path.length - proj.s, 0.0)))
        a = g.kp * (proj.point - p) + g.kd * (v_s * proj.tangent - v)
        norm = float(np.linalg.norm(a))
        if norm > g.accel_max:
            a *= g.accel_max / norm
        return a


def make_pd_tracker(scenario, **_) -> PDTracker:
    """The PD tracker for ``scenario``'s route with the shipped gains."""
    return PDTracker(scenario.path, scenario.v_desired, scenario.a_lat_max, PDGains.load())
