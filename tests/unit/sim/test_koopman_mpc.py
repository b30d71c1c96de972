"""OSQPHorizonSolver against closed-form references: finite-horizon LQR, a dense condensed QP
solved with numpy, scipy's SLSQP on the constrained condensed QP; warm start, updates, NaN."""

import dataclasses

import numpy as np
import pytest

pytest.importorskip("osqp")

from vflpcd.controllers.koopman_mpc import OSQPHorizonSolver, benchmark  # noqa: E402
from vflpcd.core.control.problem import HorizonProblem, finite_horizon_lqr  # noqa: E402

INF = np.inf


def random_system(rng, n, n_u):
    """A stable-ish (spectral radius 0.95..1.05) A (n, n) and B (n, n_u)."""
    A = rng.standard_normal((n, n))
    A *= rng.uniform(0.95, 1.05) / max(abs(np.linalg.eigvals(A)))
    B = rng.standard_normal((n, n_u))
    return A, B


def make_problem(rng, N=8, n=4, n_u=2, m=1, gamma=1.0, time_varying=False, c_scale=0.0, **kw):
    A, B = random_system(rng, n, n_u)
    As = np.repeat(A[None], N, 0)
    Bs = np.repeat(B[None], N, 0)
    if time_varying:
        As = As + 0.1 * rng.standard_normal((N, n, n))
        Bs = Bs + 0.1 * rng.standard_normal((N, n, n_u))
    L = rng.standard_normal((n, n))
    Q = L @ L.T / n + 0.1 * np.eye(n)
    R = np.diag(rng.uniform(0.5, 2.0, n_u))
    P = 2.0 * Q
    base = dict(
        A=As, B=Bs, c=c_scale * rng.standard_normal((N, n)), x0=rng.standard_normal(n), Q=Q, R=R, P=P,
        gamma=gamma, u_ref=np.zeros((N, n_u)), u_min=np.full(n_u, -INF), u_max=np.full(n_u, INF),
        du_max=np.full(n_u, INF), u_prev=np.zeros(n_u), G=np.zeros((N + 1, m, n)), g=np.zeros((N + 1, m)))
    base.update(kw)
    return HorizonProblem(**base)


def condensed(p: HorizonProblem):
    """V(u~) = 1/2 u' H u + f' u + const with u = u~.ravel(); returns H, f."""
    N, n, n_u = p.N, p.n, p.n_u
    # x_k = S_k u + s_k
    S = np.zeros((N + 1, n, N * n_u))
    s = np.zeros((N + 1, n))
    s[0] = p.x0
    for k in range(N):
        S[k + 1] = p.A[k] @ S[k]
        S[k + 1][:, k * n_u:(k + 1) * n_u] += p.B[k]
        s[k + 1] = p.A[k] @ s[k] + p.c[k]
    H = np.zeros((N * n_u, N * n_u))
    f = np.zeros(N * n_u)
    for k in range(N + 1):
        W = p.gamma ** k * (p.Q if k < N else p.P)
        H += 2 * S[k].T @ W @ S[k]
        f += 2 * S[k].T @ W @ s[k]
    for k in range(N):
        E = np.zeros((n_u, N * n_u))
        E[:, k * n_u:(k + 1) * n_u] = np.eye(n_u)
        H += 2 * p.gamma ** k * E.T @ p.R @ E
    return H, f


def dense_solution(p: HorizonProblem) -> np.ndarray:
    H, f = condensed(p)
    return np.linalg.solve(H, -f).reshape(p.N, p.n_u)


def rel_err(a, b):
    return np.linalg.norm(a - b) / max(np.linalg.norm(b), 1e-12)


# ----------------------------------------------------------------- unconstrained


@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_unconstrained_first_control_is_lqr(gamma):
    rng = np.random.default_rng(1)
    p = make_problem(rng, N=15, n=5, n_u=2, gamma=gamma)
    K = finite_horizon_lqr(p.A[0], p.B[0], p.Q, p.R, p.P, p.N, gamma)
    u = OSQPHorizonSolver().solve(p)
    assert u is not None and u.shape == (15, 2)
    assert rel_err(u[0], -K[0] @ p.x0) < 1e-4


