"""Deep Koopman training (torch): beats DMDc on a nonlinear system, deterministic, command line."""

import json
from dataclasses import replace as dataclass_replace

import numpy as np
import pytest

torch = pytest.importorskip("torch", reason="torch is not installed (pip install '.[train]')")

from vflpcd.config.koopman_file import load_koopman  # noqa: E402
from vflpcd.training.datasets import Log, save_log  # noqa: E402
from vflpcd.training.dmdc import fit_dmdc  # noqa: E402
from vflpcd.training.train_koopman import TrainConfig, main, train_koopman, validation_mse  # noqa: E402

NAMES = ("theta", "omega")
CONTROLS = ("tau",)
DT = 0.05


def pendulum_logs(n_logs=8, n=400, seed=0):
    """A damped pendulum driven by a smooth random torque, swinging far into the nonlinear range."""
    rng = np.random.default_rng(seed)
    logs = []
    for i in range(n_logs):
        x = np.array([rng.uniform(-2.5, 2.5), rng.uniform(-1, 1)])
        tau = 0.0
        xs, us = np.empty((n, 2)), np.empty((n, 1))
        for k in range(n):
            tau = 0.95 * tau + 0.3 * rng.standard_normal()
            xs[k], us[k] = x, tau
            for _ in range(5):  # 5 Euler sub-steps per sample
                th, om = x
                x = x + DT / 5 * np.array([om, -9.81 * np.sin(th) - 0.5 * om + 2.0 * tau])
        logs.append(Log(f"pend{i}", xs, us, DT, NAMES, CONTROLS))
    return logs


CFG = TrainConfig(n_lift=6, horizon_s=1.0, epochs=25, seed=0, stride=4, val_stride=4, hidden=(32, 32),
                  windows_per_epoch=1024, batch=128, lr=3e-3, patience=10)


def test_training_beats_dmdc_on_a_nonlinear_system():
    logs = pendulum_logs()
    train, val = logs[:6], logs[6:]
    res = train_koopman(train, val, CFG)
    koop = res.model
    dmdc = fit_dmdc(train, window_s=1.0, stride=4)
    k_mse = validation_mse(koop, val, 1.0, koop.x_std, stride=4)
    d_mse = validation_mse(dmdc, val, 1.0, koop.x_std, stride=4)
    assert k_mse < 0.8 * d_mse, (k_mse, d_mse)
    # the exported numpy model reproduces the validation loss the training saw (float32 vs float64)
    assert k_mse == pytest.approx(koop.metadata["metrics"]["val_pred_mse"], rel=1e-3)
    assert koop.n_K == 6 and koop.metadata["fingerprint"] and res.best_epoch >= 1


def speed_gain_logs(n_logs=8, n=400, seed=0):
    """A yaw rate w that follows v * s (s a steering input): the input's gain grows with the speed v."""
    rng = np.random.default_rng(seed)
    logs = []
    for i in range(n_logs):
        v, w, a, st = rng.uniform(1, 12), 0.0, 0.0, 0.0
        xs, us = np.empty((n, 2)), np.empty((n, 2))
        for k in range(n):
            a = 0.97 * a + 0.2 * rng.standard_normal()
            st = 0.95 * st + 0.02 * rng.standard_normal()
            xs[k], us[k] = (v, w), (a - 0.2 * (v - 7.0), st)
            v = min(max(v + DT * us[k, 0], 0.5), 15.0)
            w = w + DT * 3.0 * (v * st - w)
        logs.append(Log(f"car{i}", xs, us, DT, ("v", "w"), ("acc", "steer")))
    return logs


def test_a_scheduled_input_matrix_learns_a_gain_that_grows_with_the_speed():
    logs = speed_gain_logs()
    train, val = logs[:6], logs[6:]
    linear = train_koopman(train, val, CFG).model
    scheduled = train_koopman(train, val, dataclass_replace(CFG, schedule="v")).model
    assert scheduled.scheduled and scheduled.schedule == "v" and not linear.scheduled
    lin_mse = validation_mse(linear, val, 1.0, linear.x_std, stride=4)
    sch_mse = validation_mse(scheduled, val, 1.0, scheduled.x_std, stride=4)
    assert sch_mse < 0.5 * lin_mse, (sch_mse, lin_mse)
    # the steady turn rate per unit of steering, held for 2 s at 2 and at 10 (true: v)
    gains = [scheduled.rollout(np.array([v, 0.0]), np.tile([0.0, 0.05], (40, 1)))[-1, 1] / 0.05 for v in (2.0, 10.0)]
    assert gains[0] == pytest.approx(2.0, rel=0.3) and gains[1] == pytest.approx(10.0, rel=0.3)
    with pytest.raises(ValueError, match="schedule"):
        train_koopman(train, val, dataclass_replace(CFG, schedule="speed"))


def test_command_line_is_deterministic_and_writes_a_manifest(tmp_path, capsys):
    data = tmp_path / "data"
    for lg in pendulum_logs(n_logs=3, n=200, seed=5):
        save_log(lg, data / f"{lg.name}.npz")
    outs = []
    for run in ("a", "b"):
        out = tmp_path / run / "model.npz"
        rc = main(["train", "koopman", "--data", str(data), "--val", "pend2", "--n-lift", "5", "--horizon-s", "0.5",
                   "--epochs", "3", "--seed", "7", "--out", str(out), "--hidden", "16", "16",
                   "--windows-per-epoch", "256", "--quiet", "--data-command", "synthetic pendulum"])
        assert rc == 0
        outs.append(out)
    assert outs[0].read_bytes() == outs[1].read_bytes()
    model = load_koopman(outs[0], state_names=NAMES, control_names=CONTROLS)
    manifest = json.loads(outs[0].with_suffix(".manifest.json").read_text())
    assert manifest["seed"] == 7 and "--seed 7" in manifest["command"] and manifest["val_logs"] == ["pend2"]
    assert manifest["train_fingerprint"] == model.metadata["fingerprint"]
    assert set(manifest["metrics"]["val_open_loop_rmse"]) == {"koopman", "dmdc", "edmdc"}
    assert "1" in manifest["metrics"]["val_open_loop_rmse"]["koopman"]["rmse"]


@pytest.mark.parametrize("argv", [
    ["--data", "x"],                                                          # missing options
    ["--data", "x", "--val", "a", "--n-lift", "ten", "--out", "m.npz"],       # not an integer
    ["--data", "x", "--val", "a", "--n-lift", "10", "--out", "m.npz", "--epochs", "0"],
    ["--data", "/nonexistent", "--val", "a", "--n-lift", "10", "--out", "m.npz"],
    ["--data", "x", "--val", "a", "--n-lift", "10", "--out", "m.txt"],
])
def test_bad_arguments_exit_2_with_one_line(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("vflpcd train koopman: error:") and "\n" not in err
