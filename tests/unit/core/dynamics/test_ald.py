"""ALD dictionary (Engel et al. 2004): admission test, size cap, replacement, inverse update."""

import numpy as np

from vflpcd.core.dynamics.ald import ALDDictionary, sparsify
from vflpcd.core.dynamics.sparse_gp import se_kernel


def test_near_duplicate_rejected_far_point_admitted():
    ald = ALDDictionary(2, nu=1e-3, m_max=10, ell=0.5)
    assert ald.consider(np.array([0.0, 0.0]))
    assert ald.consider(np.array([1.0, 0.0]))
    assert not ald.consider(np.array([1.0, 1e-6]))          # 1e-6 from a dictionary point
    assert ald.n_rejected_dependent == 1
    assert ald.consider(np.array([5.0, 5.0]))              # far away: delta ~ sf2
    assert ald.m == 3


def test_delta_matches_direct_formula_and_inverse_stays_exact():
    rng = np.random.default_rng(0)
    ald = ALDDictionary(3, nu=1e-2, m_max=12, ell=0.7)
    for z in rng.uniform(-2, 2, (200, 3)):
        ald.consider(z)
    D = ald.points
    assert ald.m == 12 and ald.n_replaced > 0
    K = se_kernel(D, D, 1.0, 0.7)
    np.testing.assert_allclose(ald._P, np.linalg.inv(K), atol=1e-8 * np.abs(np.linalg.inv(K)).max())
    z = rng.uniform(-2, 2, 3)
    k = se_kernel(D, z[None], 1.0, 0.7)[:, 0]
    assert abs(ald.delta(z) - (1.0 - k @ np.linalg.solve(K, k))) < 1e-10


def test_cap_is_respected_and_full_dictionary_replaces_most_redundant():
    rng = np.random.default_rng(1)
    ald = ALDDictionary(2, nu=1e-3, m_max=5, ell=1.0)
    for z in rng.uniform(-0.3, 0.3, (5, 2)):                # a tight cluster fills it
        ald.consider(z)
    assert ald.m == 5
    for z in rng.uniform(-0.3, 0.3, (50, 2)):
        ald.consider(z)
        assert ald.m <= 5
    far = np.array([10.0, 10.0])
    assert ald.consider(far)                                # more novel than any cluster point
    assert ald.m == 5 and any(np.allclose(p, far) for p in ald.points)
    n_rep = ald.n_replaced
    assert not ald.consider(np.array([10.0, 10.0 + 1e-6]))  # near-duplicate of the new point
    assert ald.n_replaced == n_rep


def test_nonfinite_candidates_rejected_and_counted():
    ald = ALDDictionary(2, nu=1e-3, m_max=5)
    assert not ald.consider(np.array([np.nan, 0.0]))
    assert not ald.consider(np.array([np.inf, 0.0]))
    assert ald.m == 0 and ald.n_rejected_nonfinite == 2


def test_sparsify_returns_kept_indices():
    rng = np.random.default_rng(2)
    base = rng.uniform(-3, 3, (8, 2))
    Z = np.vstack([base, base + 1e-7, base[:3] + 1e-7])     # 8 distinct points + duplicates
    Y = np.zeros((Z.shape[0], 1))
    Y[0] = np.nan                                           # first sample unusable
    idx = sparsify(Z, Y, nu=1e-3, m_max=20, ell=0.5)
    assert idx.dtype.kind == "i" and np.all(np.diff(idx) > 0)
    assert len(idx) == 8 and 0 not in idx and 8 in idx     # index 8 stands in for index 0
    assert len(sparsify(Z, None, nu=1e-3, m_max=4, ell=0.5)) == 4
