"""Linear MPC on the Koopman error model, solved by OSQP: a horizon solver for VF-LPC.

This is a *horizon solver*, not a controller: every tick the VF-LPC controller builds a
:class:`vflpcd.core.control.problem.HorizonProblem` from the guidance reference and the lifted
(GP-corrected) Koopman error model, and either its Eb-RHRL solver or
:class:`OSQPHorizonSolver` solves it. Symbols are those of ``problem.py``.

The QP (sparse formulation: states and inputs are both variables)
-----------------------------------------------------------------
Variables, stacked into z (n_z = (N+1) n + N n_u + (N+1) m):

    z = [x~_0 .. x~_N  (N+1, n),  u~_0 .. u~_{N-1}  (N, n_u),  s_0 .. s_N  (N+1, m)]

with s_tau >= 0 one slack per obstacle half-plane row. Cost (OSQP form 1/2 z'Hz + q'z):

    V + sum_tau sum_j (w1 s_tau,j + w2 s_tau,j^2),
    V = sum_{tau<N} gamma^tau (x~_tau' Q x~_tau + u~_tau' R u~_tau) + gamma^N x~_N' P x~_N

(w1 = ``slack_l1``, w2 = ``slack_l2``; Q, R, P are symmetrised). Constraints, one row block
each, in this order:

    dynamics     x~_0 = x0;   x~_{tau+1} - A_tau x~_tau - B_tau u~_tau = c_tau       (N+1) n rows
    input bounds u_min - u_r,tau <= u~_tau <= u_max - u_r,tau                       N n_u rows
    rate limits  |u~_0 + u_r,0 - u_prev| <= du_max,
                 |u~_tau - u~_{tau-1} + u_r,tau - u_r,tau-1| <= du_max (tau >= 1)      N n_u rows
    half-planes  G_tau x~_tau - s_tau <= g_tau    (tau = 0 .. N)                    (N+1) m rows
    slacks       s_tau >= 0                                                          (N+1) m rows

Rows of G that are all zero, and rows with g = +inf, are inactive (upper bound +inf).
Input bounds and rate limits are hard. u_prev is first clipped into [u_min, u_max]: then the
input constraints are always jointly feasible (hold u = clip(u_prev) over the horizon),
even when the previous command lies outside the bounds. du_max = inf disables a rate limit.

Why soft half-planes
--------------------
The half-planes are linearisations of keep-out sets around a reference that may itself be
infeasible for them (x~_0 already inside an obstacle margin, a rate-limited vehicle that cannot
turn away in time, a stale linearisation). A hard constraint would then make the whole QP
primal infeasible and leave the controller without any command. With the exact L1 penalty
w1 s the slacks stay exactly zero whenever the hard problem is feasible and w1 exceeds the
largest half-plane multiplier of the hard problem, and otherwise the violation is minimised;
the small quadratic w2 s^2 keeps the QP strictly convex in s. w1 defaults to 1e3: on the
bicycle benchmark below (Q, R of order one, unit-norm G rows) the multipliers stay below
~3e2, and a larger w1 slows ADMM down markedly when slacks are active; scale it with Q, R.
Inactive rows get no L1 term (q = 0 there), so their slack sits at 0 with a zero multiplier.
Slack is in the units of G x~: normalise G's rows (unit norm) to read it as metres.

Build once, update, warm start
------------------------------
The constraint matrix and the Hessian are built once per problem shape (N, n, n_u, m) with a
FIXED sparsity pattern: every A_tau, B_tau and G_tau block and the upper triangles of the
Q, R, P blocks are stored as dense blocks with explicit zeros, so a later problem of the same
shape only calls ``OSQP.update`` (l and u every call; Ax when A, B or G change, e.g. with a GP
correction; Px when Q, R, P or gamma change - both trigger OSQP's refactorisation of the KKT
matrix; q, which only holds w1 on the active half-plane rows). A different shape rebuilds the
solver (``builds`` counts OSQP setups). Before each solve the previous solution is
warm-started shifted by one step: primal (x~, u~, s) and dual y
(each row block moved one step earlier, the last step repeated; x~_0 set to the new x0). A
failed solve, an invalid problem or :meth:`OSQPHorizonSolver.reset` drops the warm start and
the next solve starts cold from z = 0, y = 0.

Result
------
:meth:`OSQPHorizonSolver.solve` returns u~ (N, n_u), or None on any status other than
"solved" (primal/dual infeasible, max_iter, time limit, non-convex, solved-inaccurate) and on
non-finite problem data (NaN anywhere, +-inf where a finite value is needed, -inf in g,
u_min > u_max, du_max < 0, gamma <= 0: checked before OSQP is touched, so the solver stays
usable). Each None adds one to ``failures`` and leaves the reason in
``last_status``. Shape mismatches are programming errors and raise ValueError. The returned
sequence is projected, step by step, onto the hard input set (bounds and rate limits on the
absolute u = u_ref + u~), which changes it by no more than the solver tolerance but makes the
hard constraints hold to round-off; ``last_x`` (N+1, n) and ``last_slack`` (N+1, m) hold the
QP's predicted error states and slacks.

A non-convex cost (Q, R or P not positive semidefinite, checked whenever they change) also
returns None: OSQP's ``update`` would otherwise silently keep the previous Hessian.

Accuracy: when polishing succeeds (``last_polish`` == 1) the solution is the exact QP optimum
to round-off (< 1e-6). When it fails (on the bicycle benchmark: ~3 % of calls with x0 ~ 0.1,
~12 % with x0 ~ 0.03, mostly with slacks active or many rate limits touching) the ADMM iterate
at eps_abs = eps_rel = 1e-5 is returned: cost within ~0.5 % of the optimum, u~ off by up to
~4e-2 along weakly penalised directions (the acceleration there; steering < 4e-3).
``check_dualgap=True`` (OSQP 1.x's default) brings that to ~1e-3 at ~1.6x the iterations.
Unconstrained problems match the finite-horizon LQR to < 1e-4 relative.

:func:`benchmark` times warm-started solves on the shipped dynamic-bicycle Koopman model
(``python -m vflpcd.controllers.koopman_mpc``).
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np
import osqp
import scipy.sparse as sp

from vflpcd.core.control.barrier import HorizonBarrier
from vflpcd.core.control.problem import HorizonProblem

_INF = 1e30  # OSQP_INFTY


def _shift(v: np.ndarray, blocks: int, size: int) -> np.ndarray:
    """v (blocks * size,) -> the same blocks moved one step earlier, the last one repeated."""
    if blocks == 0 or size == 0:
        return v.copy()
    b = v.reshape(blocks, size)
    out = np.empty_like(b)
    out[:-1] = b[1:]
    out[-1] = b[-1]
    return out.ravel()


class OSQPHorizonSolver:
    """Solve :class:`HorizonProblem` as a sparse QP with OSQP (see the module docstring).

    Parameters: ``slack_l1`` (w1) and ``slack_l2`` (w2) the half-plane slack penalties,
    ``eps_abs`` / ``eps_rel`` OSQP tolerances, ``max_iter`` ADMM iteration cap, ``time_limit``
    seconds per solve (0: none), ``polish`` OSQP solution polishing, ``check_dualgap`` OSQP 1.x's
    extra duality-gap termination test (off by default: on the bicycle benchmark it
    raises the iteration count ~1.6-2x; the classic primal / dual residual tests and polishing
    still apply; see Accuracy in the module docstring), ``shift_warm_start`` shift the
    previous solution one step before warm starting (False: reuse it as is),
    ``accept_inaccurate`` also accept OSQP's "solved inaccurate" status (default: None).

    State kept between calls: ``builds`` (number of OSQP setups), ``failures`` (number of None
    returns), ``last_status`` (str), ``last_iter``, ``last_polish``, ``last_solve_time`` (s,
    OSQP's run time), ``last_x`` (N+1, n), ``last_slack`` (N+1, m), ``last_u`` (N, n_u).
    """

    def __init__(self, *, slack_l1: float = 1e3, slack_l2: float = 1.0, eps_abs: float = 1e-5,
                 eps_rel: float = 1e-5, max_iter: int = 4000, time_limit: float = 0.0,
                 polish: bool = True, check_dualgap: bool = False, shift_warm_start: bool = True,
                 accept_inaccurate: bool = False) -> None:
        if not (slack_l1 > 0 and slack_l2 > 0):
            raise ValueError("slack_l1 and slack_l2 must be > 0")
        if not (max_iter >= 1):
            raise ValueError("max_iter must be >= 1")
        self.slack_l1 = float(slack_l1)
        self.slack_l2 = float(slack_l2)
        self.settings: dict[str, Any] = dict(
            verbose=False, polishing=bool(polish), eps_abs=float(eps_abs), eps_rel=float(eps_rel),
            max_iter=int(max_iter), warm_starting=True, check_dualgap=bool(check_dualgap),
        )
        if time_limit and time_limit > 0:
            self.settings["time_limit"] = float(time_limit)
        self.shift_warm_start = bool(shift_warm_start)
        self.accept_inaccurate = bool(accept_inaccurate)

        self.builds = 0
        self.failures = 0
        self.last_status = "not run"
        self.last_iter = 0
        self.last_polish = 0
        self.last_solve_time = 0.0
        self.last_x: np.ndarray | None = None
        self.last_slack: np.ndarray | None = None
        self.last_u: np.ndarray | None = None

        self._shape: tuple[int, int, int, int] | None = None
        self._solver: osqp.OSQP | None = None
        self._z_prev: np.ndarray | None = None
        self._y_prev: np.ndarray | None = None
        self._Ax: np.ndarray | None = None
        self._Px: np.ndarray | None = None

    # ------------------------------------------------------------------ public

    def reset(self) -> None:
        """Forget the warm start (the next solve starts from z = 0, y = 0); keeps the setup."""
        self._z_prev = None
        self._y_prev = None

    def solve(self, problem: HorizonProblem) -> np.ndarray | None:
        """Optimal u~ (N, n_u) for ``problem``, or None (see the module docstring)."""
        N, n, n_u, m = self._check_shapes(problem)
        if not self._finite(problem):
            return self._fail("non-finite problem data")

        rebuild = self._shape != (N, n, n_u, m)
        if rebuild:
            self._shape, self._solver = None, None
            self._pattern(N, n, n_u, m)
        Px = self._hessian_values(problem)
        Ax = self._constraint_values(problem)
        q, l, u = self._vectors(problem)
        new_P = rebuild or not np.array_equal(Px, self._Px)
        if new_P and not self._convex(problem):
            # OSQP would refuse the setup, or (worse) ignore the update and solve the old problem
            return self._fail("non-convex cost (Q, R or P not positive semidefinite)")

        try:
            if rebuild:
                self._build(Px, q, Ax, l, u)
            else:
                kw: dict[str, Any] = dict(q=q, l=l, u=u)
                if not np.array_equal(Ax, self._Ax):
                    kw["Ax"] = Ax
                if new_P:
                    kw["Px"] = Px
                self._solver.update(**kw)
        except (osqp.OSQPException, ValueError) as exc:   # setup / update refused: rebuild next time
            self._shape, self._solver = None, None
            return self._fail(f"OSQP setup/update failed: {exc!r}")
        self._Ax, self._Px = Ax, Px

        z0, y0 = self._warm_start_point(problem)
        self._solver.warm_start(x=z0, y=y0)
        res = self._solver.solve(raise_error=False)

        info = res.info
        self.last_status = str(info.status)
        self.last_iter = int(info.iter)
        self.last_polish = int(info.status_polish)
        self.last_solve_time = float(info.run_time)
        ok = info.status_val == osqp.SolverStatus.OSQP_SOLVED or (
            self.accept_inaccurate and info.status_val == osqp.SolverStatus.OSQP_SOLVED_INACCURATE)
        z = np.array(res.x, dtype=float, copy=True)
        if not ok or not np.all(np.isfinite(z)):
            return self._fail(self.last_status)

        self._z_prev = z
        self._y_prev = np.array(res.y, dtype=float, copy=True)
        nx, nu = (N + 1) * n, N * n_u
        self.last_x = z[:nx].reshape(N + 1, n)
        self.last_slack = z[nx + nu:].reshape(N + 1, m)
        u_tilde = self._project_inputs(problem, z[nx:nx + nu].reshape(N, n_u))
        self.last_u = u_tilde
        return u_tilde.copy()

    # --------------------------------------------------------------- internals

    def _fail(self, status: str) -> None:
        self.failures += 1
        self.last_status = status
        self.reset()
        return None

    @staticmethod
    def _check_shapes(p: HorizonProblem) -> tuple[int, int, int, int]:
        A, B, G = np.asarray(p.A), np.asarray(p.B), np.asarray(p.G)
        if A.ndim != 3 or A.shape[1] != A.shape[2] or A.shape[0] < 1:
            raise ValueError(f"A must be (N, n, n) with N >= 1, got {A.shape}")
        N, n = A.shape[0], A.shape[1]
        if B.ndim != 3 or B.shape[:2] != (N, n):
            raise ValueError(f"B must be ({N}, {n}, n_u), got {B.shape}")
        n_u = B.shape[2]
        if G.ndim != 3 or G.shape[0] != N + 1 or G.shape[2] != n:
            raise ValueError(f"G must be ({N + 1}, m, {n}), got {G.shape}")
        m = G.shape[1]
        expect = {"c": (N, n), "x0": (n,), "Q": (n, n), "R": (n_u, n_u), "P": (n, n),
                  "u_ref": (N, n_u), "u_min": (n_u,), "u_max": (n_u,), "du_max": (n_u,),
                  "u_prev": (n_u,), "g": (N + 1, m)}
        for name, shape in expect.items():
            got = np.shape(getattr(p, name))
            if got != shape:
                raise ValueError(f"{name} must be {shape}, got {got}")
        if np.ndim(p.gamma) != 0:
            raise ValueError("gamma must be a scalar")
        return N, n, n_u, m

    @staticmethod
    def _finite(p: HorizonProblem) -> bool:
        for name in ("A", "B", "c", "x0", "Q", "R", "P", "u_ref", "u_prev", "G"):
            if not np.all(np.isfinite(getattr(p, name))):
                return False
        if not np.isfinite(p.gamma) or p.gamma <= 0:
            return False
        u_min, u_max, du = np.asarray(p.u_min, float), np.asarray(p.u_max, float), np.asarray(p.du_max, float)
        if np.any(np.isnan(u_min)) or np.any(np.isnan(u_max)) or np.any(np.isnan(du)):
            return False
        if np.any(u_min > u_max) or np.any(du < 0) or np.any(u_min == np.inf) or np.any(u_max == -np.inf):
            return False
        g = np.asarray(p.g, float)
        return not (np.any(np.isnan(g)) or np.any(g == -np.inf))

    @staticmethod
    def _convex(p: HorizonProblem) -> bool:
        """Q, R, P (symmetrised) positive semidefinite, to a relative 1e-9."""
        for M in (p.Q, p.R, p.P):
            M = np.asarray(M, float)
            ev = np.linalg.eigvalsh(0.5 * (M + M.T))
            if ev[0] < -1e-9 * max(1.0, abs(ev[-1])):
                return False
        return True

    def _hessian_values(self, p: HorizonProblem) -> np.ndarray:
        """Upper-triangle values of H in the (fixed) CSC order of :meth:`_build`."""
        N, m = p.N, np.shape(p.G)[1]
        gamma = float(p.gamma)
        Q = 0.5 * (np.asarray(p.Q, float) + np.asarray(p.Q, float).T)
        R = 0.5 * (np.asarray(p.R, float) + np.asarray(p.R, float).T)
        P = 0.5 * (np.asarray(p.P, float) + np.asarray(p.P, float).T)
        disc = 2.0 * gamma ** np.arange(N + 1)
        (iq, jq), (ir, jr) = self._triu_x, self._triu_u
        qv, pv, rv = Q[iq, jq], P[iq, jq], R[ir, jr]
        parts = [np.outer(disc[:N], qv).ravel(), disc[N] * pv,
                 np.outer(disc[:N], rv).ravel(), np.full((N + 1) * m, 2.0 * self.slack_l2)]
        return np.concatenate(parts)

    def _constraint_values(self, p: HorizonProblem) -> np.ndarray:
        Ax = self._Ax_template.copy()
        Ax[self._posA] = -np.asarray(p.A, float).ravel()
        Ax[self._posB] = -np.asarray(p.B, float).ravel()
        Ax[self._posG] = np.asarray(p.G, float).ravel()
        return Ax

    def _pattern(self, N: int, n: int, n_u: int, m: int) -> None:
        """Fixed CSC pattern of the constraint matrix for this shape (stored as _pat_*)."""
        nx, nu, ns = (N + 1) * n, N * n_u, (N + 1) * m
        r_in = nx                 # first row of the input bounds
        r_rate = r_in + nu        # first row of the rate limits
        r_hp = r_rate + nu        # first row of the half-planes
        r_sl = r_hp + ns          # first row of the slack bounds
        rows, cols, vals = [], [], []
        slices: dict[str, slice] = {}

        def add(name: str, r: np.ndarray, c: np.ndarray, v: np.ndarray) -> None:
            start = sum(len(x) for x in rows)
            rows.append(r.ravel()); cols.append(c.ravel()); vals.append(np.broadcast_to(v, r.shape).ravel())
            slices[name] = slice(start, start + r.size)

        tau = np.arange(N)
        # dynamics: identity on x~_0 .. x~_N
        idx = np.arange(nx)
        add("Ix", idx, idx, np.ones(1))
        # -A_tau on rows of block tau+1, columns of x~_tau (row-major per block = A.ravel())
        i, j = np.arange(n)[:, None], np.arange(n)[None, :]
        r = (tau[:, None, None] + 1) * n + i + 0 * j
        c = tau[:, None, None] * n + j + 0 * i
        add("A", r, c, np.zeros(1))
        # -B_tau: rows of block tau+1, columns of u~_tau
        i, j = np.arange(n)[:, None], np.arange(n_u)[None, :]
        r = (tau[:, None, None] + 1) * n + i + 0 * j
        c = nx + tau[:, None, None] * n_u + j + 0 * i
        add("B", r, c, np.zeros(1))
        # input bounds: identity on u~
        idx = np.arange(nu)
        add("Iu", r_in + idx, nx + idx, np.ones(1))
        # rate limits: +u~_tau, -u~_{tau-1}
        add("rate+", r_rate + idx, nx + idx, np.ones(1))
        idx1 = np.arange(n_u, nu)
        add("rate-", r_rate + idx1, nx + idx1 - n_u, -np.ones(1))
        # half-planes: G_tau on x~_tau, -I on s_tau
        t1 = np.arange(N + 1)
        i, j = np.arange(m)[:, None], np.arange(n)[None, :]
        r = r_hp + t1[:, None, None] * m + i + 0 * j
        c = t1[:, None, None] * n + j + 0 * i
        add("G", r, c, np.zeros(1))
        idx = np.arange(ns)
        add("Is", r_hp + idx, nx + nu + idx, -np.ones(1))
        # slack bounds
        add("Isb", r_sl + idx, nx + nu + idx, np.ones(1))

        rows_a, cols_a = np.concatenate(rows), np.concatenate(cols)
        vals_a = np.concatenate(vals).astype(float)
        n_rows, n_z = r_sl + ns, nx + nu + ns
        # CSC order: by column, then row (no duplicates by construction)
        order = np.lexsort((rows_a, cols_a))
        pos = np.empty_like(order)
        pos[order] = np.arange(order.size)        # COO index -> CSC position
        indptr = np.zeros(n_z + 1, dtype=np.int64)
        np.add.at(indptr, cols_a + 1, 1)
        self._pat_indices = rows_a[order].astype(np.int64)
        self._pat_indptr = np.cumsum(indptr)
        self._pat_dims = (n_rows, n_z)
        self._pat_shape = (N, n, n_u, m)
        # upper triangles of the Q / P and R blocks in CSC order (by column, then row)
        self._triu_x = np.tril_indices(n)[::-1]
        self._triu_u = np.tril_indices(n_u)[::-1]
        self._Ax_template = vals_a[order]
        self._posA, self._posB, self._posG = pos[slices["A"]], pos[slices["B"]], pos[slices["G"]]
        self._rows = dict(in_=r_in, rate=r_rate, hp=r_hp, sl=r_sl, end=n_rows)

    def _hessian_pattern(self, N: int, n: int, n_u: int, m: int) -> tuple[np.ndarray, np.ndarray]:
        """(indices, indptr) of the block-diagonal upper-triangular Hessian."""
        n_z = (N + 1) * n + N * n_u + (N + 1) * m
        indices, counts = [], np.zeros(n_z, dtype=np.int64)
        col = 0
        for size, reps in ((n, N + 1), (n_u, N)):
            for _ in range(reps):
                for j in range(size):
                    indices.append(col + np.arange(j + 1))
                    counts[col + j] = j + 1
                col += size
        s = np.arange(col, n_z)
        indices.append(s)
        counts[col:] = 1
        indptr = np.concatenate([[0], np.cumsum(counts)])
        return np.concatenate(indices).astype(np.int64), indptr

    def _vectors(self, p: HorizonProblem) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """q (n_z,), l and u (n_rows,) for this problem."""
        N, n, n_u = p.N, p.n, p.n_u
        m = np.shape(p.G)[1]
        u_min, u_max = np.asarray(p.u_min, float), np.asarray(p.u_max, float)
        du = np.asarray(p.du_max, float)
        u_ref = np.asarray(p.u_ref, float)
        u_prev = np.clip(np.asarray(p.u_prev, float), u_min, u_max)

        dyn = np.concatenate([np.asarray(p.x0, float), np.asarray(p.c, float).ravel()])
        in_l = (u_min[None, :] - u_ref).ravel()
        in_u = (u_max[None, :] - u_ref).ravel()
        d_ref = np.empty_like(u_ref)
        d_ref[0] = u_ref[0] - u_prev
        d_ref[1:] = u_ref[1:] - u_ref[:-1]
        rate_l = (-du[None, :] - d_ref).ravel()
        rate_u = (du[None, :] - d_ref).ravel()
        G, g = np.asarray(p.G, float), np.asarray(p.g, float)
        active = (np.any(G != 0.0, axis=2) & np.isfinite(g)).ravel()
        hp_u = np.where(active, g.ravel(), np.inf)
        ns = (N + 1) * m
        l = np.concatenate([dyn, in_l, rate_l, np.full(ns, -np.inf), np.zeros(ns)])
        u = np.concatenate([dyn, in_u, rate_u, hp_u, np.full(ns, np.inf)])
        # inactive rows: no L1 term, so their slack sits at 0 with a zero multiplier
        q = np.zeros(self._pat_dims[1])
        q[(N + 1) * n + N * n_u:] = np.where(active, self.slack_l1, 0.0)
        return q, np.clip(l, -_INF, _INF), np.clip(u, -_INF, _INF)

    def _build(self, Px: np.ndarray, q: np.ndarray, Ax: np.ndarray, l: np.ndarray, u: np.ndarray) -> None:
        """OSQP setup for the shape of :meth:`_pattern` (the only place OSQP.setup is called)."""
        N, n, n_u, m = self._pat_shape
        n_rows, n_z = self._pat_dims
        A_csc = sp.csc_matrix((Ax.copy(), self._pat_indices.copy(), self._pat_indptr.copy()), shape=(n_rows, n_z))
        h_ind, h_ptr = self._hessian_pattern(N, n, n_u, m)
        P_csc = sp.csc_matrix((Px.copy(), h_ind, h_ptr), shape=(n_z, n_z))
        solver = osqp.OSQP()
        solver.setup(P_csc, q, A_csc, l, u, **self.settings)
        self._solver = solver
        self._shape = self._pat_shape
        self.builds += 1
        self.reset()

    def _warm_start_point(self, p: HorizonProblem) -> tuple[np.ndarray, np.ndarray]:
        N, n, n_u, m = self._shape
        n_rows, n_z = self._pat_dims
        if self._z_prev is None or self._y_prev is None:
            return np.zeros(n_z), np.zeros(n_rows)
        z, y = self._z_prev, self._y_prev
        if not self.shift_warm_start:
            z = z.copy()
            z[:n] = p.x0
            return z, y.copy()
        nx, nu = (N + 1) * n, N * n_u
        zs = np.concatenate([_shift(z[:nx], N + 1, n), _shift(z[nx:nx + nu], N, n_u),
                             _shift(z[nx + nu:], N + 1, m)])
        zs[:n] = p.x0
        r = self._rows
        ys = np.concatenate([_shift(y[:nx], N + 1, n), _shift(y[r["in_"]:r["rate"]], N, n_u),
                             _shift(y[r["rate"]:r["hp"]], N, n_u), _shift(y[r["hp"]:r["sl"]], N + 1, m),
                             _shift(y[r["sl"]:], N + 1, m)])
        return zs, ys

    @staticmethod
    def _project_inputs(p: HorizonProblem, u_tilde: np.ndarray) -> np.ndarray:
        """Project u~ (N, n_u) step by step onto the hard input set (bounds, rate limits)."""
        u_min, u_max = np.asarray(p.u_min, float), np.asarray(p.u_max, float)
        du = np.asarray(p.du_max, float)
        u_ref = np.asarray(p.u_ref, float)
        prev = np.clip(np.asarray(p.u_prev, float), u_min, u_max)
        out = np.empty_like(u_tilde)
        for k in range(u_tilde.shape[0]):
            lo = np.maximum(u_min, prev - du)
            hi = np.minimum(u_max, prev + du)
            uk = np.clip(u_ref[k] + u_tilde[k], lo, hi)
            out[k] = uk - u_ref[k]
            prev = uk
        return out


class KoopmanMPC:
    """:class:`OSQPHorizonSolver` behind VF-LPC's horizon-solver protocol: the barrier's threatening
    obstacles become the QP's soft half-planes (at most ``m``, the fixed sparsity pattern's width),
    so the Koopman-MPC baseline sees the same reference, model, cost and threats as Eb-RHRL.
    Its warm start is OSQP's own (shifted previous solution), so ``shift`` has nothing to do."""

    def __init__(self, m: int, **options) -> None:
        self.m = int(m)
        self.qp = OSQPHorizonSolver(**options)

    def solve(self, problem: HorizonProblem, barrier: HorizonBarrier | None):
        if barrier is not None:
            G, g = barrier.halfplanes(problem.n, self.m)
        else:
            G, g = np.zeros((problem.N + 1, self.m, problem.n)), np.zeros((problem.N + 1, self.m))
        u = self.qp.solve(replace(problem, G=G, g=g))
        return u, self.qp.last_status

    def shift(self) -> None:
        pass

    def reset(self) -> None:
        self.qp.reset()


