"""FlightRecorder: round trip through the MCAP file, errors, a full disk, and a process killed
with SIGKILL."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap
import time
from datetime import datetime
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader

from fulldisk import FullDisk
from mcap_readers import READERS, mcap_messages
from vflpcd.log.writer import FlightRecorder, log_path
from vflpcd.log.records import Event, MissionHeader, ObstacleRecord, TickRecord
from vflpcd.base.errors import ConfigError
from vflpcd.log.reader import read_flight_log
from vflpcd.log.summary import KILLED, log_stop_line

LOGGER = "vflpcd.log.writer"
REPO = Path(__file__).resolve().parents[3]


def header() -> MissionHeader:
    return MissionHeader(
        vehicle_id="car1", platform="inproc", controller="vflpc", dim=2, rate_hz=100.0,
        state_names=("X", "Y", "psi"), control_names=("a_x", "delta_f"),
        path=((0.0, 0.0), (10.0, 0.0), (20.0, 5.0)),
        obstacles=({"id": "rock", "center": (5.0, 1.0), "velocity": (0.0, 0.0), "radius": 0.5,
                    "outline": ((5.5, 1.0), (5.0, 1.5), (4.5, 1.0), (5.0, 0.5), (5.5, 1.0))},),
        mission_file="missions/test.toml", model_file="models/car.npz")


def tick(k: int) -> TickRecord:
    """Tick k: no state at k % 97 == 0, no command at k % 50 == 1, no plan before k = 3; the
    obstacle "walker" moves and is seen only for 200 <= k < 700."""
    t = 0.01 * k
    obstacles = [ObstacleRecord("rock", (5.0, 1.0), (0.0, 0.0), 0.5, "mission")]
    if 200 <= k < 700:
        obstacles.append(ObstacleRecord("walker", (8.0, -3.0 + 0.01 * k), (0.0, 1.0), 0.4, "perception"))
    return TickRecord(
        k=k, t=t, stamp_ns=1_000_000_000 + 10_000_000 * k,
        mode="failsafe" if k >= 990 else "running",
        state=() if k % 97 == 0 else (t, 0.1 * np.sin(t), 0.01 * k),
        state_age_s=0.002, reference=() if k < 3 else (t + 0.1, 0.0),
        command=() if k % 50 == 1 else (0.5 * np.cos(t), -0.1 + 1e-4 * k),
        lateness_s=1e-5 * (k % 7), compute_s=1e-3 + 1e-6 * k, overrun=k % 333 == 0,
        threats=("walker",) if 300 <= k < 400 else (), plan_version=1 + k // 500, model_version=k // 250,
        obstacles=tuple(obstacles))


EVENTS = [
    Event(0.0, 1_000_000_000, "started", {"rate_hz": 100.0, "controller": "vflpc"}),
    Event(0.05, 1_005_000_000, "ready"),
    Event(9.9, 1_990_000_000, "failsafe", {"reason": "stale_state", "action": "brake"}),
    Event(9.99, 1_999_000_000, "stopping", {"reason": "failsafe"}),
]


def test_round_trip_returns_identical_values(tmp_path):
    path = tmp_path / "run.mcap"
    ticks = [tick(k) for k in range(1000)]
    rec = FlightRecorder(path, header(), flush_period_s=0.05)
    rec.record_event(EVENTS[0])
    rec.record_event(EVENTS[1])
    for tk in ticks:
        rec.record_tick(tk)
    rec.record_event(EVENTS[2])
    rec.record_event(EVENTS[3])
    rec.close()
    assert (rec.written, rec.dropped, rec.failed) == (1004, 0, False)

    log = read_flight_log(path)
    assert not log.truncated
    assert log.header == header()
    assert log.events == EVENTS
    assert len(log) == 1000
    np.testing.assert_array_equal(log.k, np.arange(1000))
    np.testing.assert_array_equal(log.t, [tk.t for tk in ticks])
    assert log.stamp_ns.dtype == np.int64
    np.testing.assert_array_equal(log.stamp_ns, [tk.stamp_ns for tk in ticks])
    assert list(log.mode) == [tk.mode for tk in ticks]
    for k, tk in enumerate(ticks):
        for arr, value, width in ((log.state, tk.state, 3), (log.reference, tk.reference, 2),
                                  (log.command, tk.command, 2)):
            if value:
                assert tuple(arr[k]) == value
            else:
                assert arr[k].shape == (width,) and np.isnan(arr[k]).all()
    for name in ("state_age_s", "lateness_s", "compute_s", "overrun", "plan_version", "model_version"):
        np.testing.assert_array_equal(getattr(log, name), [getattr(tk, name) for tk in ticks])
    assert log.overrun.dtype == bool
    assert log.threats == [tk.threats for tk in ticks]
    assert set(log.obstacles) == {"rock", "walker"}
    assert log.obstacle_radius == {"rock": 0.5, "walker": 0.4}
    np.testing.assert_array_equal(log.obstacles["rock"], np.tile([5.0, 1.0], (1000, 1)))
    walker = log.obstacles["walker"]
    assert walker.shape == (1000, 2)
    assert np.isnan(walker[:200]).all() and np.isnan(walker[700:]).all()
    np.testing.assert_array_equal(walker[200:700], [tk.obstacles[1].center for tk in ticks[200:700]])


def test_file_is_valid_mcap_with_json_schemas(tmp_path):
    path = tmp_path / "run.mcap"
    with FlightRecorder(path, header()) as rec:
        rec.record_tick(tick(5))
        rec.record_event(EVENTS[0])
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert set(topics) == {"/header", "/tick", "/event"}
        for channel in topics.values():
            schema = summary.schemas[channel.schema_id]
            assert channel.message_encoding == "json" and schema.encoding == "jsonschema"
        messages = [(ch.topic, m.log_time, m.publish_time) for _, ch, m in reader.iter_messages()]
    assert ("/tick", tick(5).stamp_ns, tick(5).stamp_ns) in messages
    assert ("/event", EVENTS[0].stamp_ns, EVENTS[0].stamp_ns) in messages
    assert [m[0] for m in messages].count("/header") == 1


def test_never_raises_after_close_and_counts_dropped(tmp_path):
    rec = FlightRecorder(tmp_path / "run.mcap", header())
    rec.record_tick(tick(0))
    rec.close()
    rec.close()
    rec.record_tick(tick(1))
    rec.record_event(EVENTS[0])
    assert (rec.written, rec.dropped, rec.failed) == (1, 2, False)
    assert not rec._thread.is_alive()
    assert len(read_flight_log(tmp_path / "run.mcap")) == 1


def test_write_error_is_logged_once_and_stops_writing(tmp_path, caplog):
    rec = FlightRecorder(tmp_path / "run.mcap", header(), flush_period_s=0.01)
    full = os.open("/dev/full", os.O_WRONLY)
    try:  # the disk fills up under the open file
        os.dup2(full, rec._file.fileno())
    finally:
        os.close(full)
    with caplog.at_level(logging.ERROR, logger=LOGGER):
        for k in range(300):
            rec.record_tick(tick(k))
            if k % 50 == 0:
                time.sleep(0.03)
        deadline = time.monotonic() + 2.0
        while not rec.failed and time.monotonic() < deadline:
            time.sleep(0.01)
        assert rec.failed
        rec.record_tick(tick(300))
        rec.close()
    errors = [r for r in caplog.records if r.name == LOGGER and r.levelno == logging.ERROR]
    assert len(errors) == 1 and "event=flight_log_write_failed" in errors[0].getMessage()
    assert "reason=disk full (ENOSPC)" in errors[0].getMessage() and "stop_recorded=no" in errors[0].getMessage()
    assert rec.stop_reason == "disk full (ENOSPC)"
    assert rec.written + rec.dropped == 301 and rec.dropped > 0
    assert not rec._thread.is_alive()


def tick_ids(path: Path, reader: str) -> list[int]:
    """The k of every /tick message as the mcap package's ``reader`` reads the file."""
    return [json.loads(m.data)["k"] for topic, m in mcap_messages(path.read_bytes(), reader) if topic == "/tick"]


