import numpy as np
import pytest

from vflpcd.core.dynamics.lifted import LiftedLinearModel, to_physical, to_physical_scheduled
from vflpcd.training.datasets import Log
from vflpcd.training.dmdc import DictionaryModel, fit_dmdc, fit_edmdc
from vflpcd.training.evaluate import open_loop_rmse

NAMES = ("a", "b", "c")
CONTROLS = ("u1", "u2")


def linear_system(seed=0):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(3, 3))
    A *= 0.95 / max(abs(np.linalg.eigvals(A)))
    B = rng.normal(size=(3, 2))
    return A, B


def linear_logs(A, B, n_logs=3, n=400, seed=1, offset=(0.0, 0.0)):
    rng = np.random.default_rng(seed)
    logs = []
    for i in range(n_logs):
        x = rng.normal(size=3) * 5.0 + 10.0
        xs, us = np.empty((n, 3)), rng.normal(size=(n, 2)) * [2.0, 0.3] + np.asarray(offset)
        for k in range(n):
            xs[k] = x
            x = A @ x + B @ us[k]
        logs.append(Log(f"lin{i}", xs, us, 0.05, NAMES, CONTROLS))
    return logs


@pytest.mark.parametrize("offset", [(0.0, 0.0), (3.0, -7.0)])
def test_dmdc_recovers_an_exactly_linear_system(offset):
    A, B = linear_system()
    model = fit_dmdc(linear_logs(A, B, offset=offset), window_s=1.0, stride=3)
    assert isinstance(model, LiftedLinearModel) and model.n_K == 4
    np.testing.assert_allclose(model.A[:3, :3], A, atol=1e-8)
    np.testing.assert_allclose(model.B[:3], B, atol=1e-8)
    np.testing.assert_allclose(model.A[:3, 3], 0.0, atol=1e-8)  # no affine offset in the true system
    np.testing.assert_array_equal(model.A[3], [0, 0, 0, 1])
    np.testing.assert_array_equal(model.B[3], [0, 0])
    # the normalisation lives in the model and is not the identity here
    assert not np.allclose(model.x_std, 1.0) and not np.allclose(model.u_std, 1.0)
    np.testing.assert_allclose(model.u_mean, offset, atol=0.2)


def test_lift_starts_with_the_state_and_rollout_iterates_the_lifted_system():
    A, B = linear_system(3)
    model = fit_edmdc(linear_logs(A, B), dictionary="rff", n_features=8, seed=4, window_s=1.0)
    x = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    U = model.lift(x)
    assert U.shape == (2, 3 + 8 + 1)
    np.testing.assert_array_equal(U[:, :3], x)
    np.testing.assert_allclose(U[:, -1], 1.0)
    u = np.random.default_rng(0).normal(size=(5, 2))
    traj = model.rollout(x[0], u)
    Uk = model.lift(x[0])
    for k in range(5):
        Uk = model.A @ Uk + model.B @ u[k]
        np.testing.assert_allclose(traj[k + 1], Uk[:3], rtol=1e-12, atol=1e-12)
    assert traj.shape == (6, 3)


def test_rff_dictionary_is_seeded():
    A, B = linear_system(5)
    logs = linear_logs(A, B, n_logs=2, n=200)
    m1 = fit_edmdc(logs, dictionary="rff", n_features=16, seed=7, window_s=0.5)
    m2 = fit_edmdc(logs, dictionary="rff", n_features=16, seed=7, window_s=0.5)
    m3 = fit_edmdc(logs, dictionary="rff", n_features=16, seed=8, window_s=0.5)
    np.testing.assert_array_equal(m1.A, m2.A)
    assert not np.allclose(m1.A, m3.A)


def test_to_physical_matches_the_normalised_model():
    rng = np.random.default_rng(0)
    n_x, n_phi, n_u = 3, 2, 2
    n_K = n_x + n_phi + 1
    A_n = rng.normal(size=(n_K, n_K)) * 0.3
    A_n[-1] = 0.0
    A_n[-1, -1] = 1.0
    B_n = rng.normal(size=(n_K, n_u))
    B_n[-1] = 0.0
    xm, xs, um, us = rng.normal(size=n_x), rng.uniform(0.5, 2, n_x), rng.normal(size=n_u), rng.uniform(0.5, 2, n_u)
    A, B = to_physical(A_n, B_n, xm, xs, um, us)
    x, phi, u = rng.normal(size=n_x), rng.normal(size=n_phi), rng.normal(size=n_u)
    Zn = np.concatenate([(x - xm) / xs, phi, [1.0]])
    Zn1 = A_n @ Zn + B_n @ ((u - um) / us)
    U1 = A @ np.concatenate([x, phi, [1.0]]) + B @ u
    np.testing.assert_allclose(U1[:n_x], Zn1[:n_x] * xs + xm, atol=1e-12)
    np.testing.assert_allclose(U1[n_x:], Zn1[n_x:], atol=1e-12)


