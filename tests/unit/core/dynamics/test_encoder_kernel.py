"""The encoder's arithmetic (``encoder_kernel``): its tanh against the correctly rounded float32 tanh,
its loop against its numpy layers bit for bit (compiled and run as Python), and both against the
MLP in float64."""

import numpy as np
import pytest

from vflpcd.core.dynamics.encoder_kernel import (TANH_CLAMP, TANH_Q, encoder_layers, encoder_loop,
                                                 encoder_tanh)


def _ulps(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Units in the last place between float32 arrays of one sign pattern (the int32 views' distance)."""
    return np.abs(a.view(np.int32).astype(np.int64) - b.view(np.int32).astype(np.int64))


def test_tanh_is_within_an_ulp_of_the_correctly_rounded_one():
    x = np.concatenate([np.linspace(-12.0, 12.0, 1_000_001), np.logspace(-38, 1.2, 20_001),
                        -np.logspace(-38, 1.2, 20_001), [0.0, TANH_CLAMP, -TANH_CLAMP, 1e30, -1e30]]).astype(np.float32)
    exact = np.tanh(x.astype(np.float64)).astype(np.float32)      # float64 tanh, rounded once
    got = encoder_tanh(x)
    assert got.dtype == np.float32
    assert _ulps(got, exact).max() <= 1
    assert np.mean(got != exact) < 0.15
    np.testing.assert_array_equal(encoder_tanh(-x), -got)                 # odd
    assert np.all(np.abs(got) <= 1.0)
    z = np.linspace(0.0, TANH_CLAMP ** 2, 100_001)
    q = np.polynomial.polynomial.polyval(z, TANH_Q)
    assert q.min() > 0.5                                                  # no pole on the clamped range
    assert np.isnan(encoder_tanh(np.array([np.nan], np.float32))[0])


def _encoder(rng, widths):
    W = [(rng.normal(size=(a, b)) / np.sqrt(a)).astype(np.float32) for a, b in zip(widths[:-1], widths[1:])]
    b = [rng.normal(size=w.shape[1]).astype(np.float32) * 0.5 for w in W]
    return W, b


def _loop_lift(loop, h, W, b, first=2):
    widths = [h.shape[1]] + [w.shape[1] for w in W]
    U = np.full((len(h), first + widths[-1] + 1), np.nan)
    loop(h, np.concatenate([w.ravel() for w in W]), np.concatenate(b), np.array(widths, np.int64),
         np.empty((2, len(h), max(widths)), np.float32), U, first)
    return U[:, first: first + widths[-1]]


@pytest.fixture(scope="module")
def compiled_loop():
    numba = pytest.importorskip("numba")
    from vflpcd.controllers.loops import tick_loops

    assert tick_loops() is not None             # registers what the loop calls
    return numba.njit(error_model="numpy")(encoder_loop)


@pytest.mark.parametrize("widths", [(6, 3), (6, 64, 3), (6, 64, 64, 3), (9, 32, 48, 16, 5)])
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_loop_gives_the_numpy_layers_bit_for_bit(compiled_loop, widths, run):
    rng = np.random.default_rng(len(widths))
    W, b = _encoder(rng, widths)
    rows = 21 if run == "compiled" else 3
    h = (rng.normal(size=(rows, widths[0])) * 2.0).astype(np.float32)
    h[0, 0] = 40.0                                   # a pre-activation beyond the tanh's clamp
    want = encoder_layers(h, W, b).astype(np.float64)
    got = _loop_lift(compiled_loop if run == "compiled" else encoder_loop, h, W, b)
    np.testing.assert_array_equal(got, want)


def test_the_numpy_layers_are_the_mlp_and_do_not_depend_on_the_batch():
    """Against the MLP in float64 (np.tanh, matrix products) to float32's precision; a row's numbers do
    not depend on the batch it is lifted in, nor on the batch's leading shape."""
    rng = np.random.default_rng(3)
    W, b = _encoder(rng, (6, 64, 64, 3))
    h = rng.normal(size=(3000, 6)).astype(np.float32)
    got = encoder_layers(h, W, b)
    ref = h.astype(np.float64)
    for i, (w, c) in enumerate(zip(W, b)):
        ref = ref @ w.astype(np.float64) + c
        ref = np.tanh(ref) if i < len(W) - 1 else ref
    np.testing.assert_allclose(got, ref, rtol=0, atol=2e-5)
    np.testing.assert_array_equal(encoder_layers(h[-5:], W, b), got[-5:])
    np.testing.assert_array_equal(encoder_layers(h[:40].reshape(4, 10, 6), W, b), got[:40].reshape(4, 10, 3))


@pytest.mark.parametrize("name", ["dynamic_bicycle", "quadrotor"])
def test_a_model_with_the_compiled_encoder_lifts_the_same_bits(compiled_loop, name):
    """``KoopmanModel.compile_encoder``: the shipped models' lift of one state and of a batch of any
    leading shape is numpy's, bit for bit."""
    from vflpcd.base.paths import config_dir
    from vflpcd.config.koopman_file import load_koopman
    from vflpcd.controllers.loops import encoder_loop

    model = load_koopman(config_dir() / "models" / f"{name}.npz")
    X = np.random.default_rng(5).normal(size=(4, 6, model.n_x)) * 3.0
    want, want_one = model.lift(X), model.lift(X[1, 2])
    model.compile_encoder(encoder_loop())
    np.testing.assert_array_equal(model.lift(X), want)
    np.testing.assert_array_equal(model.lift(X[1, 2]), want_one)
