"""The increment (rate-aware) form of the horizon problem, and Eb-RHRL on it."""

import numpy as np
import pytest
import scipy.linalg as sl

from vflpcd.core.control.ebrhrl import EbRHRL, KernelFeatures
from vflpcd.core.control.problem import HorizonProblem, finite_horizon_lqr
from vflpcd.core.control.rate import RateForm

N, n, n_u = 12, 4, 2


def _problem(rng) -> HorizonProblem:
    A = np.eye(n) + 0.1 * rng.normal(size=(N, n, n))
    B = 0.2 * rng.normal(size=(N, n, n_u))
    inf = np.full(n_u, np.inf)
    return HorizonProblem(A=A, B=B, c=0.05 * rng.normal(size=(N, n)), x0=rng.normal(size=n),
                          Q=np.diag(rng.uniform(0.5, 2.0, n)), R=np.diag([0.3, 0.7]), P=np.eye(n), gamma=0.95,
                          u_ref=rng.normal(size=(N, n_u)), u_min=-inf, u_max=inf, du_max=inf,
                          u_prev=rng.normal(size=n_u), G=np.zeros((N + 1, 1, n)), g=np.zeros((N + 1, 1)))


def test_the_increment_form_predicts_what_the_original_does():
    rng = np.random.default_rng(0)
    p = _problem(rng)
    rf = RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma)
    z = rf.problem(p)
    v = rng.normal(size=(N, n_u))
    u_tilde = (p.u_prev - p.u_ref[0]) + np.cumsum(v, axis=0)     # u~_tau = u~_{-1} + v_0 + .. + v_tau
    x = p.rollout(u_tilde)
    xz = z.rollout(v)
    np.testing.assert_allclose(xz[:, :n], x, atol=1e-12)
    np.testing.assert_allclose(xz[1:, n:], u_tilde, atol=1e-12)
    np.testing.assert_allclose(rf.deviation(z.x0, v[0]), u_tilde[0])
    # stage cost: x~' Q x~ + u~_{tau-1}' R u~_{tau-1} + v' R_rate v
    prev = np.vstack([p.u_prev - p.u_ref[0], u_tilde[:-1]])
    stages = (np.einsum("ti,ij,tj->t", x[:-1], p.Q, x[:-1]) + np.einsum("ti,ij,tj->t", prev, p.R, prev)
              + np.einsum("ti,ij,tj->t", v, rf.R, v))
    terminal = xz[-1] @ rf.P @ xz[-1]
    assert np.isclose(z.cost(v), np.sum(p.gamma ** np.arange(N) * stages) + p.gamma ** N * terminal)
    assert z.G.shape == (N + 1, 1, n + n_u) and np.all(z.G[..., n:] == 0.0)


def test_a_command_increment_is_the_command_s_own_change_reference_steps_included():
    """Input 0 in ``command``: its v is u_tau - u_{tau-1} (u_{-1} = u_prev), so the same commands
    predict the same errors as the original problem, and R_rate weighs the command's own steps."""
    rng = np.random.default_rng(2)
    p = _problem(rng)
    rf = RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma, command=np.array([True, False]))
    z = rf.problem(p)
    u = rng.normal(size=(N, n_u))                                 # the commands applied
    u_tilde = u - p.u_ref
    v = np.empty((N, n_u))
    v[:, 0] = np.diff(np.concatenate([[p.u_prev[0]], u[:, 0]]))  # the command's own increments
    v[:, 1] = np.diff(np.concatenate([[p.u_prev[1] - p.u_ref[0, 1]], u_tilde[:, 1]]))   # the deviation's
    xz = z.rollout(v)
    np.testing.assert_allclose(xz[:, :n], p.rollout(u_tilde), atol=1e-12)
    np.testing.assert_allclose(xz[1:, n:], u_tilde, atol=1e-12)
    np.testing.assert_allclose(rf.deviation(z.x0, v[0]), u_tilde[0])
    # following the reference control exactly costs the command's steps of input 0, none of input 1
    follow = np.zeros((N, n_u))
    follow[0] = p.u_ref[0] - p.u_prev
    follow[1:, 0] = np.diff(p.u_ref[:, 0])
    np.testing.assert_allclose(z.rollout(follow)[1:, n:], 0.0, atol=1e-12)
    plain = RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma).problem(p)
    np.testing.assert_allclose(plain.c[:, n:], 0.0)
    assert not np.allclose(z.c, plain.c)


def test_a_command_flag_per_input_is_asked_for():
    rng = np.random.default_rng(3)
    p = _problem(rng)
    with pytest.raises(ValueError, match="one per input"):
        RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma, command=np.array([True]))


