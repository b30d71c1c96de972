"""`bench dynamics`' steering response: the plant's yaw rate against the model's own prediction."""

import numpy as np
import pytest

from sim.bench.dynamics import steering_response
from vflpcd.config.koopman_file import load_koopman
from vflpcd.base.paths import config_dir
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.core.dynamics.koopman import KoopmanModel


@pytest.fixture(scope="module")
def model():
    return load_koopman(config_dir() / "models" / "dynamic_bicycle_scheduled.npz",
                        state_names=("X", "Y", "psi", "vx", "vy", "omega"), control_names=("a_x", "delta_f"))


def test_rows_are_the_plant_and_the_models_open_loop_prediction(model):
    rows = steering_response(model, speeds=(3.0, 6.0, 12.0), delta=0.05, seconds=1.0)
    assert [r["speed"] for r in rows] == [3.0, 6.0, 12.0]
    for r in rows:
        # the plant is the symmetric bicycle: the right turn mirrors the left one
        assert r["plant_left"] > 0.0 and r["plant_right"] == pytest.approx(-r["plant_left"], rel=1e-9)
        pred = model.rollout(np.array([0.0, 0.0, 0.0, r["speed"], 0.0, 0.0]), np.tile([0.0, 0.05], (20, 1)))
        assert r["model_left"] == pytest.approx(pred[-1, 5], rel=1e-12)
        assert r["ratio_left"] == pytest.approx(r["model_left"] / r["plant_left"])
        assert r["ratio_right"] == pytest.approx(r["model_right"] / r["plant_right"])
    # the car's yaw-rate gain grows with speed (kinematic: about v delta / L) ...
    assert rows[0]["plant_left"] < rows[1]["plant_left"] < rows[2]["plant_left"]
    p = BicycleConfig.load("nominal").params
    assert rows[0]["plant_left"] == pytest.approx(3.0 * 0.05 / (p.lf + p.lr), rel=0.1)
    # ... and so does the scheduled model's (config/models/dynamic_bicycle_scheduled.npz)
    assert model.scheduled and model.schedule == "vx"
    for r in rows:
        assert 0.85 < r["ratio_left"] < 1.15 and 0.85 < r["ratio_right"] < 1.15
    # the same model with its input matrix frozen at 6 m/s keeps one gain: its ratio falls with speed
    frozen = KoopmanModel(model.A, model.B + 6.0 * model.B_s, enc_weights=model.enc_weights,
                          enc_biases=model.enc_biases, state_names=model.state_names,
                          control_names=model.control_names, dt=model.dt, x_mean=model.x_mean, x_std=model.x_std,
                          u_mean=model.u_mean, u_std=model.u_std)
    linear = steering_response(frozen, speeds=(3.0, 6.0, 12.0), delta=0.05, seconds=1.0)
    assert linear[0]["ratio_left"] > 1.3 > 0.8 > linear[2]["ratio_left"]