def test_unconstrained_huge_bounds_and_m0():
    rng = np.random.default_rng(2)
    p = make_problem(rng, m=0, u_min=np.full(2, -1e9), u_max=np.full(2, 1e9))
    K = finite_horizon_lqr(p.A[0], p.B[0], p.Q, p.R, p.P, p.N)
    u = OSQPHorizonSolver().solve(p)
    assert rel_err(u[0], -K[0] @ p.x0) < 1e-4


def test_time_varying_with_affine_term_matches_dense_kkt():
    rng = np.random.default_rng(3)
    p = make_problem(rng, N=10, n=5, n_u=2, gamma=0.95, time_varying=True, c_scale=0.3)
    u = OSQPHorizonSolver().solve(p)
    ref = dense_solution(p)
    assert rel_err(u, ref) < 1e-4
    assert p.cost(u) == pytest.approx(p.cost(ref), rel=1e-6)


# ------------------------------------------------------------- input constraints


def slsqp_reference(p: HorizonProblem) -> np.ndarray:
    """The bound / rate constrained condensed QP by scipy's SLSQP (tight tolerance)."""
    from scipy.optimize import minimize

    H, f = condensed(p)
    N, n_u = p.N, p.n_u
    lo = (p.u_min[None] - p.u_ref).ravel()
    hi = (p.u_max[None] - p.u_ref).ravel()
    D = np.eye(N * n_u) - np.eye(N * n_u, k=-n_u)          # u~_k - u~_{k-1}
    d_ref = np.diff(np.vstack([np.clip(p.u_prev, p.u_min, p.u_max), p.u_ref]), axis=0).ravel()
    du = np.tile(p.du_max, N)
    fin = np.isfinite(du)
    cons = [{"type": "ineq", "fun": lambda v: (du - D @ v - d_ref)[fin], "jac": lambda v: -D[fin]},
            {"type": "ineq", "fun": lambda v: (du + D @ v + d_ref)[fin], "jac": lambda v: D[fin]}]
    res = minimize(lambda v: 0.5 * v @ H @ v + f @ v, np.zeros(N * n_u), jac=lambda v: H @ v + f,
                   bounds=list(zip(lo, hi)), constraints=cons, method="SLSQP",
                   options=dict(ftol=1e-14, maxiter=500))
    return res.x.reshape(N, n_u)


def input_violation(p: HorizonProblem, u_tilde: np.ndarray) -> float:
    u = p.u_ref + u_tilde
    du = np.diff(np.vstack([np.clip(p.u_prev, p.u_min, p.u_max), u]), axis=0)
    return float(max(np.max(u - p.u_max), np.max(p.u_min - u), np.max(np.abs(du) - p.du_max)))


def test_input_bounds_and_rate_limits_are_respected_and_optimal():
    rng = np.random.default_rng(4)
    p = make_problem(rng, N=10, n=4, n_u=2, time_varying=True,
                     u_ref=0.1 * rng.standard_normal((10, 2)), u_prev=np.array([0.2, -0.1]),
                     u_min=np.array([-0.5, -0.3]), u_max=np.array([0.4, 0.3]), du_max=np.array([INF, 0.05]))
    p = dataclasses.replace(p, x0=5.0 * p.x0)
    u_free = dense_solution(p)
    assert input_violation(p, u_free) > 0.1                 # the constraints do bite
    u = OSQPHorizonSolver().solve(p)
    assert u is not None
    assert input_violation(p, u) <= 1e-6
    ref = slsqp_reference(p)
    assert p.cost(u) <= p.cost(ref) * (1 + 1e-6) + 1e-9
    assert rel_err(u, ref) < 1e-3


def test_u_prev_outside_bounds_is_clipped_not_infeasible():
    rng = np.random.default_rng(5)
    p = make_problem(rng, u_min=np.array([-1.0, -0.2]), u_max=np.array([1.0, 0.2]),
                     du_max=np.array([0.1, 0.01]), u_prev=np.array([3.0, -0.9]))
    solver = OSQPHorizonSolver()
    u = solver.solve(p)
    assert u is not None and solver.failures == 0
    assert input_violation(p, u) <= 1e-6                    # measured from clip(u_prev)


