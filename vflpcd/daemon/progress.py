"""Progress along the mission's reference path, to know when the mission is complete."""

from __future__ import annotations

import numpy as np

from vflpcd.core.path import ReferencePath, progress_delta


class Progress:
    """Arc length covered along ``path`` by the positions given to ``update`` (the platform state's
    entries ``position_index``); complete once it reaches ``goal`` metres."""

    def __init__(self, path: ReferencePath, goal: float, position_index: list[int]) -> None:
        self.path, self.goal, self.index = path, float(goal), list(position_index)
        self._s: float | None = None
        self.covered = 0.0
        self.lateral = float("nan")     # distance to the path at the last update (m)

    def update(self, state: np.ndarray) -> bool:
        """Advance with a new state (n_x,); True once the goal is reached."""
        proj = self.path.project(np.asarray(state)[self.index], self._s)
        s, self.lateral = proj.s, abs(float(proj.lateral))
        if self._s is not None:
            self.covered += progress_delta(self.path, s, self._s)
        self._s = s
        return self.covered >= self.goal
