"""read_flight_log on bad and cut files; plot_flight_log on small 2-D and 3-D logs."""

from __future__ import annotations

import json

import numpy as np
import pytest
from mcap.writer import Writer

from vflpcd.log.writer import FlightRecorder
from vflpcd.log.records import Event, MissionHeader, ObstacleRecord, TickRecord
from vflpcd.base.errors import ConfigError
from vflpcd.log.reader import read_flight_log
from vflpcd.log.plot import main, plot_flight_log

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def car_header() -> MissionHeader:
    square = ((6.5, 1.0), (6.5, 2.0), (5.5, 2.0), (5.5, 1.0), (6.5, 1.0))
    return MissionHeader(
        vehicle_id="car1", platform="inproc", controller="vflpc", dim=2, rate_hz=50.0,
        state_names=("X", "Y", "psi", "vx", "vy", "omega"), control_names=("a_x", "delta_f"),
        path=tuple((float(x), 0.1 * x) for x in range(0, 21, 2)),
        obstacles=({"id": "box", "center": (6.0, 1.5), "velocity": (0.0, 0.0), "radius": 0.71, "outline": square},
                   {"id": "walker", "center": (12.0, -2.0), "velocity": (0.0, 1.0), "radius": 0.4}),
        mission_file="m.toml")


def drone_header() -> MissionHeader:
    return MissionHeader(
        vehicle_id="uav1", platform="inproc", controller="vflpc", dim=3, rate_hz=50.0,
        state_names=("X", "Y", "Z", "vx", "vy", "vz"), control_names=("ax", "ay", "az"),
        path=((0.0, 0.0, 2.0), (10.0, 0.0, 3.0), (20.0, 5.0, 3.0)),
        obstacles=({"id": "pole", "center": (8.0, 0.5, 0.0), "velocity": (0.0, 0.0, 0.0), "radius": 0.5},),
        mission_file="m.toml")


def write_log(path, header: MissionHeader, n: int = 200) -> None:
    d, n_x, n_u = header.dim, len(header.state_names), len(header.control_names)
    rng = np.random.default_rng(0)
    with FlightRecorder(path, header) as rec:
        rec.record_event(Event(0.0, 0, "started", {"rate_hz": header.rate_hz}))
        for k in range(n):
            t = k / header.rate_hz
            pos = [t, 0.1 * t + 0.05 * np.sin(t), 2.0 + 0.05 * t][:d]
            obstacles = [ObstacleRecord(o["id"], tuple(np.add(o["center"], t * np.asarray(o["velocity"]))),
                                        o["velocity"], o["radius"], "mission") for o in header.obstacles]
            rec.record_tick(TickRecord(
                k=k, t=t, stamp_ns=int(t * 1e9), mode="failsafe" if k > 0.9 * n else "running",
                state=() if k == 5 else tuple(pos + [0.1] * (n_x - d)), state_age_s=0.001,
                reference=tuple(np.add(pos, 0.02)), command=() if k == 7 else tuple(rng.normal(size=n_u)),
                lateness_s=abs(rng.normal(2e-4, 1e-4)), compute_s=abs(rng.normal(3e-3, 1e-3)),
                overrun=k == 50, obstacles=tuple(obstacles)))
        rec.record_event(Event(0.9 * n / header.rate_hz, 0, "failsafe", {"reason": "test", "action": "brake"}))


def test_missing_file(tmp_path):
    with pytest.raises(ConfigError, match="file not found") as err:
        read_flight_log(tmp_path / "nope.mcap")
    assert err.value.field == "<file>" and err.value.file == str(tmp_path / "nope.mcap")


@pytest.mark.parametrize("content", [b"", b"abc", b"not an mcap file at all\n" * 10])
def test_not_mcap(tmp_path, content):
    path = tmp_path / "x.mcap"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match="not an MCAP file") as err:
        read_flight_log(path)
    assert err.value.field == "<file>"


def test_mcap_without_header(tmp_path):
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start()
        sid = w.register_schema("x", "jsonschema", b"{}")
        cid = w.register_channel("/tick", "json", sid)
        w.add_message(cid, 1, json.dumps({"k": 0}).encode(), 1)
        w.finish()
    with pytest.raises(ConfigError, match="no /header message") as err:
        read_flight_log(path)
    assert err.value.field == "<file>"


def test_every_cut_reads_a_prefix(tmp_path):
    full = tmp_path / "full.mcap"
    write_log(full, car_header(), n=20)
    data = full.read_bytes()
    complete = read_flight_log(full)
    assert not complete.truncated and len(complete) == 20
    cut = tmp_path / "cut.mcap"
    previous = 0
    header_end = None
    for size in range(8, len(data), 5):
        cut.write_bytes(data[:size])
        try:
            log = read_flight_log(cut)
        except ConfigError as exc:  # cut before or inside the header message
            assert header_end is None and "no /header" in str(exc)
            continue
        header_end = header_end or size
        assert log.truncated or size >= len(data) - 8
        assert len(log) >= previous
        previous = len(log)
        np.testing.assert_array_equal(log.k, np.arange(len(log)))
        np.testing.assert_array_equal(log.state, complete.state[: len(log)])
    assert previous == 20


@pytest.mark.parametrize("make_header", [car_header, drone_header])
def test_plot_writes_png(tmp_path, make_header, capsys):
    path = tmp_path / "run.mcap"
    write_log(path, make_header())
    log = read_flight_log(path)
    assert log.obstacles and log.state.shape == (200, len(log.header.state_names))
    out = plot_flight_log(log, tmp_path / "fig.png")
    assert out.read_bytes()[:8] == PNG_MAGIC and out.stat().st_size > 10_000
    default = main(path)
    assert default == path.with_suffix(".png") and default.read_bytes()[:8] == PNG_MAGIC
    assert f"wrote {default}" in capsys.readouterr().out


def test_plot_of_log_without_ticks(tmp_path):
    path = tmp_path / "empty.mcap"
    FlightRecorder(path, car_header()).close()
    log = read_flight_log(path)
    assert len(log) == 0 and log.state.shape == (0, 6) and log.reference.shape == (0, 2)
    assert plot_flight_log(log, tmp_path / "e.png").stat().st_size > 0


def test_a_fifo_or_a_device_is_refused_without_blocking(tmp_path):
    import os

    fifo = tmp_path / "log.mcap"
    os.mkfifo(fifo)
    for path, what in ((fifo, "a FIFO"), ("/dev/zero", "a character device")):
        with pytest.raises(ConfigError, match=f"not a regular file \\({what}\\)"):
            read_flight_log(path)