# ---------------------------------------------------------------------- timing


def bicycle_problem(rng: np.random.Generator, N: int = 20, m: int = 2, x0_scale: float = 0.1,
                    model_path: str | None = None) -> HorizonProblem:
    """A HorizonProblem on the shipped dynamic-bicycle Koopman model (n = 9, n_u = 2).

    A = A_K[:-1, :-1], B = B_K[:-1] (the constant observable dropped; for a model scheduled on the
    speed, B_K + 6 B_s, its input matrix at 6 m/s) for every step,
    Q = diag(1, 4, 4, 0.5, 0, ...), R = diag(0.1, 1), P the discrete ARE solution, gamma = 1,
    c = 0, u_ref = 0, x0 = x0_scale * standard normal (n,), a in [-6, 3], delta in
    [-0.5, 0.5], du_max = [inf, 0.03], u_prev = 0, and (m <= 2) two unit-norm half-planes per
    step on the X-Y error: Y~ <= 0.15 and -0.6 X~ - 0.8 Y~ <= 0.2.
    """
    import scipy.linalg as sla

    from vflpcd.config.koopman_file import load_koopman
    from vflpcd.base.paths import config_dir

    path = model_path if model_path is not None else config_dir() / "models" / "dynamic_bicycle.npz"
    km = load_koopman(path)
    A = np.asarray(km.A, float)[:-1, :-1]
    B = np.asarray(km.B + (6.0 * km.B_s if km.scheduled else 0.0), float)[:-1]
    n, n_u = A.shape[0], B.shape[1]
    Q = np.diag([1.0, 4.0, 4.0, 0.5] + [0.0] * (n - 4))
    R = np.diag([0.1, 1.0])
    P = sla.solve_discrete_are(A, B, Q, R)
    G = np.zeros((N + 1, m, n))
    g = np.zeros((N + 1, m))
    if m > 0:
        G[:, 0, 1], g[:, 0] = 1.0, 0.15
    if m > 1:
        G[:, 1, 0], G[:, 1, 1], g[:, 1] = -0.6, -0.8, 0.2
    return HorizonProblem(
        A=np.repeat(A[None], N, 0), B=np.repeat(B[None], N, 0), c=np.zeros((N, n)),
        x0=x0_scale * rng.standard_normal(n), Q=Q, R=R, P=P, gamma=1.0, u_ref=np.zeros((N, n_u)),
        u_min=np.array([-6.0, -0.5]), u_max=np.array([3.0, 0.5]), du_max=np.array([np.inf, 0.03]),
        u_prev=np.zeros(n_u), G=G, g=g)


