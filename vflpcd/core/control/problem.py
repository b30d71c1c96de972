"""The receding-horizon error problem that every horizon solver receives (Eb-RHRL, OSQP MPC).

Error model (paper eqs. discrete-time-nonlinear-system-dynmaics and identification_form_dynmaic),
linearised at the reference for the solvers that need it:

    x~_{tau+1} = A_tau x~_tau + B_tau u~_tau + c_tau,      tau = 0 .. N-1

x~ = Upsilon(x) - Upsilon(x_r) (n,) is the lifted error without the constant observable (it is
identically zero), u~ = u - u_r (n_u,) the control deviation from the reference control u_r,
A_tau = A_d,tau (n, n) and B_tau = B_d,tau (n, n_u) the (GP-corrected, eq. JocabianMatrices)
Jacobians, and c_tau (n,) what the reference itself does not satisfy under the model
(A Upsilon_r,tau + B u_r,tau + B_d m(z_r,tau) - Upsilon_r,tau+1).

Cost (paper eqs. cost_barrier and performance_index, without the barrier term h, which only
the Eb-RHRL solver carries):

    V = sum_{tau<N} gamma^tau (x~_tau' Q x~_tau + u~_tau' R u~_tau) + gamma^N x~_N' P x~_N

(V_tau = L_tau + gamma V_{tau+1}, V_N = F = x~_N' P x~_N).

Constraints on the applied control u = u_r + u~: u_min <= u <= u_max, and
|u_tau - u_{tau-1}| <= du_max (u_{-1} = u_prev). Obstacle half-planes G_tau x~_tau <= g_tau
(rows of zeros are inactive) are the linearised keep-out constraints of the constrained
solvers (the OSQP Koopman-MPC keeps them soft, with a penalised slack); the Eb-RHRL solver uses
the barrier instead. The rows of step 0 involve only x~_0 = x0, which no control can change.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(eq=False)
class HorizonProblem:
    """One tick's horizon problem; N steps, error dimension n, n_u controls, m half-planes.
    Read-only by convention (built once a tick, not frozen: a frozen dataclass's constructor costs
    twice as much, and arrays have no equality; ``dataclasses.replace`` makes a changed copy).

    A (N, n, n), B (N, n, n_u), c (N, n), x0 (n,), Q (n, n), R (n_u, n_u), P (n, n),
    gamma (scalar in (0, 1]), u_ref (N, n_u), u_min / u_max (n_u,), du_max (n_u,) per step
    (inf: no rate limit), u_prev (n_u,) the command applied at the previous tick,
    G (N + 1, m, n), g (N + 1, m) obstacle half-planes on x~_0 .. x~_N.
    """

    A: np.ndarray
    B: np.ndarray
    c: np.ndarray
    x0: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P: np.ndarray
    gamma: float
    u_ref: np.ndarray
    u_min: np.ndarray
    u_max: np.ndarray
    du_max: np.ndarray
    u_prev: np.ndarray
    G: np.ndarray
    g: np.ndarray

    @property
    def N(self) -> int:
        return int(self.A.shape[0])

    @property
    def n(self) -> int:
        return int(self.A.shape[1])

    @property
    def n_u(self) -> int:
        return int(self.B.shape[2])

    def rollout(self, u_tilde: np.ndarray) -> np.ndarray:
        """Linear prediction: u~ (N, n_u) -> x~ (N + 1, n), row 0 = x0."""
        x = np.empty((self.N + 1, self.n))
        x[0] = self.x0
        for k in range(self.N):
            x[k + 1] = self.A[k] @ x[k] + self.B[k] @ u_tilde[k] + self.c[k]
        return x

    def cost(self, u_tilde: np.ndarray) -> float:
        """V of the module docstring for u~ (N, n_u) on the linear prediction."""
        x = self.rollout(u_tilde)
        disc = self.gamma ** np.arange(self.N)
        stage = np.einsum("ki,ij,kj->k", x[:-1], self.Q, x[:-1]) + np.einsum("ki,ij,kj->k", u_tilde, self.R, u_tilde)
        return float(disc @ stage + self.gamma ** self.N * (x[-1] @ self.P @ x[-1]))


def finite_horizon_lqr(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                       N: int, gamma: float = 1.0) -> list[np.ndarray]:
    """Gains K_0 .. K_{N-1} (n_u, n) of the finite-horizon LQR u_tau = -K_tau x_tau for the
    cost of :class:`HorizonProblem` with time-invariant A (n, n), B (n, n_u), by the backward
    Riccati recursion S_N = P, K = (R + g B'SB)^-1 g B'SA, S = Q + g A'S(A - BK) (g = gamma)."""
    S = np.array(P, dtype=float)
    gains: list[np.ndarray] = []
    for _ in range(N):
        K = np.linalg.solve(R + gamma * B.T @ S @ B, gamma * B.T @ S @ A)
        S = Q + gamma * A.T @ S @ (A - B @ K)
        S = 0.5 * (S + S.T)
        gains.append(K)
    return gains[::-1]