# ------------------------------------------------------------------ half-planes


def test_active_half_plane_is_respected_with_zero_slack():
    rng = np.random.default_rng(6)
    p = make_problem(rng, N=10, n=4, n_u=2, m=2)
    x_free = p.rollout(dense_solution(p))
    G = np.zeros((p.N + 1, 2, p.n))
    g = np.zeros((p.N + 1, 2))
    G[1:, 0, 0] = 1.0                                       # x~_0[0] <= bound, from step 1 on
    bound = x_free[1:, 0].max() - 0.3
    g[1:, 0] = bound
    g[:, 1] = 5.0                                           # second row: inactive (G row zero)
    p = dataclasses.replace(p, G=G, g=g)
    solver = OSQPHorizonSolver()
    u = solver.solve(p)
    assert u is not None
    x = p.rollout(u)
    assert np.max(x[1:, 0]) <= bound + 1e-5
    assert np.max(x[1:, 0]) >= bound - 1e-5                 # active
    assert np.max(solver.last_slack) < 1e-6
    assert np.allclose(solver.last_x, x, atol=1e-5)


def test_infeasible_half_plane_returns_a_solution_with_positive_slack():
    rng = np.random.default_rng(7)
    p = make_problem(rng, N=10, n=4, n_u=2, m=1)
    G = np.zeros((p.N + 1, 1, p.n))
    G[:, 0, 1] = 1.0
    g = np.full((p.N + 1, 1), p.x0[1] - 1.0)                # x~_0 already violates it by 1
    p = dataclasses.replace(p, G=G, g=g, u_min=np.full(2, -0.2), u_max=np.full(2, 0.2))
    solver = OSQPHorizonSolver()
    u = solver.solve(p)
    assert u is not None, solver.last_status
    assert solver.last_slack[0, 0] == pytest.approx(1.0, abs=1e-5)
    assert np.all(solver.last_slack >= -1e-7)
    assert input_violation(p, u) <= 1e-6


# ------------------------------------------------------- warm start and updates


def test_warm_start_reuses_setup_and_matches_cold_solve():
    rng = np.random.default_rng(8)
    p = make_problem(rng, N=12, n=5, n_u=2, m=1, time_varying=True, c_scale=0.1,
                     u_min=np.full(2, -0.5), u_max=np.full(2, 0.5), du_max=np.array([0.2, INF]))
    solver = OSQPHorizonSolver()
    u1 = solver.solve(p)
    p2 = dataclasses.replace(p, x0=p.x0 + 0.05 * rng.standard_normal(p.n))
    u2 = solver.solve(p2)
    assert solver.builds == 1
    cold = OSQPHorizonSolver().solve(p2)
    assert u1 is not None and u2 is not None
    np.testing.assert_allclose(u2, cold, atol=1e-6)
    solver.reset()
    np.testing.assert_allclose(solver.solve(p2), cold, atol=1e-6)
    assert solver.builds == 1
    # a different shape rebuilds
    p3 = make_problem(rng, N=6, n=5, n_u=2, m=1)
    assert solver.solve(p3) is not None
    assert solver.builds == 2


def test_changing_A_values_with_same_structure():
    rng = np.random.default_rng(9)
    p = make_problem(rng, N=10, n=5, n_u=2, m=1, time_varying=True, c_scale=0.2, gamma=0.97)
    A1 = p.A.copy()
    A1[:, 0, 1:] = 0.0                                      # zeros in the first call ...
    A1[3] = 0.0                                             # ... a whole block too
    B1 = p.B.copy()
    B1[:, 2, :] = 0.0
    p1 = dataclasses.replace(p, A=A1, B=B1)
    solver = OSQPHorizonSolver()
    assert rel_err(solver.solve(p1), dense_solution(p1)) < 1e-4
    p2 = dataclasses.replace(p, A=p.A * (1 + 0.2 * rng.standard_normal(p.A.shape)))   # ... non-zero now
    u2 = solver.solve(p2)
    assert solver.builds == 1
    ref = dense_solution(p2)
    assert rel_err(u2, ref) < 1e-4
    np.testing.assert_allclose(u2, OSQPHorizonSolver().solve(p2), atol=1e-6)
    # Q, R, P and gamma changes are picked up too (Px update)
    p3 = dataclasses.replace(p2, Q=2 * p2.Q, R=0.5 * p2.R, gamma=0.9)
    assert rel_err(solver.solve(p3), dense_solution(p3)) < 1e-4
    assert solver.builds == 1


