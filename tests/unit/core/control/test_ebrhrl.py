"""Eb-RHRL against closed forms: finite-horizon LQR (h = 0, linear model) and a direct optimiser."""

import numpy as np
import pytest
import scipy.linalg as sl
from scipy.optimize import minimize

from vflpcd.controllers.loops import ebrhrl_loop
from vflpcd.core.control.barrier import HorizonBarrier
from vflpcd.core.control.ebrhrl import EbRHRL, KernelFeatures
from vflpcd.core.control.problem import HorizonProblem, finite_horizon_lqr

N, n, n_u = 15, 5, 2


def _system(seed: int):
    rng = np.random.default_rng(seed)
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))          # open-loop unstable in general
    B = 0.2 * rng.normal(size=(n, n_u))
    Q = np.diag(rng.uniform(0.5, 3.0, n))
    R = np.diag(rng.uniform(0.1, 1.0, n_u))
    return rng, A, B, Q, R


def _problem(A, B, Q, R, P, x0, c=None, gamma=1.0) -> HorizonProblem:
    inf = np.full(n_u, np.inf)
    return HorizonProblem(A=np.repeat(A[None], N, 0), B=np.repeat(B[None], N, 0),
                          c=np.zeros((N, n)) if c is None else c, x0=x0, Q=Q, R=R, P=P, gamma=gamma,
                          u_ref=np.zeros((N, n_u)), u_min=-inf, u_max=inf, du_max=inf, u_prev=np.zeros(n_u),
                          G=np.zeros((N + 1, 0, n)), g=np.zeros((N + 1, 0)))


def _barrier() -> HorizonBarrier:
    T = N + 1
    return HorizonBarrier(pos_index=np.array([0, 1]), p_ref=np.zeros((T, 2)),
                          x_p=np.tile([[0.3, 0.2]], (1, T, 1)), normal=np.tile([[0.6, 0.8]], (1, T, 1)),
                          mu=np.array([2.0]))


def _features(rng, ell=5.0):
    return KernelFeatures.from_samples(rng.normal(size=(300, n)), np.full(n, ell), 0.05, 16)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("terminal", ["dare", "Q", "10dare"])
@pytest.mark.parametrize("gamma", [1.0, 0.9])
def test_converged_actor_is_the_finite_horizon_lqr(seed, terminal, gamma):
    rng, A, B, Q, R = _system(seed)
    P_dare = sl.solve_discrete_are(np.sqrt(gamma) * A, np.sqrt(gamma) * B, Q, R)
    P = {"dare": P_dare, "Q": Q, "10dare": 10 * P_dare}[terminal]
    solver = EbRHRL(A, B, Q, R, P, gamma, _features(rng), N, i_max=200, tol=1e-20)
    solver.W_a = 0.3 * rng.normal(size=solver.W_a.shape)   # start away from the prior
    x0 = rng.normal(size=n)
    u, info = solver.solve(_problem(A, B, Q, R, P, x0, gamma=gamma))
    u_lqr = -finite_horizon_lqr(A, B, Q, R, P, N, gamma)[0] @ x0
    assert np.linalg.norm(u[0] - u_lqr) / np.linalg.norm(u_lqr) < 1e-3
    assert info.converged and info.iterations < 50


def test_affine_term_matches_the_condensed_qp():
    rng, A, B, Q, R = _system(7)
    P = sl.solve_discrete_are(A, B, Q, R)
    c = 0.1 * rng.normal(size=(N, n))
    prob = _problem(A, B, Q, R, P, rng.normal(size=n), c)
    u, info = EbRHRL(A, B, Q, R, P, 1.0, _features(rng), N, i_max=100, tol=1e-20).solve(prob)
    best = minimize(lambda v: prob.cost(v.reshape(N, n_u)), np.zeros(N * n_u), method="BFGS",
                    options={"gtol": 1e-10}).x.reshape(N, n_u)
    assert np.allclose(u, best, atol=1e-4)


def test_with_the_barrier_it_reaches_the_optimum_of_the_barrier_cost():
    rng, A, B, Q, R = _system(3)
    P = sl.solve_discrete_are(A, B, Q, R)
    x0 = np.array([1.0, 0.5, 0.0, 0.0, 0.0])
    prob = _problem(A, B, Q, R, P, x0)
    barrier = _barrier()

    def total(v):
        U = v.reshape(N, n_u)
        x = prob.rollout(U)
        return prob.cost(U) + float(barrier.value(x)[:-1] @ np.ones(N) + barrier.value(x)[-1])

    solver = EbRHRL(A, B, Q, R, P, 1.0, _features(rng), N, i_max=200, tol=1e-22)
    u, info = solver.solve(prob, barrier)
    best = minimize(total, np.zeros(N * n_u), method="BFGS", options={"gtol": 1e-10}).x.reshape(N, n_u)
    assert info.converged
    assert np.allclose(u, best, atol=1e-4)
    assert total(u.ravel()) <= total(best.ravel()) + 1e-8