def test_scheduled_to_physical_matches_the_normalised_bilinear_model():
    rng = np.random.default_rng(1)
    n_x, n_phi, n_u, j = 3, 2, 2, 1
    n_K = n_x + n_phi + 1
    A_n = rng.normal(size=(n_K, n_K)) * 0.3
    A_n[-1] = 0.0
    A_n[-1, -1] = 1.0
    B_n, B_s_n = rng.normal(size=(n_K, n_u)), rng.normal(size=(n_K, n_u))
    B_n[-1] = B_s_n[-1] = 0.0
    xm, xs, um, us = rng.normal(size=n_x), rng.uniform(0.5, 2, n_x), rng.normal(size=n_u), rng.uniform(0.5, 2, n_u)
    A, B, B_s = to_physical_scheduled(A_n, B_n, B_s_n, j, xm, xs, um, us)
    for _ in range(3):
        x, phi, u = rng.normal(size=n_x), rng.normal(size=n_phi), rng.normal(size=n_u)
        Zn = np.concatenate([(x - xm) / xs, phi, [1.0]])
        u_n = (u - um) / us
        Zn1 = A_n @ Zn + (B_n + Zn[j] * B_s_n) @ u_n
        U = np.concatenate([x, phi, [1.0]])
        U1 = A @ U + (B + U[j] * B_s) @ u
        np.testing.assert_allclose(U1[:n_x], Zn1[:n_x] * xs + xm, atol=1e-12)
        np.testing.assert_allclose(U1[n_x:], Zn1[n_x:], atol=1e-12)
    # without a slope it is the linear conversion
    A0, B0, Bs0 = to_physical_scheduled(A_n, B_n, np.zeros_like(B_n), j, xm, xs, um, us)
    np.testing.assert_allclose(np.hstack([A0, B0]), np.hstack(to_physical(A_n, B_n, xm, xs, um, us)), atol=1e-14)
    assert not Bs0.any()


def bicycle_logs(n_logs=3, n=600, seed=0):
    """Kinematic-ish car with first-order speed/yaw-rate response (nonlinear in the pose)."""
    rng = np.random.default_rng(seed)
    dt, logs = 0.05, []
    for i in range(n_logs):
        x = np.array([rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-3, 3), 8.0, 0.0, 0.0])
        xs, us = np.empty((n, 6)), np.empty((n, 2))
        a = s = 0.0
        for k in range(n):
            a = 0.95 * a + 0.3 * rng.normal()
            s = 0.97 * s + 0.01 * rng.normal()
            us[k] = [a, s]
            xs[k] = x
            X, Y, psi, vx, vy, r = x
            vx_n = max(vx + dt * (a - 0.05 * (vx - 8.0)), 1.0)
            r_n = r + dt * 4.0 * (vx * s / 2.8 - r)
            vy_n = vy + dt * 4.0 * (0.4 * r * vx / 8.0 - vy)
            x = np.array([X + dt * (vx * np.cos(psi) - vy * np.sin(psi)), Y + dt * (vx * np.sin(psi) + vy * np.cos(psi)),
                          psi + dt * r, vx_n, vy_n, r_n])
        logs.append(Log(f"car{i}", xs, us, dt, ("X", "Y", "yaw", "vx", "vy", "yaw_rate"), ("a", "steer")))
    return logs


def test_edmdc_vehicle_dictionary_beats_dmdc_on_a_car():
    train, val = bicycle_logs(seed=0), bicycle_logs(n_logs=1, seed=1)
    dmdc, edmdc = fit_dmdc(train), fit_edmdc(train)
    assert isinstance(edmdc, DictionaryModel) and edmdc.dictionary == "vehicle" and edmdc.n_K == 6 + 13 + 1
    r_d = open_loop_rmse(dmdc, val, horizons_s=(1.0,))["rmse"][1.0]
    r_e = open_loop_rmse(edmdc, val, horizons_s=(1.0,))["rmse"][1.0]
    assert r_e["position"] < r_d["position"]
    assert r_e["position"] < 0.5