def test_eb_rhrl_on_the_increment_form_is_its_finite_horizon_lqr():
    rng = np.random.default_rng(1)
    A = np.eye(n) + 0.1 * rng.normal(size=(n, n))
    B = 0.2 * rng.normal(size=(n, n_u))
    Q, R = np.diag(rng.uniform(0.5, 2.0, n)), np.diag([0.3, 0.7])
    rf = RateForm.of(A, B, Q, R, np.diag([2.0, 20.0]), 1.0)
    assert np.allclose(rf.P, sl.solve_discrete_are(rf.A, rf.B, rf.Q, rf.R))
    feats = KernelFeatures.from_samples(rng.normal(size=(300, n + n_u)), np.full(n + n_u, 5.0), 0.05, 16)
    solver = EbRHRL(rf.A, rf.B, rf.Q, rf.R, rf.P, 1.0, feats, N, i_max=200, tol=1e-20)
    inf = np.full(n_u, np.inf)
    p = HorizonProblem(A=np.repeat(A[None], N, 0), B=np.repeat(B[None], N, 0), c=np.zeros((N, n)),
                       x0=rng.normal(size=n), Q=Q, R=R, P=Q, gamma=1.0, u_ref=np.zeros((N, n_u)), u_min=-inf,
                       u_max=inf, du_max=inf, u_prev=np.array([0.4, -0.2]), G=np.zeros((N + 1, 0, n)),
                       g=np.zeros((N + 1, 0)))
    z = rf.problem(p)
    v, info = solver.solve(z)
    v_lqr = -finite_horizon_lqr(rf.A, rf.B, rf.Q, rf.R, rf.P, N, 1.0)[0] @ z.x0
    assert np.linalg.norm(v[0] - v_lqr) / np.linalg.norm(v_lqr) < 1e-3
    assert info.converged


@pytest.mark.parametrize("command", [(False, False), (True, False), (True, True)])
def test_the_increment_bounds_keep_the_command_within_its_rate_limit(command):
    """Increments at the bounds move the command u = u_r + u~ by exactly -du_max / +du_max at every
    step (u_{-1} = u_prev), whichever inputs are the command's own increments; an input without a
    limit is open."""
    rng = np.random.default_rng(4)
    p = _problem(rng)
    du = np.array([0.3, np.inf])
    p = HorizonProblem(**{**p.__dict__, "du_max": du})
    rf = RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma, command=np.array(command))
    z, (lo, hi) = rf.increments(p)
    assert np.all(np.isinf(lo[:, 1])) and np.all(np.isinf(hi[:, 1]))
    for v0, sign in ((lo[:, 0], -1.0), (hi[:, 0], 1.0)):
        v = np.zeros((N, n_u))
        v[:, 0] = v0
        u = p.u_ref + z.rollout(v)[1:, n:]
        np.testing.assert_allclose(np.diff(np.concatenate([[p.u_prev[0]], u[:, 0]])), sign * du[0], atol=1e-12)


def test_the_compiled_increment_fill_is_the_numpy_one_and_allocates_no_problem():
    """``rate_kernel.increment_loop`` compiled gives ``RateForm.increments``' numpy fill (c, x0 and the
    bounds) to 1e-12, on a view of the error model's c and a broadcast B as the tick passes them; the
    increment problem is the same object at the next tick while A, B and the (absent) half-planes
    are the same arrays."""
    from vflpcd.controllers.loops import tick_loops

    loops = tick_loops()
    if loops is None:
        pytest.skip("numba is not installed")
    rng = np.random.default_rng(5)
    for command in ((False, False), (True, False), (False, True)):
        p = _problem(rng)
        wide = np.zeros((N, n + 1))
        wide[:, :n] = p.c
        B = np.broadcast_to(p.B[0], (N, n, n_u))
        p = HorizonProblem(**{**p.__dict__, "c": wide[:, :n], "B": B, "A": np.broadcast_to(p.A[0], (N, n, n)),
                              "du_max": np.array([0.2, np.inf]), "G": np.zeros((N + 1, 0, n)),
                              "g": np.zeros((N + 1, 0))})
        forms = [RateForm.of(p.A[0], p.B[0], p.Q, p.R, np.diag([1.0, 50.0]), p.gamma, command=np.array(command),
                             loop=loop) for loop in (None, loops.increment)]
        (zn, bn), (zc, bc) = (f.increments(p) for f in forms)
        for a, b in ((zn.c, zc.c), (zn.x0, zc.x0), (bn[0], bc[0]), (bn[1], bc[1])):
            np.testing.assert_allclose(b, a, rtol=0, atol=1e-12)
        assert not np.allclose(zc.c[1:], zc.c[1:] * 0)
        again = HorizonProblem(**{**p.__dict__, "x0": p.x0 + 1.0})
        z2, _ = forms[1].increments(again)
        assert z2 is zc and np.allclose(zc.x0[:n], p.x0 + 1.0)
