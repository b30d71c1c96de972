import numpy as np
import pytest

from sim.collect import collect, main
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.config.vehicles import QuadrotorParams
from vflpcd.training.datasets import load_log, load_logs


def test_collect_is_seeded(tmp_path):
    a = collect("dynamic_bicycle", 0.2, 3, tmp_path / "a")
    b = collect("dynamic_bicycle", 0.2, 3, tmp_path / "b")
    c = collect("dynamic_bicycle", 0.2, 4, tmp_path / "c")
    assert [p.name for p in a] == ["dynamic_bicycle_3_000.npz"]
    assert a[0].read_bytes() == b[0].read_bytes()
    assert not np.array_equal(load_log(a[0]).controls, load_log(c[0]).controls)


def test_bicycle_duration_limits_and_speed_range(tmp_path):
    paths = collect("dynamic_bicycle", 2.5, 0, tmp_path)
    assert [p.name for p in paths] == [f"dynamic_bicycle_0_{k:03d}.npz" for k in range(3)]
    logs = load_logs(tmp_path)
    assert [lg.n_samples for lg in logs] == [1200, 1200, 600]
    assert sum(lg.duration for lg in logs) == pytest.approx(150.0)
    assert all(lg.dt == 0.05 and lg.dropped_rows == 0 for lg in logs)
    assert logs[0].state_names == ("X", "Y", "psi", "vx", "vy", "omega")
    assert logs[0].control_names == ("a_x", "delta_f")
    lim = BicycleConfig.load("nominal").limits
    u = np.concatenate([lg.controls for lg in logs])
    s = np.concatenate([lg.states for lg in logs])
    assert u[:, 0].min() >= lim.a_min and u[:, 0].max() <= lim.a_max
    assert np.abs(u[:, 1]).max() <= lim.delta_max
    assert u[:, 0].std() > 0.3 and u[:, 1].std() > 0.02  # actually excited
    assert 1.5 < s[:, 3].min() and s[:, 3].max() < 16.0   # the speed-holding term works
    assert np.abs(np.diff(s[:, 2])).max() < 0.1            # heading unwrapped
    # logs continue one another (one run split into minutes)
    assert np.linalg.norm(logs[1].states[0, :2] - logs[0].states[-1, :2]) < 1.0


def test_quadrotor_duration_limits_and_box(tmp_path):
    paths = collect("quadrotor", 0.5, 1, tmp_path)
    (lg,) = [load_log(p) for p in paths]
    assert paths[0].name == "quadrotor_1_000.npz"
    assert lg.n_samples == 600 and lg.duration == pytest.approx(30.0)
    assert lg.state_names == ("X", "Y", "Z", "vx", "vy", "vz") and lg.control_names == ("ax", "ay", "az")
    assert np.abs(lg.controls).max() <= QuadrotorParams.from_toml().accel_max + 1e-9
    assert lg.controls.std(axis=0).min() > 0.3
    assert lg.states[:, 2].min() > 0.0 and np.abs(lg.states[:, :2]).max() < 25.0
    assert np.linalg.norm(lg.states[:, 3:], axis=1).max() < 7.0


def test_command_line(tmp_path, capsys):
    assert main(["quadrotor", "--minutes", "0.05", "--seed", "2", "--out", str(tmp_path)]) == 0
    assert (tmp_path / "quadrotor_2_000.npz").is_file()
    capsys.readouterr()
    assert main(["boat", "--minutes", "1"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "unknown plant" in err
    assert main(["quadrotor", "--minutes", "0"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "positive" in err
    assert main(["quadrotor"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    with pytest.raises(ValueError):
        collect("boat", 1, 0, tmp_path)
    with pytest.raises(ValueError):
        collect("quadrotor", -1, 0, tmp_path)
