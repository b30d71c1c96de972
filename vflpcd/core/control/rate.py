"""Rate-aware (increment) form of the horizon problem, for the unconstrained Eb-RHRL solver.

The plant slews its inputs at a bounded rate (the car's steering at 0.6 rad/s, 0.03 rad per
50 ms step), and a solver that does not know it asks for steps the actuator cannot make: the
clip in front of the plant then delays the command and the loop oscillates (measured on
``carsim_avoidance``: the lateral error grows past 5 m after the parked car). Eb-RHRL has no
constraints, so the rate enters its model and cost instead. The state carries the previous
control deviation and the decision is the increment:

    z_tau = [x~_tau; u~_{tau-1}],   v_tau = u~_tau - u~_{tau-1},
    z_{tau+1} = [[A_tau, B_tau], [0, I]] z_tau + [[B_tau], [I]] v_tau + [c_tau; 0],
    stage cost z' blkdiag(Q, R) z + v' R_rate v,   terminal z' P_z z (DARE of the nominal pair),

with u~_{-1} = u_prev - u_r,0. The control cost acts on u~_{tau-1} (one step late), and the
half-planes and the barrier act on the x~ part unchanged. The applied deviation is
u~_0 = u~_{-1} + v_0.

An input in ``command`` has the command's own increment as its v instead, v_tau = u_tau - u_{tau-1}:
then u~_tau = u~_{tau-1} + v_tau - (u_r,tau - u_r,tau-1), the reference control's steps enter the
affine terms,

    z_{tau+1} = ... + [c_tau - B_tau s_tau; -s_tau],   s_tau = u_r,tau - u_r,tau-1 (s_0 = 0),

and R_rate weighs the command's rate of change wherever it comes from. Without it, a step of u_r
inside the horizon costs nothing, but at the next tick u~_{-1} = u_prev - u_r,0 carries the same
step into v_0, which R_rate then slows: the plan of one tick (follow the step) is not the next
tick's, and the command lags a planned step instead of easing into it ahead of it (a stop planned
at 2.5 m/s^2 from 6 m/s: the throttle began to brake as the reference did, at up to 3.2 m/s^2,
and the car stopped 0.29 m past the goal; in the command's increments it brakes 0.65 s earlier,
at up to 2.6 m/s^2, and stops 0.16 m short of it).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg as sl

from vflpcd.core.control.problem import HorizonProblem


@dataclass(frozen=True)
class RateForm:
    """The nominal increment-form matrices of an error model with A (n, n), B (n, n_u), Q, R,
    discount gamma and increment weight R_rate (n_u, n_u): A, B, Q, R (= R_rate), P (DARE) and the
    terminal LQR gain K_terminal (n_u, n + n_u); ``commanded``: the indices of the inputs whose
    increment is the command's own (module docstring; ``of`` takes them as ``command``, one flag
    per input)."""

    n: int
    n_u: int
    A: np.ndarray
    B: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    P: np.ndarray
    K_terminal: np.ndarray
    gamma: float
    commanded: tuple[int, ...]
    _pair: list = field(default_factory=lambda: [None, None, None], compare=False, repr=False)
    loop: object = field(default=None, compare=False, repr=False)     # rate_kernel.increment_loop compiled, or None
    _blank: dict = field(default_factory=dict, compare=False, repr=False)     # N -> _Blank
    _work: dict = field(default_factory=dict, compare=False, repr=False)      # N -> _Work

    @classmethod
    def of(cls, A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: np.ndarray, R_rate: np.ndarray,
           gamma: float, command: np.ndarray | None = None, loop=None) -> "RateForm":
        n, n_u = B.shape
        command = np.zeros(n_u, bool) if command is None else np.asarray(command, bool)
        if command.shape != (n_u,):
            raise ValueError(f"command must be {n_u} flags, one per input, got {command!r}")
        R_rate = np.asarray(R_rate, float)
        if R_rate.shape != (n_u, n_u) or np.any(np.linalg.eigvalsh(0.5 * (R_rate + R_rate.T)) <= 0):
            raise ValueError(f"R_rate must be a positive definite {n_u}x{n_u} matrix, got {R_rate!r}")
        Az, Bz = augment_pair(A, B)
        Qz = sl.block_diag(Q, R)
        g = np.sqrt(gamma)
        P = sl.solve_discrete_are(g * Az, g * Bz, Qz, R_rate)
        K = np.linalg.solve(R_rate + gamma * Bz.T @ P @ Bz, gamma * Bz.T @ P @ Az)
        return cls(n, n_u, Az, Bz, Qz, R_rate, P, K, float(gamma), tuple(int(j) for j in np.flatnonzero(command)),
                   loop=loop)

    def problem(self, p: HorizonProblem) -> HorizonProblem:
        """The increment form of problem p (module docstring); its u_ref is the previous deviation
        carried along (zeros: v has no reference) and its input bounds are open (``increments``)."""
        return self.increments(p)[0]

    def increments(self, p: HorizonProblem) -> tuple[HorizonProblem, tuple[np.ndarray, np.ndarray]]:
        """``problem(p)`` and the bounds (lo, hi) (N, n_u) on its increments v_tau that keep the
        command u = u_r + u~ within p's rate limit du_max at every step: u moves by
        v_tau + (u_r,tau - u_r,tau-1) (u~_{-1} = u_prev - u_r,0, so step 0 moves it by v_0), by v_tau
        alone for an input whose v is the command's own increment; open for an input without a limit.
        Its c, x0 and the bounds are the form's own arrays, rewritten by its next call (one
        compiled fill, ``rate_kernel.increment_loop``, with ``loop``; numpy without), and the problem
        is the same object while p's A, B and half-planes are the same arrays (the nominal
        linearisation's): nothing is allocated at a tick."""
        N, n = p.N, self.n
        work = self.work(N)
        if self.loop is not None:
            self.loop(p.c, p.B, p.u_ref, p.x0, p.u_prev, p.du_max, work.commanded, work.c, work.x0, work.lo, work.hi)
        else:
            _increment_fill(p, self.commanded, work)
        A, B = self.augmented(p.A, p.B)
        blank = self._blank.get(N) or self._blank.setdefault(N, _blank(N, n, self.n_u))
        G = blank.G if p.G.shape == (N + 1, 0, n) else np.concatenate([p.G, np.zeros(p.G.shape[:2] + (self.n_u,))], axis=2)
        z = work.problem
        if z is None or z.A is not A or z.B is not B or z.G is not G or z.g is not p.g or z.gamma != p.gamma:
            z = work.problem = HorizonProblem(A=A, B=B, c=work.c, x0=work.x0, Q=self.Q, R=self.R, P=self.P,
                                              gamma=p.gamma, u_ref=blank.u_ref, u_min=blank.lower,
                                              u_max=blank.upper, du_max=blank.upper, u_prev=blank.u_prev, G=G, g=p.g)
        return z, (work.lo, work.hi)

    def work(self, N: int) -> "_Work":
        """The arrays an N-step increment problem is written into at every tick (``_Work``)."""
        return self._work.get(N) or self._work.setdefault(N, _Work.of(N, self.n, self.n_u, self.commanded))

    def augmented(self, A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """augment_pair(A, B), kept while the problem's A and B are the same arrays (the nominal
        linearisation hands out the same ones every tick)."""
        if self._pair[0] is A and self._pair[1] is B:
            return self._pair[2]
        out = augment_pair(A, B)
        self._pair[:] = [A, B, out]
        return out

    def deviation(self, z0: np.ndarray, v0: np.ndarray) -> np.ndarray:
        """The first control deviation u~_0 = u~_{-1} + v_0 from the increment-form start z0."""
        return z0[self.n:] + v0


@dataclass(frozen=True)
class _Blank:
    """The arrays of an increment problem that are the same at every tick (read-only): no reference,
    open bounds, no half-plane."""

    u_ref: np.ndarray
    u_prev: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    G: np.ndarray


@dataclass
class _Work:
    """An increment problem's arrays rewritten at every tick (``RateForm.increments``): c (N, n + n_u),
    x0 (n + n_u,), the bounds lo, hi (N, n_u), the commanded inputs' indices, and the problem
    built on them (kept while its input's A, B and half-planes are the same arrays)."""

    c: np.ndarray
    x0: np.ndarray
    lo: np.ndarray
    hi: np.ndarray
    commanded: np.ndarray
    problem: HorizonProblem | None = None

    @classmethod
    def of(cls, N: int, n: int, n_u: int, commanded: tuple[int, ...]) -> "_Work":
        return cls(np.zeros((N, n + n_u)), np.zeros(n + n_u), np.zeros((N, n_u)), np.zeros((N, n_u)),
                   np.array(commanded, dtype=np.int64))


def _increment_fill(p: HorizonProblem, commanded: tuple[int, ...], work: _Work) -> None:
    """``rate_kernel.increment_loop`` in numpy (the same numbers)."""
    n = p.n
    c = work.c
    c[:, :n] = p.c
    c[:, n:] = 0.0
    ref_step = np.zeros_like(work.lo)
    np.subtract(p.u_ref[1:], p.u_ref[:-1], out=ref_step[1:])
    for j in commanded:             # the reference control's steps s_tau (module docstring)
        u_r = p.u_ref[:, j]
        step = np.subtract(u_r[:-1], u_r[1:], out=c[1:, n + j])           # -s_tau, tau >= 1
        c[1:, :n] += p.B[1:, :, j] * step[:, None]
        ref_step[:, j] = 0.0
    work.x0[:n] = p.x0
    np.subtract(p.u_prev, p.u_ref[0], out=work.x0[n:])
    np.subtract(-p.du_max, ref_step, out=work.lo)
    np.subtract(p.du_max, ref_step, out=work.hi)


def _blank(N: int, n: int, n_u: int) -> _Blank:
    arrays = (np.zeros((N, n_u)), np.zeros(n_u), np.full(n_u, -np.inf), np.full(n_u, np.inf), np.zeros((N + 1, 0, n + n_u)))
    for a in arrays:
        a.flags.writeable = False
    return _Blank(*arrays)


def augment_pair(A: np.ndarray, B: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """[[A, B], [0, I]] and [[B], [I]] for one pair (n, n), (n, n_u) or stacked (N, n, n), (N, n, n_u)."""
    n, n_u = B.shape[-2:]
    lead = A.shape[:-2]
    Az = np.zeros(lead + (n + n_u, n + n_u))
    Az[..., :n, :n], Az[..., :n, n:] = A, B
    Az[..., n:, n:] = np.eye(n_u)
    Bz = np.zeros(lead + (n + n_u, n_u))
    Bz[..., :n, :], Bz[..., n:, :] = B, np.eye(n_u)
    return Az, Bz
