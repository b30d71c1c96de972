"""A threat's safety points in the window frame compiled (``barrier_kernel.safety_points_loop``, by
``ErrorModel.safety_points_in_window``) against the numpy path (``barrier.safety_points`` and
``ErrorModel.to_window``): the same points and normals to 1e-12 for the shapes with a closed form,
robot positions outside, inside and on a box's medial planes, a car's and a quadrotor's window; the
other shapes go the numpy way."""

import numpy as np
import pytest

from vflpcd.base.paths import config_dir
from vflpcd.config.koopman_file import load_koopman
from vflpcd.core.control.barrier import safety_points
from vflpcd.core.control.barrier_kernel import safety_points_loop
from vflpcd.core.control.error_model import ErrorModel, Limits, TickLoops
from vflpcd.core.control.tick_kernel import linearisation_loop, window_loop
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Box, Box3, Circle, Ellipse, Sphere

N = 20


def _errors(name, barrier):
    model = load_koopman(config_dir() / "models" / f"{name}.npz")
    n_u = model.n_u
    limits = Limits(-np.ones(n_u), np.ones(n_u), np.full(n_u, np.inf))
    loops = None if barrier is None else TickLoops(window=window_loop, linearisation=linearisation_loop,
                                                   correction=None, barrier=barrier)
    return ErrorModel(model, np.ones(model.n_x), 0.1, np.eye(n_u), 0.95, N, limits, tick_loops=loops)


@pytest.fixture(scope="module")
def compiled():
    pytest.importorskip("numba")
    from vflpcd.controllers.loops import tick_loops

    return tick_loops().barrier


CASES = {
    "dynamic_bicycle": [Circle(0.4), Box(4.5, 1.8), Ellipse(1.0, 0.5)],
    "quadrotor": [Sphere(0.5), Box3(1.0, 2.0, 0.6)],
}


@pytest.mark.parametrize("name", sorted(CASES))
@pytest.mark.parametrize("run", ["compiled", "as python"])
def test_the_loop_gives_the_numpy_points_and_normals(compiled, name, run):
    rng = np.random.default_rng(11)
    plain = _errors(name, None)
    calls = []
    loop = compiled if run == "compiled" else safety_points_loop

    def counted(*args):
        calls.append(args[0])
        return loop(*args)

    fast = _errors(name, counted)
    d = len(plain.layout.position)
    for shape in CASES[name]:
        for trial in range(6):
            state = rng.normal(size=plain.model.n_x) * 3.0
            centre = rng.normal(size=d) * 2.0
            pts = centre + rng.normal(size=(N + 1, d)) * (0.3 if trial < 3 else 4.0)   # inside and outside
            if trial == 0:
                pts[:4] = centre                    # the centre: on every medial plane, a round one's centre
                pts[4, 0] = centre[0] + 0.1
            obstacle = ObstacleState("o", shape, centre, float(rng.uniform(-3, 3)), rng.normal(size=d), 0.3)
            times = 0.5 + 0.05 * np.arange(N + 1)
            frame = plain.frame(state, np.tile(state, (N + 1, 1)))
            want = [plain.to_window(frame, a, vectors=v) for a, v in zip(safety_points(obstacle, pts, times, 0.7),
                                                                          (False, True))]
            got = np.full((2, N + 1, d), np.nan)
            fast.safety_points_in_window(frame, obstacle, pts, times, 0.7, got[0], got[1])
            for g, w in zip(got, want):
                np.testing.assert_allclose(g, w, rtol=0, atol=1e-12, err_msg=f"{shape}")
            np.testing.assert_allclose(np.linalg.norm(got[1], axis=1), 1.0, atol=1e-12)
    assert len(calls) == 6 * sum(s.closed_form != "" for s in CASES[name])        # the others: numpy