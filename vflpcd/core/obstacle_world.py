"""Where each scenario obstacle is at time t, including the ones that wait for the robot.

Triggers (per obstacle):
- ``always``: present from t = 0, moving with its constant velocity (zero for a static one);
- ``move``: present from t = 0, at rest until the robot first comes within
  ``trigger_distance`` of its centre, then moving with its velocity (the paper's 25 m
  moving-obstacle experiment);
- ``appear``: absent (not perceived, not collidable) until the robot first comes within
  ``trigger_distance``, then present and moving with its velocity (suddenly appearing).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np

from vflpcd.core.obstacles import ObstacleState


class ObstacleWorld:
    """Ground truth for the scenario obstacles; ``update`` must be called once per step."""

    def __init__(self, specs: Sequence) -> None:
        self.specs = tuple(specs)
        self.reset()

    def reset(self) -> None:
        self.t_trigger: list[float | None] = [0.0 if s.trigger == "always" else None for s in self.specs]

    def update(self, t: float, robot_position: np.ndarray) -> None:
        """Fire the triggers of obstacles the robot has come close to (robot_position: (d,))."""
        for i, spec in enumerate(self.specs):
            if self.t_trigger[i] is None and np.linalg.norm(spec.center - robot_position) <= spec.trigger_distance:
                self.t_trigger[i] = t

    def present(self, i: int) -> bool:
        return self.specs[i].trigger != "appear" or self.t_trigger[i] is not None

    def center(self, i: int, t: float) -> np.ndarray:
        """Centre of obstacle i at time t, shape (d,)."""
        spec, t0 = self.specs[i], self.t_trigger[i]
        if t0 is None:
            return spec.center.copy()
        return spec.center + spec.velocity * (t - t0)

    def velocity(self, i: int) -> np.ndarray:
        return self.specs[i].velocity if self.t_trigger[i] is not None else np.zeros_like(self.specs[i].velocity)

    def snapshot(self, t: float) -> list[ObstacleState]:
        """The obstacles present at t, as a controller perceives them."""
        return [ObstacleState(id=s.id, shape=s.shape, center=self.center(i, t), yaw=s.yaw,
                              velocity=self.velocity(i).copy(), stamp=t)
                for i, s in enumerate(self.specs) if self.present(i)]