@pytest.mark.parametrize("slack", [4096, 0], ids=["room_for_a_last_record", "no_room_at_all"])
def test_a_full_disk_stops_the_log_and_the_reason_is_kept(tmp_path, monkeypatch, caplog, slack):
    path = tmp_path / "run.mcap"
    disk = FullDisk(tmp_path, limit=40_000, slack=slack)
    monkeypatch.setattr(os, "pwrite", disk)
    with caplog.at_level(logging.ERROR, logger=LOGGER):
        rec = FlightRecorder(path, header(), flush_period_s=0.02)
        for k in range(400):
            rec.record_tick(tick(k))
            if k % 10 == 0:
                time.sleep(0.01)
        rec.close()
    monkeypatch.setattr(os, "pwrite", disk.real)
    assert rec.failed and disk.failures >= 1
    assert rec.stop_reason == "disk full (ENOSPC)"
    assert rec.written + rec.dropped == 400 and rec.dropped > 0
    (error,) = [r.getMessage() for r in caplog.records if r.name == LOGGER]
    assert "event=flight_log_write_failed" in error and "reason=disk full (ENOSPC)" in error
    assert f"stop_recorded={'yes' if slack else 'no'}" in error
    assert path.stat().st_size <= 40_000 + slack

    log = read_flight_log(path)
    assert log.truncated and 0 < len(log) == rec.written < 400
    np.testing.assert_array_equal(log.k, np.arange(len(log)))
    for reader in READERS:                # what was written stays readable by all
        assert tick_ids(path, reader) == list(range(len(log)))
    if slack:                                           # the log says why it stopped
        assert log.events[-1].kind == "log_stopped"
        assert log.events[-1].detail == {"reason": "disk full (ENOSPC)", "errno": "ENOSPC"}
        assert log.events[-1].t >= log.t[-1]
        assert log_stop_line(log) == f"stopped at {log.t[-1]:.2f} s: disk full (ENOSPC)"
    else:                                               # only the recorder can say it
        assert log.stop_reason is None
        assert log_stop_line(log) == f"stopped at {log.t[-1]:.2f} s: {KILLED}"
        assert log_stop_line(log, (1000, 10.0), rec.stop_reason) == \
            f"stopped at {log.t[-1]:.2f} s of a 10.00 s run: disk full (ENOSPC)"