def test_changing_half_planes_between_calls():
    rng = np.random.default_rng(10)
    p = make_problem(rng, N=10, n=4, n_u=2, m=1)
    solver = OSQPHorizonSolver()
    u0 = solver.solve(p)                                    # G = 0: unconstrained
    assert rel_err(u0, dense_solution(p)) < 1e-4
    x_free = p.rollout(u0)
    G = np.zeros((p.N + 1, 1, p.n))
    G[2:, 0, 2] = -1.0
    g = np.full((p.N + 1, 1), -(x_free[2:, 2].min() + 0.2))
    p2 = dataclasses.replace(p, G=G, g=g)                   # -x~[2] <= -(min + 0.2): active
    u = solver.solve(p2)
    assert np.min(p2.rollout(u)[2:, 2]) >= x_free[2:, 2].min() + 0.2 - 1e-5
    np.testing.assert_allclose(u, OSQPHorizonSolver().solve(p2), atol=1e-6)
    assert solver.builds == 1


# ----------------------------------------------------------------------- failures


def test_nan_x0_returns_none_and_solver_stays_usable():
    rng = np.random.default_rng(11)
    p = make_problem(rng, m=1, u_min=np.full(2, -1.0), u_max=np.full(2, 1.0))
    solver = OSQPHorizonSolver()
    assert solver.solve(p) is not None
    bad = dataclasses.replace(p, x0=np.where(np.arange(p.n) == 1, np.nan, p.x0))
    assert solver.solve(bad) is None
    assert solver.failures == 1 and solver.last_status == "non-finite problem data"
    u = solver.solve(p)
    assert u is not None and solver.last_status == "solved" and solver.builds == 1
    np.testing.assert_allclose(u, OSQPHorizonSolver().solve(p), atol=1e-6)


def test_nan_before_first_build_and_bad_shapes():
    rng = np.random.default_rng(12)
    p = make_problem(rng)
    solver = OSQPHorizonSolver()
    assert solver.solve(dataclasses.replace(p, A=np.full_like(p.A, np.nan))) is None
    assert solver.failures == 1 and solver.builds == 0
    assert solver.solve(p) is not None
    with pytest.raises(ValueError):
        solver.solve(dataclasses.replace(p, x0=np.zeros(p.n + 1)))


def test_non_convex_cost_returns_none_and_solver_stays_usable():
    # OSQP's update() would ignore a non-convex Px and solve the previous problem: refused first
    rng = np.random.default_rng(14)
    p = make_problem(rng)
    solver = OSQPHorizonSolver()
    u = solver.solve(p)
    assert solver.solve(dataclasses.replace(p, Q=-p.Q)) is None
    assert solver.failures == 1 and "non-convex" in solver.last_status
    np.testing.assert_allclose(solver.solve(p), u, atol=1e-6)
    assert OSQPHorizonSolver().solve(dataclasses.replace(p, R=-p.R)) is None   # before any build


def test_max_iter_failure_is_counted():
    rng = np.random.default_rng(13)
    p = make_problem(rng, u_min=np.full(2, -0.1), u_max=np.full(2, 0.1), du_max=np.full(2, 0.01))
    solver = OSQPHorizonSolver(max_iter=1, polish=False)
    assert solver.solve(p) is None
    assert solver.failures == 1 and "iter" in solver.last_status


def test_benchmark_runs():
    pytest.importorskip("scipy")
    r = benchmark(n_calls=5, closed_loop=True)
    assert r["builds"] == 1 and r["median_ms"] > 0
