import logging
from pathlib import Path

import numpy as np
import pytest

import vflpcd
from vflpcd.base.errors import ConfigError
from vflpcd.training.datasets import (CARSIM_CONTROLS, CARSIM_STATES, Log, fingerprint, load_carsim, load_log,
                                      load_logs, save_log, split_by_log)

CARSIM = Path(vflpcd.__file__).resolve().parents[2] / "shared" / "data" / "carsim_dclass_suv"
needs_carsim = pytest.mark.skipif(not CARSIM.is_dir(), reason=f"CarSim logs not present at {CARSIM}")


def make_log(name="a", n=50, seed=0, **kw):
    rng = np.random.default_rng(seed)
    return Log(name, rng.normal(size=(n, 3)), rng.normal(size=(n, 2)), 0.05, ("X", "Y", "yaw"), ("u1", "u2"), **kw)


def write_carsim(path, n=20, **override):
    t = 0.01 + 0.05 * np.arange(n)
    cols = {"t": t, **{k: np.linspace(0, 1, n) for k in CARSIM_STATES + CARSIM_CONTROLS}}
    cols.update(override)
    cols = {k: v for k, v in cols.items() if v is not None}
    np.savez(path, **cols)
    return path


@needs_carsim
def test_carsim_loader_reads_the_real_logs():
    logs = load_carsim(CARSIM)
    assert [lg.name for lg in logs] == [f"unit_{i:02d}" for i in range(1, 31)]
    raw = np.load(CARSIM / "unit_07.npz")
    lg = logs[6]
    assert lg.state_names == CARSIM_STATES and lg.control_names == CARSIM_CONTROLS
    assert lg.dt == 0.05
    assert lg.states.dtype == np.float64 and lg.states.shape == (raw["t"].shape[0], 6)
    assert lg.controls.shape == (raw["t"].shape[0], 3)
    for i, k in enumerate(CARSIM_STATES):
        np.testing.assert_array_equal(lg.states[:, i], raw[k])  # yaw kept unwrapped as logged
    for i, k in enumerate(CARSIM_CONTROLS):
        np.testing.assert_array_equal(lg.controls[:, i], raw[k])
    assert sum(lg.n_samples for lg in logs) > 250_000
    assert all(lg.dropped_rows == 0 and lg.breaks == () for lg in logs)


@needs_carsim
def test_split_of_real_logs_is_by_whole_logs():
    logs = load_carsim(CARSIM)
    val_names = [f"unit_{i:02d}" for i in range(25, 31)]
    train, val = split_by_log(logs, val_names)
    assert [lg.name for lg in val] == val_names
    assert len(train) == 24 and not {lg.name for lg in train} & set(val_names)
    assert sum(lg.n_samples for lg in train + val) == sum(lg.n_samples for lg in logs)


def test_split_by_log_rejects_unknown_and_duplicate_names():
    logs = [make_log("a"), make_log("b"), make_log("c")]
    train, val = split_by_log(logs, ["b"])
    assert [lg.name for lg in train] == ["a", "c"] and [lg.name for lg in val] == ["b"]
    assert val[0] is logs[1]  # whole logs, untouched
    with pytest.raises(ValueError, match="unknown"):
        split_by_log(logs, ["b", "zz"])
    with pytest.raises(ValueError, match="unique"):
        split_by_log([make_log("a"), make_log("a", seed=1)], ["a"])


def test_non_finite_rows_are_dropped_counted_and_logged(caplog):
    rng = np.random.default_rng(1)
    states, controls = rng.normal(size=(30, 3)), rng.normal(size=(30, 2))
    states[5, 1] = np.nan
    controls[6, 0] = np.inf
    states[20] = -np.inf
    with caplog.at_level(logging.WARNING, logger="vflpcd.training.datasets"):
        lg = Log("x", states, controls, 0.05, ("X", "Y", "yaw"), ("u1", "u2"))
    assert lg.dropped_rows == 3 and lg.n_samples == 27
    assert np.all(np.isfinite(lg.states)) and np.all(np.isfinite(lg.controls))
    np.testing.assert_array_equal(lg.states[5], states[7])
    assert lg.breaks == (5, 18)
    assert lg.segments() == [(0, 5), (5, 18), (18, 27)]
    assert list(lg.window_starts(6, 1)) == list(range(5, 13)) + list(range(18, 22))
    assert sum("dropped 3 of 30 rows" in r.getMessage() for r in caplog.records) == 1


def test_log_validates_shapes():
    with pytest.raises(ConfigError, match="states"):
        Log("a", np.zeros((5, 2)), np.zeros((5, 2)), 0.05, ("X", "Y", "yaw"), ("u1", "u2"))
    with pytest.raises(ConfigError, match="controls"):
        Log("a", np.zeros((5, 3)), np.zeros((4, 2)), 0.05, ("X", "Y", "yaw"), ("u1", "u2"))
    with pytest.raises(ConfigError, match="dt"):
        Log("a", np.zeros((5, 3)), np.zeros((5, 2)), 0.0, ("X", "Y", "yaw"), ("u1", "u2"))


