"""The online GP's per-sample update compiled (``gp_kernel.add_sample_loop``) against
``FITCGP.add_sample``'s numpy path: the same posterior to 1e-12 over a run of samples, on a
dictionary of two and of thirty inducing inputs."""

import numpy as np
import pytest

from vflpcd.core.dynamics.gp_kernel import add_sample_loop
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
