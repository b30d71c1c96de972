"""The exponential barrier of the cost (paper eq. barrierfunction and eq. cost_barrier).

    h(x) = mu_o exp(-pi(x, x_p) / l_b)

x_p is the point of the threatening obstacle's safety boundary (its physical boundary grown by
the safety distance: robot body radius + safety margin, i.e. the terminal set of the game in
``game_region``) nearest to the robot, found per prediction step tau at the obstacle's predicted
pose, and n_p the boundary's outward unit normal there. The distance error is

    pi(x, x_p) = n_p' (p(x) - x_p),

p(x) the position part of the state. Outside the safety boundary (where the controller keeps the
robot) pi = ||p - x_p||, the paper's ||pi(x, x_p)||; inside, pi < 0 and the barrier keeps growing,
so its gradient pushes outwards there too (the plain norm would pull the robot towards the
obstacle once past x_p); below pi / l_b = PI_MIN it continues as its tangent line, so a
prediction deep inside gets a bounded push. Per tick x_p and n_p are fixed, so h is an exponential of an affine
function of the state and its gradient is exact: dh/dp = -(h / l_b) n_p. l_b (default 1 m) is
a length scale the paper leaves at 1. Several threatening obstacles add their barriers.

The same planes give the linearised keep-out half-planes n_p' (p - x_p) >= 0 of the solvers
with hard constraints (``halfplanes``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vflpcd.core.obstacles import ObstacleState

PI_MIN = -2.0  # below this pi / l_b the exponential continues as its tangent line (bounded gradient)


def safety_points(obstacle: ObstacleState, points: np.ndarray, times: np.ndarray, grow: float
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Nearest points of the obstacle's boundary grown by ``grow`` (m) and their outward normals.

    points (T, d) robot positions, times (T,) at which the obstacle is taken (constant-velocity
    prediction). Returns x_p (T, d) and n_p (T, d) (unit)."""
    points = np.atleast_2d(np.asarray(points, float))
    times = np.asarray(times, float).reshape(-1)
    shift = obstacle.velocity[None, :] * (times - obstacle.stamp)[:, None]
    q = points - shift                        # the obstacle at rest at its stamped pose
    sd, n = obstacle.distance_and_normal(q)
    x_p = points - (sd - grow)[:, None] * n
    return x_p, n


@dataclass(frozen=True)
class HorizonBarrier:
    """The barrier over one horizon of N + 1 predicted error states x~ (N + 1, n).

    pos_index (d,): where the position error sits in x~; p_ref (N + 1, d): the reference
    positions (so p = p_ref + x~[:, pos_index]); x_p, normal (K, N + 1, d): the K threatening
    obstacles' safety points and normals per step; mu (K,) >= 0; length: l_b (m)."""

    pos_index: np.ndarray
    p_ref: np.ndarray
    x_p: np.ndarray
    normal: np.ndarray
    mu: np.ndarray
    length: float = 1.0

    def __post_init__(self) -> None:
        empty = self.x_p.size == 0 and self.normal.size == 0 and self.mu.size == 0     # no obstacle: nothing to check
        if not (self.length > 0.0 and (empty or (np.isfinite(self.x_p).all() and np.isfinite(self.normal).all()
                                                 and np.isfinite(self.mu).all() and (self.mu >= 0.0).all()))):
            raise ValueError("barrier points, normals and mu must be finite, mu >= 0 and length > 0")

    @property
    def count(self) -> int:
        return int(self.mu.shape[0])

    def _scaled_pi(self, x_tilde: np.ndarray) -> np.ndarray:
        """pi / l_b, (K, N + 1)."""
        p = self.p_ref + x_tilde[:, self.pos_index]
        return np.einsum("ktd,ktd->kt", self.normal, p[None] - self.x_p) / self.length

    def value(self, x_tilde: np.ndarray) -> np.ndarray:
        """h at every step: x~ (N + 1, n) -> (N + 1,)."""
        if self.count == 0:
            return np.zeros(x_tilde.shape[0])
        pi = self._scaled_pi(x_tilde)
        deep = np.exp(-PI_MIN) * (1.0 - (pi - PI_MIN))
        return self.mu @ np.where(pi >= PI_MIN, np.exp(-np.maximum(pi, PI_MIN)), deep)

    def gradient(self, x_tilde: np.ndarray) -> np.ndarray:
        """dh/dx~ at every step: x~ (N + 1, n) -> (N + 1, n) (zero off the position entries)."""
        grad = np.zeros_like(x_tilde)
        if self.count == 0:
            return grad
        pi = np.maximum(self._scaled_pi(x_tilde), PI_MIN)
        h = self.mu[:, None] * np.exp(-pi)                          # (K, T); constant slope below PI_MIN
        grad[:, self.pos_index] = -np.einsum("kt,ktd->td", h, self.normal) / self.length
        return grad

    def halfplanes(self, n: int, m: int) -> tuple[np.ndarray, np.ndarray]:
        """Keep-out half-planes G_tau x~_tau <= g_tau of the K obstacles, padded with zero rows to m:
        -n_p' x~_pos <= n_p' (p_ref - x_p). Returns G (N + 1, m, n), g (N + 1, m)."""
        T = self.p_ref.shape[0]
        G, g = np.zeros((T, m, n)), np.zeros((T, m))
        for k in range(min(self.count, m)):
            G[:, k][:, self.pos_index] = -self.normal[k]
            g[:, k] = np.einsum("td,td->t", self.normal[k], self.p_ref - self.x_p[k])
        return G, g
