"""Eb-RHRL: receding-horizon actor-critic with the exponential barrier (paper section III-D).

Networks (eq. hat_u), one pair per prediction step tau = 0 .. N (step 0 is the current tick):

    u^_tau(x~)      = W_a,tau' Phi(x~) - K_tau x~                           (actor)
    lambda^_tau(x~) = W_c,tau' Phi(x~)                                       (critic)
    Phi(x~) = [k(x~, c_1) .. k(x~, c_nPhi)],  k(x, c) = exp(-1/2 ||(x - c) / ell||^2)

with c_j the RL dictionary (ALD over sampled error states, ``KernelFeatures.from_samples``).
The actor carries the finite-horizon LQR feedback -K_tau x~ of the nominal error model (the
Riccati recursion from the terminal P) as a fixed prior; its kernel part learns what the
prior does not know: the barrier, the GP correction and the reference's own model error c_tau.

One iteration i (Algorithm 1, function LPC):
1. apply u^_tau to the error model (eq. identification_form_dynmaic, linearised at the
   reference as ``HorizonProblem``): x~_{tau+1} = A_tau x~_tau + B_tau u^_tau + c_tau;
2. target costates (eq. approximated_optimal_valuefunction), from tau = N down to 0:
   lambda_N = 2 P x~_N + dh/dx~_N,
   lambda_tau = 2 Q x~_tau + gamma A_d,tau' lambda^_{tau+1}(x~_{tau+1}) + dh/dx~_tau
                - K_tau' (2 R u~_tau + gamma B_d,tau' lambda^_{tau+1}),
   each critic fitted to its target (eqs. epsilon_c and WaWc_update, normalised step
   eta_c = 1 / ||Phi||^2, which makes epsilon_c zero at the sample) before step tau - 1 reads it.
   The last term is the actor's stationarity residual (zero at the fixed point, where the target
   is the paper's) fed back through the prior gain: it makes lambda the costate of the closed
   loop the rollout runs, so that step 3 is a Newton step of the horizon cost;
3. target controls (eq. approximated_optimal_action) for all tau at once: the stationarity
   condition 2 R u~ + gamma B_d,tau' lambda^_{tau+1} = 0 that defines it, solved for its
   implicit dependence on u~ through x~_{tau+1} by one Newton step with the Riccati curvature:
   u~_tau <- u^_tau - M_tau^-1 (2 R u^_tau + gamma B_d,tau' lambda^_{tau+1}),  M_tau = 2 R + 2 gamma B' S_{tau+1} B;
   with S = 0 this is the paper's -1/2 gamma R^-1 B' lambda^ exactly;
4. actor update (eqs. epsilon_a and WaWc_update) with the normalised step eta_a / ||Phi||^2,
   halved for the rest of the solve whenever max epsilon_a grew (the Newton step ignores the
   barrier's curvature and can overshoot near an obstacle).
Iterate until max_tau epsilon_a <= tol or i_max. At a fixed point eq. optimal_action and eq.
optima_lambda hold along the predicted trajectory: with h = 0 and a linear model that is the
finite-horizon LQR solution.

Input bounds (optional, per solve: lo_tau <= u~_tau <= hi_tau): the rollout applies the actor's
output clipped into them, and step 3's targets are projected onto them (a projected Newton step).
The solver stays unconstrained otherwise; ``SolveInfo.saturated`` counts the steps whose target
the projection moved. VF-LPC bounds the increments of its light mode by the actuator's rate limit
(``vflpcd/core/vflpc.py``, ``VFLPC._solve_increments``).

Deviation, measured on the bicycle's Koopman model: the targets of step 2 are computed
backwards (each from the critic just updated at tau + 1, the order of finite-horizon DHP);
computing all of them from the previous iteration's critics at once diverged, and so did the
plain target of step 3 without the Newton step and the feedback prior (see the tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from vflpcd.core.control.barrier import HorizonBarrier
from vflpcd.core.control.problem import HorizonProblem
from vflpcd.core.dynamics.ald import sparsify


PHI_FLOOR = 1e-2  # floor of ||Phi||^2 in the normalised steps: far from the dictionary, no blow-up
BOUNDS_CROSSED = "input bounds with lo > hi"


class KernelFeatures:
    """Phi over a dictionary C (n_Phi, n) with per-dimension length scales ell (n,).

    k(x, c) = exp(a_j + b_j' x - 1/2 ||x / ell||^2), a_j = -1/2 ||c_j / ell||^2, b_j = c_j / ell^2."""

    def __init__(self, centers: np.ndarray, ell: np.ndarray) -> None:
        self.centers = np.array(centers, dtype=float)
        self.ell = np.array(ell, dtype=float)
        if self.centers.ndim != 2 or self.ell.shape != (self.centers.shape[1],) or np.any(self.ell <= 0):
            raise ValueError("centers must be (n_Phi, n) and ell (n,) positive")
        inv2 = 1.0 / self.ell ** 2
        self._b = self.centers * inv2                      # (n_Phi, n)
        self._a = -0.5 * np.sum(self.centers * self._b, axis=1)
        self._h = 0.5 * inv2

    @property
    def size(self) -> int:
        return int(self.centers.shape[0])

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Phi: x (..., n) -> (..., n_Phi)."""
        x = np.asarray(x, float)
        return np.exp(self._a + x @ self._b.T - (x * x) @ self._h)

    @classmethod
    def from_samples(cls, samples: np.ndarray, ell: np.ndarray, nu: float, size: int) -> "KernelFeatures":
        """ALD dictionary (threshold nu, at most ``size`` centres) over sampled error states
        samples (S, n), scaled by ell; the origin is always the first centre."""
        samples = np.asarray(samples, float)
        scaled = np.vstack([np.zeros((1, samples.shape[1])), samples / ell])
        keep = sparsify(scaled, None, nu, size)
        return cls(scaled[keep] * ell, ell)


@dataclass
class SolveInfo:
    """iterations run, whether the tolerance was met, the final max epsilon_a and epsilon_c, and
    the steps whose target control the input bounds moved (0 without bounds)."""

    iterations: int
    converged: bool
    eps_a: float
    eps_c: float
    saturated: int = 0


class EbRHRL:
    """The actor-critic solver of one horizon (module docstring).

    A (n, n), B (n, n_u): the nominal error model the prior and the Newton curvature come from;
    Q (n, n), R (n_u, n_u), P (n, n) terminal, gamma; features: Phi; N: horizon steps;
    eta_a in (0, 1]: actor step; i_max, tol: iteration cap and tolerance on max epsilon_a;
    loop: ``ebrhrl_kernel.solve_loop`` compiled (``vflpcd.controllers.loops``) to run the
    iterations with, or None for the numpy path (the same numbers to 1e-12); ``compiled`` says which.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, P: np.ndarray,
                 gamma: float, features: KernelFeatures, N: int, eta_a: float = 1.0, i_max: int = 10,
                 tol: float = 1e-8, loop=None) -> None:
        if not (0.0 < gamma <= 1.0) or not (0.0 < eta_a <= 1.0) or N < 1 or i_max < 1:
            raise ValueError("need 0 < gamma <= 1, 0 < eta_a <= 1, N >= 1, i_max >= 1")
        self.A, self.B = np.array(A, float), np.array(B, float)
        self.Q, self.R, self.P = np.array(Q, float), np.array(R, float), np.array(P, float)
        self.gamma, self.features, self.N = float(gamma), features, int(N)
        self.eta_a, self.i_max, self.tol = float(eta_a), int(i_max), float(tol)
        n, n_u = self.B.shape
        self.n, self.n_u = n, n_u
        # finite-horizon Riccati of the nominal model: S_tau (N + 1, n, n), K_tau (N, n_u, n)
        S = np.empty((N + 1, n, n))
        K = np.empty((N, n_u, n))
        S[N] = self.P
        for k in range(N - 1, -1, -1):
            K[k] = np.linalg.solve(self.R + gamma * self.B.T @ S[k + 1] @ self.B, gamma * self.B.T @ S[k + 1] @ self.A)
            S[k] = self.Q + gamma * self.A.T @ S[k + 1] @ (self.A - self.B @ K[k])
            S[k] = 0.5 * (S[k] + S[k].T)
        self.S, self.K = S, K
        M = 2.0 * self.R[None] + 2.0 * gamma * np.einsum("ji,tjk,kl->til", self.B, S[1:], self.B)
        self.M_inv = np.linalg.inv(M)                                   # (N, n_u, n_u)
        self.loop = loop
        self._closed = None
        T = self.N + 1                   # the compiled loop's arguments when no barrier is on
        self._no_barrier = (np.zeros(1, np.int64), np.zeros((T, 1)), np.zeros((0, T, 1)), np.zeros((0, T, 1)),
                            np.zeros(0), 1.0)
        self._R2 = 2.0 * self.R
        self._open = (np.full((N, n_u), -np.inf), np.full((N, n_u), np.inf))     # the loop's bounds when none
        self.reset()

    @property
    def compiled(self) -> bool:
        """Whether the iterations run as a compiled loop."""
        return self.loop is not None

    def reset(self) -> None:
        """Forget the learned weights (the actor becomes the LQR prior, the critic zero)."""
        m = self.features.size
        self.W_a = np.zeros((self.N, m, self.n_u))
        self.W_c = np.zeros((self.N + 1, m, self.n))

    def shift(self) -> None:
        """Receding horizon: step tau + 1's weights become step tau's (the last is kept)."""
        self.W_a[:-1] = self.W_a[1:]           # numpy copies overlapping operands as if apart
        self.W_c[:-1] = self.W_c[1:]

    def rollout(self, problem: HorizonProblem, closed: np.ndarray | None = None, bounds=None
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Apply the actor to the error model: x~ (N + 1, n), u~ (N, n_u), Phi (N + 1, n_Phi).
        ``closed``: A_tau - B_tau K_tau (N, n, n) if already at hand; ``bounds``: (lo, hi) (N, n_u)
        the actor's output is clipped into."""
        if bounds is not None:
            return self._bounded_rollout(problem, self.closed_loop(problem) if closed is None else closed, bounds)
        N, f = self.N, self.features
        A_cl = self.closed_loop(problem) if closed is None else closed
        BW = np.einsum("tiu,tmu->tim", problem.B, self.W_a)        # B_tau W_a,tau' (N, n, n_Phi)
        x = np.empty((N + 1, self.n))
        phi = np.empty((N + 1, f.size))
        x[0] = problem.x0
        c = problem.c
        a, b, h = f._a, f._b, f._h
        for k in range(N):  # the only sequential part: x~_{tau+1} = (A - B K) x~ + B W_a' Phi(x~) + c
            xk = x[k]
            pk = np.exp(a + b @ xk - h @ (xk * xk))
            phi[k] = pk
            x[k + 1] = A_cl[k] @ xk + BW[k] @ pk + c[k]
        phi[N] = f(x[N])
        u = np.einsum("tm,tmu->tu", phi[:-1], self.W_a) - np.einsum("tun,tn->tu", self.K, x[:-1])
        return x, u, phi

    def _bounded_rollout(self, problem: HorizonProblem, A_cl: np.ndarray, bounds
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``rollout`` with the actor's output u~_tau clipped into bounds (lo, hi) (N, n_u):
        x~_{tau+1} = (A - B K) x~ + B (u~_tau + K x~) + c."""
        N, f = self.N, self.features
        lo, hi = bounds
        x = np.empty((N + 1, self.n))
        phi = np.empty((N + 1, f.size))
        u = np.empty((N, self.n_u))
        x[0] = problem.x0
        for k in range(N):
            xk = x[k]
            phi[k] = pk = f(xk)
            Kx = self.K[k] @ xk
            u[k] = np.minimum(np.maximum(pk @ self.W_a[k] - Kx, lo[k]), hi[k])
            x[k + 1] = A_cl[k] @ xk + problem.B[k] @ (u[k] + Kx) + problem.c[k]
        phi[N] = f(x[N])
        return x, u, phi

    def closed_loop(self, problem: HorizonProblem) -> np.ndarray:
        """A_tau - B_tau K_tau (N, n, n): the error model under the prior (``closed_loop_of``)."""
        return self.closed_loop_of(problem.A, problem.B)

    def closed_loop_of(self, A: np.ndarray, B: np.ndarray) -> np.ndarray:
        """A_tau - B_tau K_tau (N, n, n) of A (N, n, n), B (N, n, n_u) (kept while they are the same
        arrays as at the last call)."""
        last = self._closed
        if last is not None and last[0] is A and last[1] is B:
            return last[2]
        A_cl = np.ascontiguousarray(A - B @ self.K)
        self._closed = (A, B, A_cl)
        return A_cl

    def costates(self, problem: HorizonProblem, x: np.ndarray, u: np.ndarray,
                 barrier: HorizonBarrier | None, closed: np.ndarray | None = None) -> np.ndarray:
        """Target costates lambda_tau (N + 1, n) of step 2 along the rollout x~ (N + 1, n), u~ (N, n_u):
        lambda_tau = 2 Q x~ + dh/dx~ - 2 K' R u~ + gamma (A - B K)' lambda_{tau+1}."""
        grad_h = barrier.gradient(x) if barrier is not None else np.zeros_like(x)
        A_cl = self.closed_loop(problem) if closed is None else closed
        lam = np.empty_like(x)
        lam[-1] = 2.0 * self.P @ x[-1] + grad_h[-1]
        stage = 2.0 * x[:-1] @ self.Q.T + grad_h[:-1] - np.einsum("tun,tu->tn", self.K, 2.0 * u @ self.R.T)
        gA_cl = self.gamma * A_cl
        for k in range(self.N - 1, -1, -1):
            lam[k] = stage[k] + lam[k + 1] @ gA_cl[k]
        return lam

    def solve(self, problem: HorizonProblem, barrier: HorizonBarrier | None = None,
              bounds: tuple[np.ndarray, np.ndarray] | None = None) -> tuple[np.ndarray, SolveInfo]:
        """Iterate from the current weights; returns u~ (N, n_u) (the last targets) and the info.
        ``bounds``: (lo, hi) (N, n_u) on u~ (module docstring), None for none."""
        if problem.B.shape != (self.N, self.n, self.n_u):
            raise ValueError(f"problem of shape N={problem.N}, n={problem.n}, n_u={problem.n_u} "
                             f"does not match the solver's {self.N}, {self.n}, {self.n_u}")
        if bounds is not None:
            bounds = (self._bound(bounds[0]), self._bound(bounds[1]))
        if self.loop is not None:
            return self._solve_compiled(problem, barrier, bounds)      # the loop checks lo <= hi
        if bounds is not None and np.greater(bounds[0], bounds[1]).any():
            raise ValueError(BOUNDS_CROSSED)
        R2, gamma = 2.0 * self.R, self.gamma
        BT = problem.B.transpose(0, 2, 1)                                # (N, n_u, n)
        info = SolveInfo(0, False, np.inf, np.inf)
        eta = self.eta_a
        closed = self.closed_loop(problem)
        saturated = 0
        for i in range(1, self.i_max + 1):
            x, u, phi = self.rollout(problem, closed, bounds)
            lam = self.costates(problem, x, u, barrier, closed)
            lam_hat = np.einsum("tm,tmn->tn", phi, self.W_c)
            inv_norm = 1.0 / np.maximum(np.einsum("tm,tm->t", phi, phi), PHI_FLOOR)
            self.W_c += np.einsum("tm,tn->tmn", phi * inv_norm[:, None], lam - lam_hat)       # eta_c = 1/||Phi||^2
            grad = u @ R2.T + gamma * np.einsum("tun,tn->tu", BT, lam[1:])
            target = u - np.einsum("tuv,tv->tu", self.M_inv, grad)                            # step 3
            if bounds is not None:                                                            # projected
                newton = target
                target = np.minimum(np.maximum(newton, bounds[0]), bounds[1])
                saturated = int(np.count_nonzero(np.any(target != newton, axis=1)))
            err = target - u
            eps_a = 0.5 * float(np.max(np.einsum("tu,tu->t", err, err)))
            if eps_a > info.eps_a:          # the last step overshot (barrier curvature): halve the next
                eta *= 0.5
            self.W_a += eta * np.einsum("tm,tu->tmu", phi[:-1] * inv_norm[:-1, None], err)
            eps_c = 0.5 * float(np.max(np.einsum("tn,tn->t", lam - lam_hat, lam - lam_hat)))
            info = SolveInfo(i, eps_a <= self.tol, eps_a, eps_c, saturated)
            if info.converged or not np.isfinite(eps_a):
                break
        return target, info

    def _bound(self, b) -> np.ndarray:
        """A bound as the (N, n_u) C-ordered, writable float array the compiled loop takes (one
        signature); an array that is one already is used as it is."""
        if (isinstance(b, np.ndarray) and b.shape == (self.N, self.n_u) and b.dtype == np.float64
                and b.flags.c_contiguous and b.flags.writeable):
            return b
        return np.array(np.broadcast_to(np.asarray(b, float), (self.N, self.n_u)))

    def _solve_compiled(self, problem: HorizonProblem, barrier: HorizonBarrier | None,
                        bounds: tuple[np.ndarray, np.ndarray] | None) -> tuple[np.ndarray, SolveInfo]:
        """``solve`` by the compiled ``ebrhrl_kernel.solve_loop`` (the same iterations)."""
        c = np.ascontiguousarray
        lo, hi = bounds if bounds is not None else self._open
        target, iterations, eps_a, eps_c, saturated = self.loop(
            self.closed_loop(problem), c(problem.B), c(problem.c), c(problem.x0), *self.loop_arguments(barrier),
            bounds is not None, lo, hi)
        return target, self.loop_info(iterations, eps_a, eps_c, saturated)

    def loop_arguments(self, barrier: HorizonBarrier | None) -> tuple:
        """``ebrhrl_kernel.solve_loop``'s arguments from K to phi_floor: the prior, the weights (updated
        in place), the features, ``barrier``'s arrays (none when it has no threat) and the settings."""
        f = self.features
        if barrier is not None and barrier.count:
            c = np.ascontiguousarray
            shield = (c(barrier.pos_index, np.int64), c(barrier.p_ref, float), c(barrier.x_p, float),
                      c(barrier.normal, float), c(barrier.mu, float), float(barrier.length))
        else:
            shield = self._no_barrier
        return (self.K, self.Q, self._R2, self.P, self.M_inv, self.gamma, self.W_a, self.W_c, f._a, f._b, f._h,
                *shield, self.eta_a, self.i_max, self.tol, PHI_FLOOR)

    def loop_info(self, iterations: int, eps_a: float, eps_c: float, saturated: int) -> SolveInfo:
        """The ``SolveInfo`` of what ``solve_loop`` returned; raises ValueError when its bounds crossed
        (iterations -1)."""
        if iterations < 0:
            raise ValueError(BOUNDS_CROSSED)
        return SolveInfo(int(iterations), bool(eps_a <= self.tol), float(eps_a), float(eps_c), int(saturated))
