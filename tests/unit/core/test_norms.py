"""The tick's norms give np.linalg.norm's numbers to the last bit."""

import numpy as np
import pytest

from vflpcd.core.norms import row_norms, vector_norm


@pytest.mark.parametrize("d", [1, 2, 3, 6, 17])
def test_norms_are_np_linalg_norms(d):
    rng = np.random.default_rng(d)
    for scale in (1e-150, 1e-3, 1.0, 1e3, 1e150):
        x = rng.normal(size=(40, d)) * scale
        assert np.array_equal(row_norms(x), np.linalg.norm(x, axis=1))
        assert np.array_equal(row_norms(x, keepdims=True), np.linalg.norm(x, axis=-1, keepdims=True))
        assert all(vector_norm(v) == np.linalg.norm(v) for v in x)
    assert np.isnan(vector_norm(np.array([np.nan, 1.0]))) and vector_norm(np.array([np.inf, 1.0])) == np.inf
