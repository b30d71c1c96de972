"""The online GP's loops compiled and run as Python against their numpy paths, to 1e-12: the
per-sample update (``add_sample_loop`` against ``FITCGP.add_sample``) over a run of samples, the
horizon's correction by the GP's mean (``corrected_next_loop`` against
``KoopmanCompensation.corrected_next``) and the dictionary's test (``ald_delta_loop`` against
``ALDDictionary.delta``, through a run of admissions and replacements), on two and thirty
inducing inputs."""

import numpy as np
import pytest

from vflpcd.core.dynamics.ald import ALDDictionary
from vflpcd.core.dynamics.compensation import KoopmanCompensation
from vflpcd.core.dynamics.gp_kernel import add_sample_loop, ald_delta_loop, corrected_next_loop
from vflpcd.core.dynamics.sparse_gp import FITCGP, SEHyper


def _runs(loop, m: int, seed: int):
    rng = np.random.default_rng(seed)
    Z, Y = rng.normal(size=(80, 8)), rng.normal(size=(80, 5)) * 0.1
    hyp = SEHyper(sf2=np.linspace(0.03, 0.07, 5), ell=np.linspace(2.0, 4.0, 5), sn2=np.full(5, 1e-4))
    plain = fast = FITCGP.fit(Z[:m], Z, Y, hyp)
    for _ in range(40):
        z, y = rng.normal(size=8), rng.normal(size=5) * 0.1
        plain, fast = plain.add_sample(z, y), fast.add_sample(z, y, loop)
    return plain, fast


@pytest.mark.parametrize("m", [2, 30])
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_loop_gives_the_numpy_posterior(m, run):
    if run == "compiled":
        from vflpcd.controllers.loops import gp_add_loop

        loop = gp_add_loop()
        if loop is None:
            pytest.skip("numba is not installed")
    else:
        loop = add_sample_loop
    plain, fast = _runs(loop, m, 3)
    assert fast.n == plain.n == 120
    for field in ("Ainv", "c", "alpha"):
        np.testing.assert_allclose(getattr(fast, field), getattr(plain, field), rtol=1e-12, atol=1e-12)
    zs = np.random.default_rng(4).normal(size=(6, 8))
    np.testing.assert_allclose(fast.means(zs), plain.means(zs), rtol=1e-12, atol=1e-12)


def _compiled(name: str):
    from vflpcd.controllers import loops

    found = loops.tick_loops() if name == "correction" else loops.ald_loop()
    if found is None:
        pytest.skip("numba is not installed")
    return found.correction if name == "correction" else found


@pytest.mark.parametrize("m", [2, 30])
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_correction_loop_gives_the_numpy_next_states(m, run):
    loop = _compiled("correction") if run == "compiled" else corrected_next_loop
    rng = np.random.default_rng(5)
    n_K, n_u, N = 9, 2, 20
    z_index = [2, 3, 4, 5, 6, 7]                                # z = [U[z_index], u]: the 8 inputs of _runs' GP
    B_d = np.zeros((n_K, 5))
    B_d[[2, 3, 4, 5, 6], range(5)] = 1.0
    comp = KoopmanCompensation(np.eye(n_K), np.ones((n_K, n_u)), B_d, z_index)
    gp = _runs(add_sample_loop, m, 6)[0]
    for _ in range(5):
        U, u = rng.normal(size=(N + 1, n_K)), rng.normal(size=(N, n_u))
        nxt = U[:-1] @ comp.A.T + u @ comp.B.T
        plain = comp.corrected_next(nxt, U[:-1], u, gp)
        fast = comp.corrected_next(nxt, U[:-1], u, gp, loop)
        np.testing.assert_allclose(fast, plain, rtol=1e-12, atol=1e-12)
        assert not np.allclose(plain, nxt)                      # the GP's mean is in it


@pytest.mark.parametrize("m_max", [2, 30])
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_ald_loop_gives_the_numpy_dictionary(m_max, run):
    loop = _compiled("ald") if run == "compiled" else ald_delta_loop
    rng = np.random.default_rng(8)
    plain, fast = ALDDictionary(4, 0.05, m_max, 1.0, 1.5), ALDDictionary(4, 0.05, m_max, 1.0, 1.5, delta_loop=loop)
    for i in range(200):
        z = rng.normal(size=4) * (0.3 if i % 3 else 2.0)
        assert fast.delta(z) == pytest.approx(plain.delta(z), rel=1e-12, abs=1e-12)
        assert fast.consider(z, tag=i) == plain.consider(z, tag=i)
    assert plain.n_admitted > m_max and plain.n_rejected_dependent > 0    # full, replacing, and rejecting
    np.testing.assert_array_equal(fast.tags, plain.tags)
    np.testing.assert_allclose(fast.points, plain.points, rtol=0, atol=0)


@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_loops_are_not_handed_shapes_they_would_read_past(run):
    """The loops do not check their indices; the methods that call them refuse a GP, a horizon or a
    sample of the wrong size with a ValueError (the numpy paths raise numpy's shape errors)."""
    correction = _compiled("correction") if run == "compiled" else corrected_next_loop
    ald_loop = _compiled("ald") if run == "compiled" else ald_delta_loop
    n_K, n_u, N = 9, 2, 4
    B_d = np.zeros((n_K, 5))
    B_d[[2, 3, 4, 5, 6], range(5)] = 1.0
    comp = KoopmanCompensation(np.eye(n_K), np.ones((n_K, n_u)), B_d, [2, 3, 4, 5, 6, 7])
    gp = _runs(add_sample_loop, 2, 6)[0]
    U, u = np.zeros((N, n_K)), np.zeros((N, n_u))
    with pytest.raises(ValueError, match="expected nxt and U"):
        comp.corrected_next(U, U, np.zeros((N, n_u + 1)), gp, correction)
    with pytest.raises(ValueError):
        comp.corrected_next(U, U, np.zeros((N, n_u + 1)), gp)
    narrow = KoopmanCompensation(np.eye(n_K), np.ones((n_K, n_u)), B_d, [2, 3, 4])
    with pytest.raises(ValueError, match="cannot correct"):
        narrow.corrected_next(U, U, u, gp, correction)
    ald = ALDDictionary(4, 0.05, 8, delta_loop=ald_loop)
    ald.consider(np.zeros(4))
    with pytest.raises(ValueError, match="expected z of 4"):
        ald.delta(np.zeros(6))
