import numpy as np
import pytest

from vflpcd.core.dynamics.lifted import LiftedLinearModel, PoseLayout, from_window_frame, to_window_frame
from vflpcd.training.datasets import Log
from vflpcd.training.evaluate import open_loop_rmse

CAR = ("X", "Y", "yaw", "vx", "vy", "yaw_rate")
QUAD = ("X", "Y", "Z", "vx", "vy", "vz")


class Plain(LiftedLinearModel):
    """A model with no observables beyond the state (n_K = n_x) and identity normalisation."""

    def __init__(self, A, B, state_names, control_names, dt=0.05):
        n_x, n_u = len(state_names), len(control_names)
        super().__init__(A, B, state_names=state_names, control_names=control_names, dt=dt,
                         x_mean=np.zeros(n_x), x_std=np.ones(n_x), u_mean=np.zeros(n_u), u_std=np.ones(n_u))

    def rho(self, x):
        return np.zeros(np.shape(x)[:-1] + (0,))


def car_states(n=200, seed=0):
    rng = np.random.default_rng(seed)
    s = rng.normal(size=(n, 6))
    s[:, 0:2] = np.cumsum(rng.normal(size=(n, 2)), axis=0) + [300.0, -120.0]
    s[:, 2] = np.cumsum(rng.normal(0, 0.3, size=n)) + 17.0  # unwrapped heading
    return s


def rigid(states, theta, shift):
    out = states.copy()
    c, s = np.cos(theta), np.sin(theta)
    out[:, 0] = c * states[:, 0] - s * states[:, 1] + shift[0]
    out[:, 1] = s * states[:, 0] + c * states[:, 1] + shift[1]
    out[:, 2] = states[:, 2] + theta
    return out


def test_pose_layouts():
    assert PoseLayout.of(CAR) == PoseLayout("planar", (0, 1), 2)
    assert PoseLayout.of(("X", "Y", "psi", "vx", "vy", "omega")).heading == 2
    assert PoseLayout.of(QUAD) == PoseLayout("position", (0, 1, 2), None)
    assert PoseLayout.of(("a", "b")).kind == "none"


def test_window_frame_is_invertible_and_starts_at_the_origin():
    s = car_states()
    windows = np.stack([s[i:i + 41] for i in range(0, 150, 7)])  # (M, 41, 6)
    w = to_window_frame(windows, CAR)
    np.testing.assert_allclose(w[:, 0, :3], 0.0, atol=1e-12)
    np.testing.assert_array_equal(w[..., 3:], windows[..., 3:])  # body-frame channels unchanged
    back = from_window_frame(w, CAR, windows[:, 0])
    np.testing.assert_allclose(back, windows, atol=1e-9)
    q = np.random.default_rng(1).normal(size=(5, 11, 6)) * 10
    wq = to_window_frame(q, QUAD)
    np.testing.assert_allclose(wq[..., :3], q[..., :3] - q[:, :1, :3], atol=1e-12)
    np.testing.assert_allclose(from_window_frame(wq, QUAD, q[:, 0]), q, atol=1e-12)


def test_rotated_and_translated_log_gives_identical_window_frame_data():
    s = car_states(seed=2)
    moved = rigid(s, 2.3, (-55.0, 812.0))
    wa = to_window_frame(np.stack([s[i:i + 21] for i in range(0, 180, 5)]), CAR)
    wb = to_window_frame(np.stack([moved[i:i + 21] for i in range(0, 180, 5)]), CAR)
    np.testing.assert_allclose(wa, wb, atol=1e-9)
    # a heading wrapped to (-pi, pi] inside the window changes nothing either
    wrapped = moved.copy()
    wrapped[:, 2] = np.angle(np.exp(1j * wrapped[:, 2]))
    wc = to_window_frame(np.stack([wrapped[i:i + 21] for i in range(0, 180, 5)]), CAR)
    np.testing.assert_allclose(wa, wc, atol=1e-9)


def constant_velocity_log(name, n=300, v=(1.0, 2.0, 2.0), dt=0.05):
    """Point mass at constant world velocity v: X_k = X_0 + k dt v, zero controls."""
    k = np.arange(n)[:, None]
    pos = np.array([5.0, -3.0, 10.0]) + k * dt * np.asarray(v)
    return Log(name, np.hstack([pos, np.tile(v, (n, 1))]), np.zeros((n, 3)), dt, QUAD, ("ax", "ay", "az"))


