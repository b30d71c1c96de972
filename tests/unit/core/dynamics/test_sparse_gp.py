"""FITC sparse GP (paper eq. FITC) against the exact GP, finite differences and itself."""

import logging

import numpy as np
import pytest

from vflpcd.core.dynamics.sparse_gp import (FITCGP, GPConditioningError, SEHyper, exact_gp_predict,
                                            fit_hyperparameters, fitc_lml_single,
                                            log_marginal_likelihood, refit)


def data(n=60, seed=0, noise=0.05):
    rng = np.random.default_rng(seed)
    Z = rng.uniform(-2.0, 2.0, (n, 3))
    Y = np.column_stack([np.sin(Z[:, 0]) * np.cos(Z[:, 1]), 0.5 * np.tanh(Z[:, 2] + Z[:, 0]),
                         0.3 * Z[:, 1] ** 2 - 0.2])
    return Z, Y + noise * rng.standard_normal(Y.shape)


HYP = SEHyper([1.0, 0.4, 0.6], [1.2, 0.8, 1.5], [1e-2, 3e-3, 2e-2])


def test_fitc_with_all_points_inducing_equals_exact_gp():
    Z, Y = data(40)
    Zs = np.random.default_rng(1).uniform(-2.5, 2.5, (30, 3))
    me, ve = exact_gp_predict(Z, Y, Zs, HYP)
    mf, vf = FITCGP.fit(Z, Z, Y, HYP, jitter=1e-12, max_cond=1e16).predict(Zs)
    np.testing.assert_allclose(mf, me, rtol=0, atol=1e-8)
    np.testing.assert_allclose(vf, ve, rtol=0, atol=1e-8)


def test_point_mean_matches_batch_prediction():
    Z, Y = data()
    gp = FITCGP.fit(Z[:20], Z, Y, HYP)
    Zs = np.random.default_rng(2).uniform(-2, 2, (5, 3))
    mb, _ = gp.predict(Zs)
    for i, z in enumerate(Zs):
        np.testing.assert_allclose(gp.mean(z), mb[i], atol=1e-12)
        np.testing.assert_allclose(gp.mean_jacobian(z)[0], mb[i], atol=1e-12)


def test_mean_jacobian_matches_central_differences():
    Z, Y = data()
    gp = FITCGP.fit(Z[::3], Z, Y, HYP)
    h = 1e-5
    for z in np.random.default_rng(3).uniform(-2, 2, (5, 3)):
        _, J = gp.mean_jacobian(z)
        Jfd = np.column_stack([(gp.mean(z + h * e) - gp.mean(z - h * e)) / (2 * h) for e in np.eye(3)])
        assert np.linalg.norm(J - Jfd) / np.linalg.norm(Jfd) < 1e-5


def test_add_sample_matches_batch_fit():
    Z, Y = data(80)
    Zm, Zs = Z[:16], np.random.default_rng(4).uniform(-2, 2, (20, 3))
    inc = FITCGP.fit(Zm, Z[:30], Y[:30], HYP)
    for z, y in zip(Z[30:], Y[30:]):
        inc = inc.add_sample(z, y)
    full = FITCGP.fit(Zm, Z, Y, HYP)
    assert inc.n == full.n == 80
    for a, b in zip(inc.predict(Zs), full.predict(Zs)):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-8)
    # from an empty training set, too
    inc0 = FITCGP.fit(Zm, Z[:0], Y[:0], HYP)
    for z, y in zip(Z, Y):
        inc0 = inc0.add_sample(z, y)
    np.testing.assert_allclose(inc0.alpha, full.alpha, rtol=0, atol=1e-8)


def test_model_is_immutable():
    Z, Y = data()
    gp = FITCGP.fit(Z[:10], Z, Y, HYP)
    before = gp.alpha.copy()
    gp2 = gp.add_sample(Z[0] + 0.1, Y[0])
    assert gp2 is not gp and np.array_equal(gp.alpha, before)
    with pytest.raises(ValueError):
        gp.alpha[0, 0] = 1.0
    with pytest.raises(AttributeError):
        gp.n = 3
    with pytest.raises(ValueError):
        gp.add_sample(np.array([np.nan, 0, 0]), Y[0])


