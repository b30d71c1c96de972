"""The flight log when the run does not end well: ``vflpcd run`` killed with SIGKILL leaves a log
that the ``mcap`` package's readers read to within a second of the kill; a disk that fills up
under the daemon stops the log, not the vehicle, and the summary says when and why."""

from __future__ import annotations

import json
import os
import time

import numpy as np
import pytest

from fulldisk import FullDisk
from mcap_readers import READERS, mcap_messages
from processes import Proc
from vflpcd.app.run import run_mission
from vflpcd.config.mission import load_mission
from vflpcd.log.reader import read_flight_log
from vflpcd.log.summary import KILLED, log_stop_line, summary_lines

RATE = 50.0


def test_sigkill_leaves_a_log_every_mcap_reader_reads_to_within_a_second(mission_file, tmp_path):
    mission = mission_file(rate_hz=RATE)
    daemon = Proc("run", str(mission))
    try:
        daemon.wait_line("event=ready", 60)
        time.sleep(2.5)
        killed_ns = time.monotonic_ns()             # CLOCK_MONOTONIC: the daemon's stamp_ns clock
    finally:
        lingered = daemon.kill()
    assert daemon.p.returncode == -9 and lingered == []
    (opened,) = daemon.lines_with("event=flight_log ")
    assert 'crash_safe="readable by every MCAP reader up to its last commit, every 0.50 s' in opened[1]

    path = next((tmp_path / "logs").glob("*.mcap"))
    log = read_flight_log(path)
    assert log.truncated and log.stop_reason is None
    assert log_stop_line(log) == f"stopped at {log.t[-1]:.2f} s: {KILLED}"
    for reader in READERS:
        got = mcap_messages(path.read_bytes(), reader)
        ticks = [json.loads(m.data) for topic, m in got if topic == "/tick"]
        assert [tk["k"] for tk in ticks] == log.k.tolist()
        assert [m.log_time for topic, m in got if topic == "/tick"] == log.stamp_ns.tolist()
        assert {topic for topic, _ in got} == {"/header", "/tick", "/event"}
    lost_s = (killed_ns - int(log.stamp_ns[-1])) * 1e-9
    assert 0.0 < lost_s <= 1.0, f"the log ends {lost_s:.2f} s before the kill"
    assert log.t[-1] > 2.0
    # every tick that ran is in the log: k steps by one, except past deadlines the rate keeper
    # skipped because the tick before them started a whole period or more late
    steps = np.diff(log.k)
    skipped = steps - 1
    assert np.all(skipped >= 0)
    assert np.all(log.lateness_s[:-1][skipped > 0] >= skipped[skipped > 0] / RATE - 1e-6), \
        f"ticks missing from the log after on-time ticks: k {log.k[:-1][skipped > 0].tolist()}"


@pytest.mark.parametrize("slack", [4096, 0], ids=["room_for_a_last_record", "no_room_at_all"])
def test_a_full_disk_stops_the_log_not_the_vehicle_and_the_summary_says_so(mission_file, tmp_path, monkeypatch,
                                                                            slack):
    mission = load_mission(mission_file(rate_hz=RATE))
    disk = FullDisk(tmp_path / "logs", limit=50_000, slack=slack)        # the header and about 1 s of ticks
    monkeypatch.setattr(os, "pwrite", disk)
    result = run_mission(mission, stop_after_s=3.0)
    monkeypatch.setattr(os, "pwrite", disk.real)
    loop, outcome = result.outcome.loop, result.outcome
    assert disk.failures >= 1 and result.log_stop == "disk full (ENOSPC)"
    assert outcome.code == 0 and outcome.reason == "ran 3 s"            # controlled to the end, braked
    assert loop.counters.commands > 2.5 * RATE and loop.platform.at_rest

    log = read_flight_log(result.log_path)
    run_s = loop.mission_time(loop.last_tick_ns)
    assert log.truncated and 0.3 < log.t[-1] < run_s - 1.0
    assert log.stop_reason == ("disk full (ENOSPC)" if slack else None)
    lines = summary_lines(log, mission.scenario, outcome, result.log_stop)
    text = "\n".join(lines)
    assert f"stopped at {log.t[-1]:.2f} s of a {run_s:.2f} s run: disk full (ENOSPC)" in text
    ticks = next(line for line in lines if line.startswith("ticks"))
    assert ticks.split()[1:] == [str(loop.counters.ticks), "at", f"{RATE:g}", "Hz", "over", f"{run_s:.2f}", "s",
                                 f"({len(log)}", "logged,", "to", f"{log.t[-1]:.2f}", "s)"]
    assert "killed" not in text
    for reader in READERS:                                              # what was written stays readable
        assert sum(topic == "/tick" for topic, _ in mcap_messages(result.log_path.read_bytes(), reader)) == len(log)