def test_unwritable_directory_is_a_config_error(tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("not a directory")
    with pytest.raises(ConfigError) as err:
        FlightRecorder(blocker / "logs" / "run.mcap", header())
    assert err.value.field == "log.dir" and err.value.file == str(blocker / "logs" / "run.mcap")
    with pytest.raises(ConfigError) as err:
        log_path(blocker / "logs", "car1")
    assert err.value.field == "log.dir"


def test_log_path_names_vehicle_and_local_time(tmp_path):
    p = log_path(tmp_path / "a" / "b", "car1", now=datetime(2024, 3, 9, 14, 5, 7))
    assert p == tmp_path / "a" / "b" / "car1-20240309-140507.mcap"
    assert p.parent.is_dir()


CHILD = textwrap.dedent("""
    import sys, time
    from vflpcd.log.writer import FlightRecorder
    from vflpcd.log.records import MissionHeader, TickRecord

    header = MissionHeader("car1", "inproc", "vflpc", 2, 100.0, ("X", "Y", "psi"), ("a_x", "delta_f"),
                           ((0.0, 0.0), (10.0, 0.0)), (), "m.toml")
    rec = FlightRecorder(sys.argv[1], header, flush_period_s=0.5)
    t0 = time.monotonic()
    k = 0
    while True:
        delay = t0 + 0.01 * k - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        rec.record_tick(TickRecord(k=k, t=0.01 * k, stamp_ns=time.monotonic_ns(), mode="running",
                                   state=(0.01 * k, 0.0, 0.0), state_age_s=0.001, reference=(0.01 * k, 0.0),
                                   command=(0.1, 0.0), lateness_s=0.0, compute_s=0.001, overrun=False))
        k += 1
        if k % 10 == 0:
            print(k, flush=True)
""")


def test_sigkill_loses_at_most_the_last_second(tmp_path):
    path = tmp_path / "killed.mcap"
    script = tmp_path / "child.py"
    script.write_text(CHILD)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))}
    proc = subprocess.Popen([sys.executable, str(script), str(path)], stdout=subprocess.PIPE, text=True,
                            cwd=tmp_path, env=env)
    last = 0
    try:
        first = proc.stdout.readline()
        assert first.strip(), "the child printed nothing"
        last = int(first)
        t_first = time.monotonic()
        while time.monotonic() - t_first < 2.5:
            line = proc.stdout.readline()
            if not line:
                break
            last = int(line)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(5)
        proc.stdout.close()
    assert proc.returncode == -signal.SIGKILL
    assert last >= 200

    log = read_flight_log(path)
    assert log.truncated and log.stop_reason is None
    assert log.header.vehicle_id == "car1"
    assert len(log) >= last - 100, (len(log), last)
    np.testing.assert_array_equal(log.k, np.arange(len(log)))
    for reader in READERS:
        assert tick_ids(path, reader) == list(range(len(log)))


def test_a_bad_record_is_skipped_and_logged_once(tmp_path, caplog):
    path = tmp_path / "run.mcap"
    with caplog.at_level(logging.ERROR, logger=LOGGER):
        with FlightRecorder(path, header()) as rec:
            rec.record_tick(tick(0))
            rec.record_event(Event(0.0, -1, "ready"))
            rec.record_event(Event(0.0, 5, "failsafe", {"reason": object()}))
            rec.record_tick(tick(1))
    assert (rec.written, rec.dropped, rec.failed) == (2, 2, False)
    errors = [r for r in caplog.records if r.name == LOGGER]
    assert len(errors) == 1 and "event=flight_log_bad_record" in errors[0].getMessage()
    log = read_flight_log(path)
    np.testing.assert_array_equal(log.k, [0, 1])
    assert not log.truncated and log.events == []
