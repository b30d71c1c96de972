"""The horizon problem of a model whose input matrix depends on the speed (B + v_x B_s)."""

import numpy as np
import pytest

from vflpcd.core.control.error_model import ErrorModel, Limits
from vflpcd.core.dynamics.lifted import LiftedLinearModel

NAMES = ("X", "Y", "psi", "vx", "vy", "omega")
N = 8


class Plain(LiftedLinearModel):
    """Upsilon = [x, 1]: the lift is exact, so a rollout of the model is a reference it can follow."""

    def rho(self, x):
        return np.ones(np.shape(x)[:-1] + (1,))


def scheduled_model(seed=0):
    rng = np.random.default_rng(seed)
    A = np.eye(7) + 0.02 * rng.normal(size=(7, 7))
    A[-1] = np.eye(7)[-1]
    B, B_s = 0.05 * rng.normal(size=(7, 2)), 0.02 * rng.normal(size=(7, 2))
    B[-1] = B_s[-1] = 0.0
    return Plain(A, B, B_s=B_s, schedule="vx", state_names=NAMES, control_names=("a_x", "delta_f"), dt=0.05,
                 x_mean=np.zeros(6), x_std=np.ones(6), u_mean=np.zeros(2), u_std=np.ones(2))


def error_model(model, **kw):
    limits = Limits(np.array([-6.0, -0.5]), np.array([3.0, 0.5]), np.array([np.inf, 0.03]))
    return ErrorModel(model, np.array([1.0, 4.0, 4.0, 0.5, 0.0, 0.0]), 0.0, np.diag([0.1, 1.0]), 1.0, N, limits, **kw)


def test_the_reference_control_and_the_linearisation_follow_the_speed():
    model = scheduled_model()
    em = error_model(model, schedule_at=6.0)
    rng = np.random.default_rng(1)
    controls = np.column_stack([rng.uniform(-1, 1, N), rng.uniform(-0.1, 0.1, N)])
    x0 = np.array([0.0, 0.0, 0.0, 6.0, 0.1, 0.05])
    ref = model.rollout(x0, controls)                       # a reference the model drives exactly
    p = em.problem(em.frame(x0, ref), np.zeros(2))            # the robot on the reference: one window frame
    np.testing.assert_allclose(p.u_ref, controls, atol=1e-10)          # u_r recovers the controls
    np.testing.assert_allclose(p.c, 0.0, atol=1e-10)
    U_r = model.lift(ref)
    for k in (0, N - 1):                                    # A_tau, B_tau: the Jacobians of the step
        np.testing.assert_allclose(p.B[k], model.input_matrix(U_r[k])[:-1], atol=1e-12)
        dU = np.zeros(7)
        dU[3] = 1e-6
        fd = (model.step(U_r[k] + dU, controls[k]) - model.step(U_r[k], controls[k]))[:-1] / 1e-6
        np.testing.assert_allclose(p.A[k][:, 3], fd, atol=1e-6)
    # the terminal pair is the model's at the nominal speed
    nominal = error_model(Plain(model.A, model.B + 6.0 * model.B_s, state_names=NAMES,
                                control_names=("a_x", "delta_f"), dt=0.05, x_mean=np.zeros(6), x_std=np.ones(6),
                                u_mean=np.zeros(2), u_std=np.ones(2)))
    np.testing.assert_allclose(em.P, nominal.P, rtol=1e-10)


def test_a_scheduled_model_needs_its_nominal_speed():
    with pytest.raises(ValueError, match="nominal pair"):
        error_model(scheduled_model())


@pytest.mark.parametrize("clipped", [False, True])
def test_the_compiled_problem_equals_the_numpy_path(clipped):
    from vflpcd.controllers.loops import scheduled_problem_loop

    loop = scheduled_problem_loop()
    if loop is None:
        pytest.skip("numba is not installed")
    model = scheduled_model(3)
    rng = np.random.default_rng(4)
    controls = np.column_stack([rng.uniform(-1, 1, N), rng.uniform(-0.1, 0.1, N) * (20.0 if clipped else 1.0)])
    x0 = np.array([0.0, 0.0, 0.0, 6.0, 0.1, 0.05])
    ref = model.rollout(x0, controls) + rng.normal(size=(N + 1, 6)) * 0.05    # not exactly drivable
    frame = error_model(model, schedule_at=6.0).frame(x0 + 0.1, ref)
    numpy_path = error_model(model, schedule_at=6.0).problem(frame, np.zeros(2))
    compiled = error_model(model, schedule_at=6.0, problem_loop=loop).problem(frame, np.zeros(2))
    assert clipped == bool(np.any(np.abs(numpy_path.u_ref[:, 1]) >= 0.5))
    for field in ("A", "B", "c", "x0", "u_ref"):
        np.testing.assert_allclose(getattr(compiled, field), getattr(numpy_path, field), rtol=1e-12, atol=1e-12)


def test_vflpc_drives_with_the_scheduled_model():
    from vflpcd.base.paths import config_dir
    from vflpcd.config.scenarios import load_scenario
    from vflpcd.controllers.vflpc import make_vflpc
    from sim.plants import make_plant

    scenario = load_scenario("racing_track")
    ctrl = make_vflpc(scenario, model_path=config_dir() / "models" / "dynamic_bicycle_scheduled.npz")
    assert ctrl.model.scheduled
    plant = make_plant(scenario, 0)
    lateral = []
    for k in range(120):                                   # 6 s: the start's heading error, then the bend
        u = ctrl.step(plant.state, k * 0.05)
        plant.step(u, 0.05)
        lateral.append(abs(scenario.path.project(plant.position()).lateral))
    assert ctrl.fallbacks == 0 and max(lateral[60:]) < 0.15, max(lateral[60:])