def test_lml_gradient_matches_finite_differences():
    Z, Y = data(50)
    Zm = Z[:12]
    for a, theta in enumerate([np.log([0.7, 0.9, 0.02]), np.log([0.3, 1.7, 0.005]), np.log([2.0, 0.5, 0.1])]):
        _, g = fitc_lml_single(Zm, Z, Y[:, a], theta)
        h = 1e-6
        gfd = np.array([(fitc_lml_single(Zm, Z, Y[:, a], theta + h * e)[0]
                         - fitc_lml_single(Zm, Z, Y[:, a], theta - h * e)[0]) / (2 * h) for e in np.eye(3)])
        np.testing.assert_allclose(g, gfd, rtol=1e-5, atol=1e-6)


def test_lml_matches_dense_formula():
    Z, Y = data(30)
    Zm, (sf2, ell, sn2) = Z[:8], (0.8, 1.1, 0.01)
    theta = np.log([sf2, ell, sn2])
    K = lambda A, B: sf2 * np.exp(-0.5 * ((A[:, None] - B[None]) ** 2).sum(-1) / ell**2)
    Q = K(Z, Zm) @ np.linalg.solve(K(Zm, Zm) + 1e-8 * sf2 * np.eye(8), K(Zm, Z))
    C = Q + np.diag(sf2 - np.diag(Q) + sn2)
    y = Y[:, 0]
    ref = -0.5 * y @ np.linalg.solve(C, y) - 0.5 * np.linalg.slogdet(C)[1] - 15 * np.log(2 * np.pi)
    assert fitc_lml_single(Zm, Z, y, theta)[0] == pytest.approx(ref, rel=1e-10)


def test_hyperparameter_fit_raises_lml():
    Z, Y = data(120, noise=0.05)
    Zm = Z[:20]
    hyp0 = SEHyper([5.0, 5.0, 5.0], [0.2, 0.2, 0.2], [1.0, 1.0, 1.0])
    before = log_marginal_likelihood(Zm, Z, Y, hyp0)
    hyp = fit_hyperparameters(Zm, Z, Y, hyp0)
    after = log_marginal_likelihood(Zm, Z, Y, hyp)
    assert after > before + 50.0
    assert np.all(hyp.sn2 < 0.1)          # the noise (0.05^2) is found, roughly


def test_refit_returns_new_model_and_keeps_previous_on_nan(caplog):
    Z, Y = data(100)
    good = refit(None, Z[:16], Z, Y, HYP)
    assert isinstance(good, FITCGP) and good.n == 100
    Ybad = Y.copy()
    Ybad[7, 1] = np.nan
    with caplog.at_level(logging.WARNING, logger="vflpcd.core.dynamics.sparse_gp"):
        kept = refit(good, Z[:16], Z, Ybad)
    assert kept is good
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "event=gp_refit_rejected" in lines[0] and "kept=previous" in lines[0]


def test_ill_conditioned_refit_keeps_last_good_gp(caplog):
    Z, Y = data(100)
    good = refit(None, Z[:16], Z, Y, HYP)
    Zdup = np.repeat(Z[:20], 5, axis=0)                      # every input five times
    Ydup = np.repeat(Y[:20], 5, axis=0)
    Zm = Zdup[:20]                                           # 4 distinct inducing inputs, each 5 times
    tiny = ((np.log(1e-6), np.log(1e2)), (np.log(1e-2), np.log(1e2)), (np.log(1e-14), np.log(1e-13)))
    hyp = SEHyper.from_log(np.tile([0.0, 0.0, np.log(1e-14)], (3, 1)))
    with pytest.raises(GPConditioningError, match="cond"):
        FITCGP.fit(Zm, Zdup, Ydup, hyp, jitter=1e-13)
    with caplog.at_level(logging.WARNING, logger="vflpcd.core.dynamics.sparse_gp"):
        kept = refit(good, Zm, Zdup, Ydup, bounds=tiny, jitter=1e-13)
    assert kept is good
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1 and "event=gp_refit_rejected reason=cond_" in lines[0]
    np.testing.assert_array_equal(kept.predict(Z[:5])[0], good.predict(Z[:5])[0])
    # the same data with distinct inducing inputs and the default jitter is accepted
    assert isinstance(refit(good, Zdup[::5], Zdup, Ydup, bounds=tiny), FITCGP)