def benchmark(n_calls: int = 500, N: int = 20, m: int = 2, seed: int = 0, x0_scale: float = 0.1,
              closed_loop: bool = False, perturb_A: bool = False,
              solver: OSQPHorizonSolver | None = None) -> dict[str, float]:
    """Wall time of warm-started :meth:`OSQPHorizonSolver.solve` on :func:`bicycle_problem`.

    One cold solve (the build) first, then ``n_calls`` timed solves of the same shape. x0 is
    drawn afresh (x0_scale * standard normal) every call, or, with ``closed_loop``, advanced
    by the linear model under the first optimal control plus noise (0.003 standard normal),
    u_prev following the applied command: consecutive problems then resemble each other as
    they do in the controller. ``perturb_A`` multiplies A_tau by (1 + 1e-3 noise) every call,
    forcing an Ax update and a KKT refactorisation, as a GP correction would. Returns the
    median / p99 / max wall time of ``solve`` in ms, the median / max OSQP iterations, the
    number of failures (None) and builds. It asserts nothing about time.
    """
    import dataclasses

    rng = np.random.default_rng(seed)
    base = bicycle_problem(rng, N=N, m=m, x0_scale=x0_scale)
    solver = solver if solver is not None else OSQPHorizonSolver()
    solver.solve(base)
    x0, u_prev = base.x0, base.u_prev
    times, iters = [], []
    for _ in range(n_calls):
        if not closed_loop:
            x0 = x0_scale * rng.standard_normal(base.n)
        kw: dict[str, Any] = dict(x0=x0, u_prev=u_prev)
        if perturb_A:
            kw["A"] = base.A * (1.0 + 1e-3 * rng.standard_normal(base.A.shape))
        prob = dataclasses.replace(base, **kw)
        t0 = time.perf_counter()
        u_t = solver.solve(prob)
        times.append(time.perf_counter() - t0)
        iters.append(solver.last_iter)
        if closed_loop:
            u0 = np.zeros(base.n_u) if u_t is None else u_t[0]
            x0 = prob.A[0] @ x0 + prob.B[0] @ u0 + 0.003 * rng.standard_normal(base.n)
            u_prev = prob.u_ref[0] + u0
    t = np.array(times) * 1e3
    return dict(median_ms=float(np.median(t)), p99_ms=float(np.percentile(t, 99)), max_ms=float(t.max()),
                median_iter=float(np.median(iters)), max_iter=float(np.max(iters)),
                failures=float(solver.failures), builds=float(solver.builds))


if __name__ == "__main__":  # pragma: no cover
    for cl in (False, True):
        for pa in (False, True):
            r = benchmark(closed_loop=cl, perturb_A=pa)
            print(f"closed_loop={cl!s:5} perturb_A={pa!s:5} " + " ".join(f"{k}={v:.3g}" for k, v in r.items()))


def make_koopman_mpc(scenario, **options):
    """VF-LPC's guidance and Koopman model with this OSQP horizon solver in place of Eb-RHRL."""
    from vflpcd.controllers.vflpc import load_params, make_vflpc

    return make_vflpc(scenario, solver=KoopmanMPC(load_params(scenario.platform).max_threats), name="koopman_mpc",
                      **options)