def test_shift_moves_each_steps_weights_one_step_earlier_and_keeps_the_last():
    rng, A, B, Q, R = _system(2)
    solver = EbRHRL(A, B, Q, R, sl.solve_discrete_are(A, B, Q, R), 1.0, _features(rng), N)
    solver.W_a[:] = rng.normal(size=solver.W_a.shape)
    solver.W_c[:] = rng.normal(size=solver.W_c.shape)
    W_a, W_c = solver.W_a.copy(), solver.W_c.copy()
    solver.shift()
    np.testing.assert_array_equal(solver.W_a, np.concatenate([W_a[1:], W_a[-1:]]))
    np.testing.assert_array_equal(solver.W_c, np.concatenate([W_c[1:], W_c[-1:]]))


def test_warm_start_after_shift_starts_near_the_solution():
    rng, A, B, Q, R = _system(1)
    P = sl.solve_discrete_are(A, B, Q, R)
    feats = _features(rng)
    c = 0.2 * rng.normal(size=(N + 1, n))
    x0 = rng.normal(size=n)
    warm = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=100, tol=1e-20)
    u, _ = warm.solve(_problem(A, B, Q, R, P, x0, c[:-1]), _barrier())
    warm.shift()
    second = _problem(A, B, Q, R, P, A @ x0 + B @ u[0] + c[0], c[1:])
    exact, _ = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=100, tol=1e-20).solve(second, _barrier())
    warm.i_max = 1
    cold = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=1)
    u_warm, _ = warm.solve(second, _barrier())
    u_cold, _ = cold.solve(second, _barrier())
    assert np.abs(u_warm[0] - exact[0]).max() < 0.2 * np.abs(u_cold[0] - exact[0]).max()


def test_shape_mismatch_is_an_error():
    rng, A, B, Q, R = _system(0)
    solver = EbRHRL(A, B, Q, R, Q, 1.0, _features(rng), N)
    prob = _problem(A, B, Q, R, Q, np.zeros(n))
    bad = HorizonProblem(**{**prob.__dict__, "A": prob.A[:-1], "B": prob.B[:-1], "c": prob.c[:-1],
                            "u_ref": prob.u_ref[:-1]})
    with pytest.raises(ValueError, match="does not match"):
        solver.solve(bad)


LOOP = ebrhrl_loop()
needs_numba = pytest.mark.skipif(LOOP is None, reason="numba is not installed")


def _two_barriers(rng) -> HorizonBarrier:
    """Two obstacles whose planes move along the horizon; the first lies close enough that part
    of the predictions are past PI_MIN (the tangent-line branch)."""
    T = N + 1
    ang = rng.uniform(0, 2 * np.pi, (2, T))
    normal = np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    x_p = np.stack([np.tile([0.2, 0.1], (T, 1)), np.tile([-0.8, 0.4], (T, 1))]) + 0.1 * rng.normal(size=(2, T, 2))
    return HorizonBarrier(pos_index=np.array([0, 2]), p_ref=0.1 * rng.normal(size=(T, 2)), x_p=x_p,
                          normal=normal, mu=np.array([3.0, 1.0]), length=0.5)


@needs_numba
@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_iterations_give_the_numpy_numbers(seed):
    """The same iterations, weights and diagnostics, to 1e-12, with time-varying A_tau, B_tau
    (a GP's Jacobians, close to the nominal pair so that the iterations converge: on a diverging
    solve any two summation orders part), an affine term, warm weights and zero, one or two barriers."""
    rng, A, B, Q, R = _system(seed)
    P = sl.solve_discrete_are(A, B, Q, R)
    feats = _features(rng)
    prob = _problem(A, B, Q, R, P, rng.normal(size=n), 0.1 * rng.normal(size=(N, n)))
    prob = HorizonProblem(**{**prob.__dict__, "A": prob.A + 0.002 * rng.normal(size=prob.A.shape),
                             "B": prob.B + 0.002 * rng.normal(size=prob.B.shape)})
    barrier = [None, _barrier(), _two_barriers(rng)][seed % 3]
    fast = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=15, tol=1e-30, loop=LOOP)
    slow = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=15, tol=1e-30)
    assert fast.compiled and not slow.compiled
    fast.W_a = slow.W_a = 0.02 * rng.normal(size=fast.W_a.shape)
    fast.W_a, fast.W_c = fast.W_a.copy(), 0.01 * rng.normal(size=fast.W_c.shape)
    slow.W_c = fast.W_c.copy()
    for _ in range(3):                                   # three ticks, shifted in between
        u_fast, i_fast = fast.solve(prob, barrier)
        u_slow, i_slow = slow.solve(prob, barrier)
        scale = max(1.0, np.abs(u_slow).max())
        assert np.abs(u_fast - u_slow).max() <= 1e-12 * scale
        for W in ("W_a", "W_c"):
            a, b = getattr(fast, W), getattr(slow, W)
            assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(b).max())
        assert i_fast.iterations == i_slow.iterations and i_fast.converged == i_slow.converged
        assert i_slow.eps_a < 1.0                         # a solve that converges, not one that diverges
        for eps in ("eps_a", "eps_c"):        # halves of squared residuals: rounding of 1e-12 in them squared
            assert abs(getattr(i_fast, eps) - getattr(i_slow, eps)) <= 1e-10 * max(1.0, getattr(i_slow, eps))
        fast.shift()
        slow.shift()