def test_exact_model_gives_zero_and_a_wrong_model_a_known_rmse():
    dt = 0.05
    exact = np.eye(6)
    exact[:3, 3:] = dt * np.eye(3)
    B = np.vstack([0.5 * dt * dt * np.eye(3), dt * np.eye(3)])
    logs = [constant_velocity_log("q1"), constant_velocity_log("q2", v=(1.0, 2.0, 2.0))]
    res = open_loop_rmse(Plain(exact, B, QUAD, ("ax", "ay", "az")), logs, stride=10)
    assert res["horizon_steps"] == [10, 20, 40]
    assert res["n_windows"] == 2 * len(range(0, 300 - 40, 10))
    assert res["channels"] == ["position", "vx", "vy", "vz"]
    for h in (0.5, 1.0, 2.0):
        assert all(v < 1e-9 for v in res["rmse"][h].values())
    # wrong: the position does not integrate the velocity -> error n dt |v| = 3 m/s * h
    wrong = open_loop_rmse(Plain(np.eye(6), B, QUAD, ("ax", "ay", "az")), logs, stride=10)
    for h in (0.5, 1.0, 2.0):
        assert wrong["rmse"][h]["position"] == pytest.approx(3.0 * h, rel=1e-9)
        assert wrong["rmse"][h]["vx"] == pytest.approx(0.0, abs=1e-12)


def test_linear_system_without_pose_and_a_car_in_the_window_frame():
    rng = np.random.default_rng(0)
    A = np.array([[0.9, 0.1], [-0.2, 0.95]])
    B = np.array([[0.0], [0.1]])
    x, xs, us = np.array([1.0, -1.0]), np.empty((200, 2)), rng.normal(size=(200, 1))
    for k in range(200):
        xs[k] = x
        x = A @ x + B @ us[k]
    lg = Log("lin", xs, us, 0.05, ("a", "b"), ("u",))
    res = open_loop_rmse(Plain(A, B, ("a", "b"), ("u",)), [lg], horizons_s=(0.25, 1.0), stride=3)
    assert res["channels"] == ["a", "b"]
    assert max(max(r.values()) for r in res["rmse"].values()) < 1e-12
    # a car driving straight at 10 m/s with an arbitrary world heading: in the window frame
    # X' = X' + dt vx exactly; a model that ignores vx errs by 10 m/s * h along X'
    n, dt = 120, 0.05
    heading = 2.0
    k = np.arange(n)
    s = np.zeros((n, 6))
    s[:, 0] = 7.0 + 10.0 * dt * k * np.cos(heading)
    s[:, 1] = -4.0 + 10.0 * dt * k * np.sin(heading)
    s[:, 2] = heading
    s[:, 3] = 10.0
    car = Log("straight", s, np.zeros((n, 2)), dt, CAR, ("steer", "throttle"))
    A_car = np.eye(6)
    A_car[0, 3] = dt
    B_car = np.zeros((6, 2))
    good = open_loop_rmse(Plain(A_car, B_car, CAR, ("steer", "throttle")), [car], stride=5)
    bad = open_loop_rmse(Plain(np.eye(6), B_car, CAR, ("steer", "throttle")), [car], stride=5)
    assert good["channels"] == ["position", "yaw", "vx", "vy", "yaw_rate"]
    for h in (0.5, 1.0, 2.0):
        assert good["rmse"][h]["position"] < 1e-9
        assert bad["rmse"][h]["position"] == pytest.approx(10.0 * h, rel=1e-9)
        assert bad["rmse"][h]["yaw"] == 0.0


def test_windows_skip_gaps_and_bad_horizons_are_rejected():
    log = constant_velocity_log("q")
    states = log.states.copy()
    states[100] = np.nan
    gap = Log("gap", states, log.controls, log.dt, QUAD, ("ax", "ay", "az"))
    exact = np.eye(6)
    exact[:3, 3:] = 0.05 * np.eye(3)
    model = Plain(exact, np.zeros((6, 3)), QUAD, ("ax", "ay", "az"))
    res = open_loop_rmse(model, [gap], horizons_s=(1.0,), stride=1)
    assert res["n_windows"] == (100 - 20) + (199 - 20)
    assert res["rmse"][1.0]["position"] < 1e-9  # no window straddles the dropped row
    with pytest.raises(ValueError, match="whole number"):
        open_loop_rmse(model, [gap], horizons_s=(0.52,))