def test_save_load_round_trip_and_identical_bytes(tmp_path):
    states = np.random.default_rng(2).normal(size=(40, 3))
    states[10] = np.nan
    lg = Log("run", states, np.ones((40, 2)), 0.05, ("X", "Y", "yaw"), ("u1", "u2"))
    p1, p2 = save_log(lg, tmp_path / "a.npz"), save_log(lg, tmp_path / "b.npz")
    assert p1.read_bytes() == p2.read_bytes()
    back = load_log(p1)
    assert (back.name, back.dt, back.state_names, back.control_names) == (lg.name, lg.dt, lg.state_names, lg.control_names)
    np.testing.assert_array_equal(back.states, lg.states)
    np.testing.assert_array_equal(back.controls, lg.controls)
    assert back.breaks == lg.breaks == (10,) and back.dropped_rows == 1
    assert fingerprint([back]) == fingerprint([lg])
    with np.load(p1) as npz:
        assert {"states", "controls", "dt", "state_names", "control_names", "name"} <= set(npz.files)


def test_bad_files_name_file_and_field(tmp_path):
    with pytest.raises(ConfigError) as e:
        load_log(tmp_path / "nope.npz")
    assert e.value.field == "<file>" and "nope.npz" in e.value.file
    lg = make_log()
    good = save_log(lg, tmp_path / "good.npz")
    with np.load(good) as npz:
        arrays = {k: npz[k] for k in npz.files}
    no_controls = tmp_path / "no_controls.npz"
    np.savez(no_controls, **{k: v for k, v in arrays.items() if k != "controls"})
    with pytest.raises(ConfigError) as e:
        load_log(no_controls)
    assert e.value.field == "controls" and e.value.file == str(no_controls)
    flat = tmp_path / "flat.npz"
    np.savez(flat, **{**arrays, "states": np.zeros(50)})
    with pytest.raises(ConfigError) as e:
        load_log(flat)
    assert e.value.field == "states" and e.value.file == str(flat)
    wrong_cols = tmp_path / "cols.npz"
    np.savez(wrong_cols, **{**arrays, "states": np.zeros((50, 4))})
    with pytest.raises(ConfigError) as e:
        load_log(wrong_cols)
    assert e.value.field == "states" and str(wrong_cols) in str(e.value)
    junk = tmp_path / "junk.npz"
    junk.write_text("not a zip")
    with pytest.raises(ConfigError, match="junk.npz: <file>"):
        load_log(junk)


def test_bad_carsim_files(tmp_path):
    with pytest.raises(ConfigError, match="folder not found"):
        load_carsim(tmp_path / "missing")
    with pytest.raises(ConfigError, match="no unit_"):
        load_carsim(tmp_path)
    write_carsim(tmp_path / "unit_01.npz", yaw=None)
    with pytest.raises(ConfigError) as e:
        load_carsim(tmp_path)
    assert e.value.field == "yaw" and e.value.file.endswith("unit_01.npz")
    write_carsim(tmp_path / "unit_01.npz", t=0.1 * np.arange(20))
    with pytest.raises(ConfigError) as e:
        load_carsim(tmp_path)
    assert e.value.field == "t"
    write_carsim(tmp_path / "unit_01.npz", vx=np.zeros(19))
    with pytest.raises(ConfigError) as e:
        load_carsim(tmp_path)
    assert e.value.field == "vx"
    vy = np.linspace(0, 1, 20)
    vy[3] = np.nan
    write_carsim(tmp_path / "unit_01.npz", vy=vy)
    (lg,) = load_carsim(tmp_path)
    assert lg.dropped_rows == 1 and lg.n_samples == 19 and lg.dt == 0.05


def test_load_logs_from_folder_and_list(tmp_path):
    save_log(make_log("b", seed=1), tmp_path / "b.npz")
    save_log(make_log("a", seed=2), tmp_path / "a.npz")
    write_carsim(tmp_path / "unit_05.npz")
    logs = load_logs(tmp_path)
    assert [lg.name for lg in logs] == ["a", "b", "unit_05"]
    assert [lg.name for lg in load_logs([tmp_path / "b.npz", str(tmp_path / "a.npz")])] == ["b", "a"]
    save_log(make_log("a", seed=3), tmp_path / "a2.npz")
    with pytest.raises(ConfigError, match="already used"):
        load_logs(tmp_path)
    with pytest.raises(ConfigError, match="not found"):
        load_logs([tmp_path / "zzz.npz"])


def test_fingerprint_identifies_the_set_of_logs():
    a, b = make_log("a"), make_log("b", seed=1)
    assert fingerprint([a, b]) == fingerprint([b, a])
    assert len(fingerprint([a])) == 64
    states = a.states.copy()
    states[3, 1] += 1e-12
    assert fingerprint([Log("a", states, a.controls, a.dt, a.state_names, a.control_names), b]) != fingerprint([a, b])
    assert fingerprint([make_log("c"), b]) != fingerprint([a, b])