def _bounded_case(seed: int):
    """A problem whose unbounded plan leaves a box on u~ at some steps, and that box."""
    rng, A, B, Q, R = _system(seed)
    P = sl.solve_discrete_are(A, B, Q, R)
    prob = _problem(A, B, Q, R, P, 3.0 * rng.normal(size=n), 0.1 * rng.normal(size=(N, n)))
    free, _ = EbRHRL(A, B, Q, R, P, 1.0, _features(rng), N, i_max=50, tol=1e-20).solve(prob)
    half = 0.5 * np.abs(free).max(axis=0)
    return rng, A, B, Q, R, P, prob, free, (np.broadcast_to(-half, (N, n_u)), np.broadcast_to(half, (N, n_u)))


@pytest.mark.parametrize("seed", range(4))
def test_bounded_solves_keep_the_bounds_and_count_the_projected_steps(seed):
    rng, A, B, Q, R, P, prob, free, (lo, hi) = _bounded_case(seed)
    solver = EbRHRL(A, B, Q, R, P, 1.0, _features(rng), N, i_max=50, tol=1e-20)
    u, info = solver.solve(prob, bounds=(lo, hi))
    assert np.all(u >= lo) and np.all(u <= hi)
    outside = int(np.count_nonzero(np.any((free < lo) | (free > hi), axis=1)))
    assert outside > 0 and info.saturated > 0
    assert info.saturated == int(np.count_nonzero(np.any((u == lo) | (u == hi), axis=1)))


@pytest.mark.parametrize("compiled", [False, True])
def test_bounds_with_lo_above_hi_are_an_error(compiled):
    """Checked by the numpy path, and by the compiled loop before its first iteration (the weights
    untouched), for a single crossed bound too."""
    if compiled and LOOP is None:
        pytest.skip("numba is not installed")
    rng, A, B, Q, R = _system(0)
    P = sl.solve_discrete_are(A, B, Q, R)
    solver = EbRHRL(A, B, Q, R, P, 1.0, _features(rng), N, loop=LOOP if compiled else None)
    with pytest.raises(ValueError, match="lo > hi"):
        solver.solve(_problem(A, B, Q, R, P, np.ones(n)), bounds=(np.ones(n_u), np.zeros(n_u)))
    lo, hi = -np.ones((N, n_u)), np.ones((N, n_u))
    lo[N - 1, n_u - 1] = 2.0
    W_a = solver.W_a.copy()
    with pytest.raises(ValueError, match="lo > hi"):
        solver.solve(_problem(A, B, Q, R, P, np.ones(n)), bounds=(lo, hi))
    np.testing.assert_array_equal(solver.W_a, W_a)


@needs_numba
@pytest.mark.parametrize("seed", range(4))
def test_the_compiled_bounded_iterations_give_the_numpy_numbers(seed):
    rng, A, B, Q, R, P, prob, _, bounds = _bounded_case(seed)
    feats = _features(rng)
    barrier = [None, _barrier()][seed % 2]
    fast = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=15, tol=1e-30, loop=LOOP)
    slow = EbRHRL(A, B, Q, R, P, 1.0, feats, N, i_max=15, tol=1e-30)
    fast.W_a = 0.02 * rng.normal(size=fast.W_a.shape)
    slow.W_a = fast.W_a.copy()
    for _ in range(3):
        u_fast, i_fast = fast.solve(prob, barrier, bounds)
        u_slow, i_slow = slow.solve(prob, barrier, bounds)
        assert np.abs(u_fast - u_slow).max() <= 1e-12 * max(1.0, np.abs(u_slow).max())
        for W in ("W_a", "W_c"):
            a, b = getattr(fast, W), getattr(slow, W)
            assert np.abs(a - b).max() <= 1e-12 * max(1.0, np.abs(b).max())
        assert (i_fast.iterations, i_fast.saturated) == (i_slow.iterations, i_slow.saturated)
        assert i_slow.saturated > 0
        fast.shift()
        slow.shift()
