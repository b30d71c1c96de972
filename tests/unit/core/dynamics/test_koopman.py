"""Deep Koopman inference side (numpy): artifact round trip, validation, no torch import, shipped models."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from vflpcd.config.koopman_file import load_koopman, save_koopman
from vflpcd.core.dynamics.koopman import KoopmanModel
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir

NAMES = ("X", "Y", "psi", "vx", "vy", "omega")
CONTROLS = ("a_x", "delta_f")
REPO = Path(__file__).resolve().parents[4]


def random_model(n_K=10, hidden=(16, 8), seed=0, scheduled=False) -> KoopmanModel:
    rng = np.random.default_rng(seed)
    n_x, n_u = len(NAMES), len(CONTROLS)
    dims = [n_x, *hidden, n_K - n_x - 1]
    Ws = [rng.normal(0, 1 / np.sqrt(a), size=(a, b)) for a, b in zip(dims[:-1], dims[1:])]
    bs = [rng.normal(0, 0.1, size=b) for b in dims[1:]]
    A = np.eye(n_K) + 0.02 * rng.normal(size=(n_K, n_K))
    A[-1] = 0.0
    A[-1, -1] = 1.0
    B = 0.05 * rng.normal(size=(n_K, n_u))
    B[-1] = 0.0
    extra = {}
    if scheduled:
        B_s = 0.01 * rng.normal(size=(n_K, n_u))
        B_s[-1] = 0.0
        extra = {"B_s": B_s, "schedule": "vx"}
    return KoopmanModel(A, B, enc_weights=Ws, enc_biases=bs, metadata={"fingerprint": "abc", "metrics": {"x": 1.0}},
                        state_names=NAMES, control_names=CONTROLS, dt=0.05, x_mean=rng.normal(size=n_x),
                        x_std=rng.uniform(0.5, 2, n_x), u_mean=rng.normal(size=n_u), u_std=rng.uniform(0.5, 2, n_u),
                        **extra)


def rewrite(src: Path, dst: Path, change) -> Path:
    with np.load(src, allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files}
    change(arrays)
    np.savez(dst, **arrays)
    return dst


def test_numpy_round_trip_and_lift_layout(tmp_path):
    m = random_model()
    path = save_koopman(m, tmp_path / "m.npz")
    got = load_koopman(path, state_names=NAMES, control_names=CONTROLS)
    assert got.n_K == 10 and got.n_x == 6 and got.n_u == 2 and got.n_encoder == 3
    np.testing.assert_array_equal(got.A, m.A)
    np.testing.assert_array_equal(got.B, m.B)
    x = np.random.default_rng(1).normal(size=(5, 6))
    U = got.lift(x)
    np.testing.assert_array_equal(U[:, :6], x)          # Upsilon = [x, rho_e, 1]
    np.testing.assert_array_equal(U[:, -1], 1.0)
    np.testing.assert_array_equal(U, m.lift(x))
    assert got.metadata["n_K"] == 10 and got.metadata["activation"] == "tanh"
    assert got.metadata["fingerprint"] == "abc"
    # identical models give identical bytes
    assert save_koopman(m, tmp_path / "again.npz").read_bytes() == path.read_bytes()


def test_scheduled_model_round_trip_and_prediction(tmp_path):
    m = random_model(scheduled=True)
    got = load_koopman(save_koopman(m, tmp_path / "s.npz"), state_names=NAMES, control_names=CONTROLS)
    assert got.scheduled and got.schedule == "vx" and got.schedule_index == 3
    np.testing.assert_array_equal(got.B_s, m.B_s)
    assert not random_model().scheduled and not load_koopman(save_koopman(random_model(), tmp_path / "l.npz")).scheduled
    rng = np.random.default_rng(2)
    x0, u = rng.normal(size=6), rng.normal(size=(4, 2))
    U = got.lift(x0)
    for k in range(4):                                     # U' = A U + (B + v_x B_s) u
        U = got.A @ U + (got.B + U[3] * got.B_s) @ u[k]
    np.testing.assert_allclose(got.rollout(x0, u)[-1], U[:6], rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(got.input_matrix(got.lift(x0)), got.B + x0[3] * got.B_s, rtol=1e-12)


@pytest.mark.parametrize("change,key", [
    (lambda a: a.pop("B_s"), "B_s"),
    (lambda a: a.__setitem__("B_s", np.ones((10, 2))), "B_s"),
    (lambda a: a.__setitem__("metadata", np.array(json.dumps(
        {**json.loads(str(a["metadata"])), "schedule": "speed"}))), "metadata.schedule"),
])
def test_bad_scheduled_artifacts_name_the_key(tmp_path, change, key):
    good = save_koopman(random_model(scheduled=True), tmp_path / "good.npz")
    with pytest.raises(ConfigError) as err:
        load_koopman(rewrite(good, tmp_path / "bad.npz", change))
    assert err.value.field == key


@pytest.mark.parametrize("scheduled", [False, True])
def test_torch_network_and_numpy_model_predict_the_same(tmp_path, scheduled):
    torch = pytest.importorskip("torch", reason="torch is not installed (pip install '.[train]')")
    from vflpcd.training.train_koopman import build_network, export_model, network_rollout

    torch.manual_seed(3)
    net = build_network(6, 2, 10, (32, 32), schedule=3 if scheduled else None)
    rng = np.random.default_rng(4)
    with torch.no_grad():
        A = np.eye(10)[:-1] + 0.05 * rng.normal(size=(9, 10))
        net.A_top.copy_(torch.as_tensor(A, dtype=torch.float32))
        net.B_top.copy_(torch.as_tensor(0.1 * rng.normal(size=(9, 2)), dtype=torch.float32))
        if scheduled:
            net.B_s_top.copy_(torch.as_tensor(0.05 * rng.normal(size=(9, 2)), dtype=torch.float32))
    stats = {"x_mean": rng.normal(size=6), "x_std": rng.uniform(0.3, 3.0, 6),
             "u_mean": rng.normal(size=2), "u_std": rng.uniform(0.3, 3.0, 2)}
    model = export_model(net, stats, NAMES, CONTROLS, 0.05, {"fingerprint": "f", "metrics": {}})
    loaded = load_koopman(save_koopman(model, tmp_path / "k.npz"), state_names=NAMES, control_names=CONTROLS)
    assert loaded.scheduled == scheduled
    x0 = rng.normal(size=(16, 6)) * stats["x_std"] + stats["x_mean"]
    for H in (1, 20):
        u = rng.normal(size=(16, H, 2)) * stats["u_std"] + stats["u_mean"]
        ref = network_rollout(net, stats, x0, u)
        got = loaded.rollout_batch(x0, u)
        assert ref.shape == got.shape == (16, H + 1, 6)
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize("key,change", [
    ("A", lambda a: a.__setitem__("A", np.eye(9))),
    ("B", lambda a: a.__setitem__("B", np.zeros((10, 3)))),
    ("enc_W2", lambda a: a.__setitem__("enc_W2", np.zeros((16, 9)))),
    ("enc_W2", lambda a: a.pop("enc_W2")),
    ("x_std", lambda a: a.pop("x_std")),
    ("metadata", lambda a: a.pop("metadata")),
    ("enc_W1", lambda a: a["enc_W1"].__setitem__((0, 0), np.nan)),
    ("enc_b3", lambda a: a["enc_b3"].__setitem__(0, np.inf)),
    ("A", lambda a: a["A"].__setitem__((2, 3), np.nan)),
    ("metadata.n_K", lambda a: a.__setitem__(
        "metadata", np.array(json.dumps({k: v for k, v in json.loads(str(a["metadata"])).items() if k != "n_K"})))),
    ("x_std", lambda a: a["x_std"].__setitem__(0, -1.0)),
    ("A", lambda a: a["A"].__setitem__((-1, 0), 0.5)),
])
def test_bad_artifacts_name_the_key(tmp_path, key, change):
    good = save_koopman(random_model(), tmp_path / "good.npz")
    bad = rewrite(good, tmp_path / "bad.npz", change)
    with pytest.raises(ConfigError) as err:
        load_koopman(bad)
    assert err.value.field == key and err.value.file == str(bad)


def test_layout_mismatch_and_missing_file(tmp_path):
    path = save_koopman(random_model(), tmp_path / "m.npz")
    with pytest.raises(ConfigError) as err:
        load_koopman(path, state_names=("X", "Y", "yaw", "vx", "vy", "omega"))
    assert err.value.field == "state_names"
    with pytest.raises(ConfigError) as err:
        load_koopman(path, state_names=NAMES, control_names=("delta_f", "a_x"))
    assert err.value.field == "control_names"
    with pytest.raises(ConfigError) as err:
        load_koopman(tmp_path / "nope.npz")
    assert err.value.field == "<file>"
    (tmp_path / "junk.npz").write_text("not a zip")
    with pytest.raises(ConfigError):
        load_koopman(tmp_path / "junk.npz")


def test_importing_the_inference_module_does_not_import_torch():
    code = ("import sys, vflpcd.core.dynamics.koopman as k; k.KoopmanModel; "
            "sys.exit(1 if 'torch' in sys.modules else 0)")
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


@pytest.mark.parametrize("name,states,controls,n_K,schedule", [
    ("dynamic_bicycle", ("X", "Y", "psi", "vx", "vy", "omega"), ("a_x", "delta_f"), 10, None),
    ("dynamic_bicycle_scheduled", ("X", "Y", "psi", "vx", "vy", "omega"), ("a_x", "delta_f"), 10, "vx"),
    ("quadrotor", ("X", "Y", "Z", "vx", "vy", "vz"), ("ax", "ay", "az"), 18, None),
])
def test_shipped_models_load(name, states, controls, n_K, schedule):
    path = config_dir() / "models" / f"{name}.npz"
    model = load_koopman(path, state_names=states, control_names=controls)
    assert model.n_K == n_K and model.n_u == len(controls) and model.dt == pytest.approx(0.05)
    assert model.schedule == schedule
    assert path.stat().st_size < 1_000_000
    manifest = json.loads(path.with_suffix(".manifest.json").read_text())
    assert manifest["seed"] == 0 and "collect" in manifest["data_command"] and "train_koopman" in manifest["command"]
    assert manifest["train_fingerprint"] == model.metadata["fingerprint"]
    # a short open-loop prediction stays finite and starts at x0
    x0 = np.zeros(len(states))
    x0[3] = 5.0
    pred = model.rollout(x0, np.zeros((20, len(controls))))
    assert np.all(np.isfinite(pred)) and np.array_equal(pred[0], x0)
