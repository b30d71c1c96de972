"""Koopman model-error compensation (paper eqs. error_model, Dynamics_for_planning, JocabianMatrices)."""

import logging

import numpy as np

from vflpcd.core.dynamics.compensation import KoopmanCompensation, OnlineCompensator
from vflpcd.core.dynamics.sparse_gp import FITCGP, SEHyper

N_K, N_U = 7, 2
Z_INDEX = [3, 4, 5]


def system(seed=0):
    rng = np.random.default_rng(seed)
    A = 0.9 * np.eye(N_K) + 0.05 * rng.standard_normal((N_K, N_K))
    B = 0.3 * rng.standard_normal((N_K, N_U))
    B_d = np.zeros((N_K, 3))
    B_d[3:6] = np.eye(3)                                    # [0_3 I_3 0]^T as in the paper
    return KoopmanCompensation(A, B, B_d, Z_INDEX)


def g(z):
    """Smooth nonlinear model error, z (N, 5) -> (N, 3)."""
    return np.column_stack([0.4 * np.sin(z[:, 0]) * np.cos(z[:, 3]),
                            0.3 * np.tanh(z[:, 1] + z[:, 4]),
                            0.2 * z[:, 2] ** 2 - 0.1])


def samples(comp, n, seed):
    rng = np.random.default_rng(seed)
    U = rng.uniform(-1.5, 1.5, (n, N_K))
    u = rng.uniform(-1.0, 1.0, (n, N_U))
    U_next = comp.nominal(U, u) + g(comp.gp_input(U, u)) @ comp.B_d.T
    return U, u, U_next + 1e-3 * rng.standard_normal(U_next.shape)


HYP0 = SEHyper([0.1] * 3, [1.0] * 3, [1e-4] * 3)


def trained(comp, n=300):
    oc = OnlineCompensator(comp, HYP0, nu=0.05, m_max=64, n_max=n)
    for U, u, Un in zip(*samples(comp, n, 1)):
        assert oc.observe(U, u, Un)
    assert oc.model is None
    assert isinstance(oc.refit(), FITCGP)
    return oc


def test_residual_target_recovers_g_and_drops_nonfinite():
    comp = system()
    U, u, Un = samples(comp, 20, 3)
    Un[4, 0] = np.nan
    u[7, 1] = np.inf
    pairs = comp.residual_target(U, u, Un)
    assert pairs.dropped == 2 and pairs.z.shape == (18, 5) and not pairs.keep[4] and not pairs.keep[7]
    np.testing.assert_allclose(pairs.d, g(comp.gp_input(U, u))[pairs.keep], atol=1e-2)


def test_compensation_halves_one_step_error_on_held_out_samples():
    comp = system()
    oc = trained(comp)
    U, u, Un = samples(comp, 200, 2)
    err_nom = np.linalg.norm(comp.predict(U, u, None) - Un, axis=1).mean()
    err_gp = np.linalg.norm(comp.predict(U, u, oc.model) - Un, axis=1).mean()
    assert err_gp < 0.5 * err_nom
    # one sample at a time gives the same as the batch
    np.testing.assert_allclose(comp.predict(U[0], u[0], oc.model), comp.predict(U, u, oc.model)[0], atol=1e-12)


def test_jacobians_match_finite_differences_of_predict():
    comp = system()
    gp = trained(comp, 150).model
    rng = np.random.default_rng(5)
    # h = 1e-4: the fitted third output (a quadratic) has a long length scale and large
    # cancelling alpha terms, so the mean carries ~1e-10 of round-off.
    U, u, h = rng.uniform(-1, 1, N_K), rng.uniform(-1, 1, N_U), 1e-4
    A_d, B_dk = comp.jacobians(U, u, gp)
    A_fd = np.column_stack([(comp.predict(U + h * e, u, gp) - comp.predict(U - h * e, u, gp)) / (2 * h)
                            for e in np.eye(N_K)])
    B_fd = np.column_stack([(comp.predict(U, u + h * e, gp) - comp.predict(U, u - h * e, gp)) / (2 * h)
                            for e in np.eye(N_U)])
    np.testing.assert_allclose(A_d, A_fd, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(B_dk, B_fd, rtol=1e-5, atol=1e-7)
    assert not np.allclose(A_d, comp.A) and not np.allclose(B_dk, comp.B)   # the GP does contribute
    A0, B0 = comp.jacobians(U, u, None)
    assert np.array_equal(A0, comp.A) and np.array_equal(B0, comp.B)


def test_nonfinite_observations_are_dropped_counted_and_never_reach_the_gp():
    comp = system()
    oc = trained(comp, 100)
    gp, n_buf = oc.model, oc.n_buffered
    U, u, Un = samples(comp, 3, 9)
    assert not oc.observe(U[0], u[0], np.full(N_K, np.nan))
    assert not oc.observe(np.r_[U[1][:-1], np.inf], u[1], Un[1])
    assert oc.dropped == 2 and oc.model is gp and oc.model.n == 100 and oc.n_buffered == n_buf
    assert oc.dictionary.n_rejected_nonfinite == 0           # stopped before the dictionary
    assert oc.observe(U[2], u[2], Un[2])
    assert oc.model is not gp and oc.model.n == 101          # a finite sample is folded in (add_sample)


def test_failed_refit_keeps_last_good_model(caplog):
    comp = system()
    oc = trained(comp, 100)
    good = oc.model
    oc._refit_kw["max_cond"] = 1.0                           # force every conditioning check to fail
    with caplog.at_level(logging.WARNING, logger="vflpcd.core.dynamics.sparse_gp"):
        assert oc.refit() is good
    assert oc.model is good
    assert sum("event=gp_refit_rejected" in r.getMessage() for r in caplog.records) == 1
