"""The tick's window, lift and nominal linearisation compiled (``tick_kernel``) against the numpy path
of ``ErrorModel``: the same frame and problem to 1e-12, for the car's and the quadrotor's models (a
deep Koopman lift: ``window_lift_loop``) and a lift of another kind, with the heading wrapping inside
the window, and with the reference controls clipped."""

import numpy as np
import pytest

from vflpcd.config.koopman_file import load_koopman
from vflpcd.core.control.error_model import ErrorModel, Limits, TickLoops
from vflpcd.core.control.tick_kernel import command_loop, linearisation_loop, window_lift_loop, window_loop
from vflpcd.core.dynamics.gp_kernel import corrected_next_loop
from vflpcd.core.dynamics.lifted import LiftedLinearModel
from vflpcd.base.paths import config_dir

N = 20


class Plain(LiftedLinearModel):
    """Upsilon = [x, sin(x), 1]: a lift that does not start from the normalised state (the generic
    ``Lifter``)."""

    def rho(self, x):
        x = np.asarray(x, float)
        return np.concatenate([np.sin(x), np.ones(x.shape[:-1] + (1,))], axis=-1)


def _plain():
    rng = np.random.default_rng(2)
    A = np.eye(13) + 0.02 * rng.normal(size=(13, 13))
    A[-1] = np.eye(13)[-1]
    B = 0.05 * rng.normal(size=(13, 2))
    B[-1] = 0.0
    return Plain(A, B, state_names=("X", "Y", "psi", "vx", "vy", "omega"), control_names=("a_x", "delta_f"),
                 dt=0.05, x_mean=np.zeros(6), x_std=np.ones(6), u_mean=np.zeros(2), u_std=np.ones(2))


def _models():
    car = load_koopman(config_dir() / "models" / "dynamic_bicycle.npz")
    quad = load_koopman(config_dir() / "models" / "quadrotor.npz")
    return {"car": car, "quad": quad, "plain": _plain()}


def _error_model(model, loops):
    n_u = model.n_u
    limits = Limits(-np.full(n_u, 0.3), np.full(n_u, 0.3), np.full(n_u, np.inf))
    Q_x = np.ones(model.n_x)
    return ErrorModel(model, Q_x, 0.1, np.eye(n_u), 0.95, N, limits, tick_loops=loops)


def _states(model, rng, wrap: bool):
    x0 = rng.normal(size=model.n_x) * 3.0
    ref = x0 + np.cumsum(rng.normal(size=(N + 1, model.n_x)) * 0.2, axis=0)
    if wrap and "psi" in model.state_names:      # the heading crosses +-pi inside the window
        h = list(model.state_names).index("psi")
        x0[h] = 3.1
        ref[:, h] = np.angle(np.exp(1j * (3.1 + 0.05 * np.arange(N + 1))))
    return x0, ref


@pytest.fixture(scope="module")
def compiled():
    from vflpcd.controllers.loops import tick_loops

    loops = tick_loops()
    if loops is None:
        pytest.skip("numba is not installed")
    return loops


@pytest.mark.parametrize("name", ["car", "quad", "plain"])
@pytest.mark.parametrize("wrap", [False, True])
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_loops_give_the_numpy_paths_frame_and_problem(compiled, name, wrap, run):
    model = _models()[name]
    loops = compiled if run == "compiled" else TickLoops(window=window_loop, linearisation=linearisation_loop,
                                                         correction=corrected_next_loop, lift=window_lift_loop)
    rng = np.random.default_rng(7)
    for _ in range(5):
        x0, ref = _states(model, rng, wrap)
        plain, fast = _error_model(model, None), _error_model(model, loops)
        a, b = plain.frame(x0, ref), fast.frame(x0, ref)
        for field in ("U", "U_r", "x_r"):
            np.testing.assert_allclose(getattr(b, field), getattr(a, field), rtol=0, atol=1e-12)
        u_prev = rng.normal(size=model.n_u) * 0.1
        p, q = plain.problem(a, u_prev), fast.problem(a, u_prev)
        assert np.any(np.abs(p.u_ref) >= 0.3)               # some reference controls are clipped
        for field in ("A", "B", "c", "x0", "u_ref"):
            np.testing.assert_allclose(getattr(q, field), getattr(p, field), rtol=0, atol=1e-12)


@pytest.mark.parametrize("run", ["python", "compiled"])
def test_the_command_loop_clips_as_numpy_does(run):
    """``command_loop`` (run as Python and compiled) gives VF-LPC's numpy clip exactly: u_r,0 + u~_0
    into the magnitude limits, then within du_max of the previous command; an input without a rate
    limit (inf) is clipped by its magnitude alone, and a NaN stays NaN."""
    if run == "compiled":
        from vflpcd.controllers.loops import tick_loops

        loops = tick_loops()
        if loops is None:
            pytest.skip("numba is not installed")
        loop = loops.command
    else:
        loop = command_loop
    rng = np.random.default_rng(7)
    u_min, u_max, du = np.array([-6.0, -0.5, -1.0]), np.array([3.0, 0.5, 1.0]), np.array([0.3, 0.03, np.inf])
    for _ in range(300):
        u_ref0, u_tilde0, u_prev = rng.normal(size=3) * 2.0, rng.normal(size=3) * 2.0, rng.normal(size=3)
        if rng.uniform() < 0.1:
            u_tilde0[rng.integers(3)] = np.nan
        expected = np.minimum(np.maximum(u_ref0 + u_tilde0, u_min), u_max)
        expected = np.minimum(np.maximum(expected, u_prev - du), u_prev + du)
        np.testing.assert_array_equal(loop(u_ref0, u_tilde0, u_min, u_max, u_prev, du), expected)
