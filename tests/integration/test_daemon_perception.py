"""Moving obstacles from perception reach the controller through a live Zenoh session, invalid
messages become aggregated events, stale ones are dropped; a flood is bounded by the message
budget without starving the replans, and values beyond the mission's world are rejected."""

import json
import subprocess
import sys
import threading
import time

import numpy as np

from loopback import zenoh_peer
from vflpcd.log.reader import read_flight_log
from vflpcd.config.mission import load_mission
from vflpcd.app.run import run_mission
from vflpcd.log.summary import clearances
from vflpcd.config.scenarios import line_scenario_toml

KEY = "vflpc/t1/perception/obstacles"


publisher = zenoh_peer


def events(log, kind):
    return [e for e in log.events if e.kind == kind]


def test_perceived_walker_is_used_then_dropped_when_stale(mission_file, port):
    mission = load_mission(mission_file(rate_hz=20.0, telemetry_port=port,
                                        telemetry_extra="perception = true\nperception_max_age_s = 0.5"))

    def perceive():
        time.sleep(3.0)                                   # the daemon listens by then
        session = publisher(port)
        for i in range(40):                               # 2 s at 20 Hz: a walker 40 m ahead, crossing slowly
            msg = {"stamp": time.time(), "obstacles": [
                {"id": "walker", "shape": {"kind": "circle", "radius": 0.4},
                 "center": [60.0, 6.0 - 0.05 * i], "velocity": [0.0, -1.0]}]}
            session.put(KEY, json.dumps(msg))
            time.sleep(0.05)
        session.put(KEY, json.dumps({"stamp": time.time(), "obstacles": [{"id": "x"}]}))   # invalid
        time.sleep(0.5)
        session.close()                                   # then silence: the last message goes stale

    sender = threading.Thread(target=perceive)
    sender.start()
    result = run_mission(mission, stop_after_s=6.5)
    sender.join()
    log = read_flight_log(result.log_path)
    walker = log.obstacles.get("perception:walker")
    assert walker is not None, list(log.obstacles)
    seen = np.flatnonzero(np.all(np.isfinite(walker), axis=1))
    assert len(seen) >= 20                                # used while fresh ...
    assert log.t[seen[-1]] < log.t[-1] - 1.0              # ... and dropped once stale
    assert log.plan_version[seen[-1]] > log.plan_version[seen[0] - 1]   # the new obstacle caused a replan
    (rejected,) = events(log, "perception_rejected")
    assert rejected.detail["count"] == 1 and "obstacles[0]" in rejected.detail["reason"]


# --------------------------------------------------------------------------- a flood of valid messages
FLOOD = r"""
import json, random, sys, time, zenoh
port, rate, seconds = int(sys.argv[1]), float(sys.argv[2]), float(sys.argv[3])
cfg = zenoh.Config()
cfg.insert_json5("mode", '"peer"')
cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
cfg.insert_json5("scouting/multicast/enabled", "false")
session = zenoh.open(cfg)
pub = session.declare_publisher(sys.argv[4])
give_up = time.monotonic() + 60.0
while not pub.matching_status.matching and time.monotonic() < give_up:
    time.sleep(0.01)
rng = random.Random(7)
def picture(k):
    # 60 parked things beside the road whose ids change with every message (a tracker that renumbers)
    # and 4 walkers on the other side whose velocities jitter by +-0.5 m/s: every message is a new picture
    obs = [{"id": f"m{k}-{i}", "shape": {"kind": "circle", "radius": 0.5},
            "center": [3.0 + 1.8 * i, 14.0 + i % 3], "velocity": [0.0, 0.0]} for i in range(60)]
    obs += [{"id": f"walker-{j}", "shape": {"kind": "circle", "radius": 0.4}, "center": [10.0 + 25.0 * j, -15.0],
             "velocity": [rng.uniform(-0.5, 0.5), 0.0]} for j in range(4)]
    return json.dumps(obs).encode()
bodies = [picture(k) for k in range(256)]
t0 = time.monotonic()
sent = 0
while time.monotonic() < t0 + seconds:
    due = int((time.monotonic() - t0) * rate) + 1
    while sent < due:
        pub.put(b'{"stamp": %.6f, "obstacles": ' % time.time() + bodies[sent % len(bodies)] + b"}")
        sent += 1
    time.sleep(0.0005)
print(json.dumps({"sent": sent, "seconds": time.monotonic() - t0}), flush=True)
pub.undeclare()
session.close()
"""

BARREL = """
[guidance]
horizon = 30.0          # m: the first plan ends before the barrel, so only replans can pass it
[[obstacles]]
id = "barrel"
shape = "circle"
radius = 1.0
center = [40.0, 0.0]
"""


def test_flood_of_valid_messages_does_not_starve_replans(tmp_path, mission_file, port):
    """64 valid obstacles per message at 1.5 kHz from another process for 11 s: the budget (50 Hz)
    drops the excess unparsed, reported once a second; replans keep being installed with the newest
    picture, the car passes the barrel on its road, and no failsafe trips."""
    (tmp_path / "barrel.toml").write_text(line_scenario_toml("barrel", length=80.0, speed=5.0, t_max=60.0,
                                                             obstacles=BARREL))
    mission = load_mission(mission_file(route="barrel.toml", rate_hz=20.0, telemetry_port=port,
                                        telemetry_extra="perception = true\nperception_rate_hz = 50.0"))
    flood = subprocess.Popen([sys.executable, "-c", FLOOD, str(port), "1500", "11", KEY],
                             stdout=subprocess.PIPE, text=True)
    try:
        result = run_mission(mission, stop_after_s=12.0)
        out, _ = flood.communicate(timeout=30)
    finally:
        if flood.poll() is None:
            flood.kill()
            flood.wait()
    sent = json.loads(out)
    assert sent["sent"] / sent["seconds"] >= 1000.0, sent
    outcome, inp = result.outcome, result.outcome.loop.perception
    assert outcome.code == 0 and outcome.reason.startswith("ran"), outcome.reason
    log = read_flight_log(result.log_path)
    assert events(log, "failsafe") == [] and set(log.mode) <= {"running", "stopping"}

    # the flood was bounded: most messages dropped before parsing, the rest accepted
    assert inp.received >= 0.9 * sent["sent"] and inp.rejected == 0
    assert inp.dropped + inp.accepted == inp.received
    assert inp.accepted <= 50.0 * (sent["seconds"] + 1.0) + inp.budget.capacity
    dropped = events(log, "perception_dropped")
    assert sum(e.detail["count"] for e in dropped) == inp.dropped
    assert len(dropped) <= sent["seconds"] / inp.report_period_s + 3
    assert all(b.t - a.t >= 0.95 * inp.report_period_s for a, b in zip(dropped[:-2], dropped[1:-1]))

    # replans kept being installed with the newest picture while it flooded
    perceived = np.array([any(oid.startswith("perception:m") and np.isfinite(c[k, 0])
                              for oid, c in log.obstacles.items()) for k in range(len(log))])
    window = np.flatnonzero(perceived)
    assert log.t[window[-1]] - log.t[window[0]] >= 7.0, (log.t[window[0]], log.t[window[-1]])
    during = slice(window[0], window[-1] + 1)
    installs = log.t[during][1:][np.diff(log.plan_version[during]) > 0]
    assert len(installs) >= 5, installs
    gaps = np.diff(np.r_[log.t[window[0]], installs, log.t[window[-1]]])
    assert gaps.max() < 3.0, gaps
    assert log.plan_version[-1] >= 6

    # ... and the car passed the barrel on its road without touching it
    x = log.state[:, 0]
    assert x.max() > 45.0, x.max()
    assert clearances(log, mission.scenario)["barrel"] > 0.0


# --------------------------------------------------------------------------- values beyond the world
def test_huge_values_are_rejected_and_the_run_goes_on(mission_file, port):
    """Finite but huge centres and velocities (that used to overflow when propagated and trip
    controller_error) are rejected with their reason; the walker sent before and after stays in
    use and the mission runs on to its end."""
    mission = load_mission(mission_file(rate_hz=20.0, telemetry_port=port,
                                        telemetry_extra="perception = true\nperception_max_age_s = 0.5"))
    walker = {"id": "walker", "shape": {"kind": "circle", "radius": 0.4}, "center": [60.0, 8.0],
              "velocity": [0.0, -0.5]}
    huge = [{**walker, "id": "far", "center": [1.7e308, 1.7e308], "velocity": [1e308, 1e308]},
            {**walker, "id": "fast", "velocity": [1e308, -1e308]}]
    sent_bad = []

    def perceive():
        time.sleep(2.5)                                   # the daemon listens by then
        session = publisher(port)
        for i in range(70):                               # 3.5 s at 20 Hz; the bad ones at 1.5 s and 2.75 s,
            if i in (30, 55):                             # each the newest message for 0.2 s (4 ticks)
                session.put(KEY, json.dumps({"stamp": time.time(), "obstacles": [walker, huge[i == 55]]}))
                sent_bad.append(time.monotonic())
                time.sleep(0.2)
            session.put(KEY, json.dumps({"stamp": time.time(), "obstacles": [walker]}))
            time.sleep(0.05)
        session.close()

    sender = threading.Thread(target=perceive)
    sender.start()
    result = run_mission(mission, stop_after_s=7.0)
    sender.join()
    assert len(sent_bad) == 2
    outcome = result.outcome
    assert outcome.code == 0 and outcome.reason.startswith("ran"), outcome.reason
    assert outcome.loop.perception.rejected == 2 and outcome.loop.perception.accepted >= 60
    log = read_flight_log(result.log_path)
    assert events(log, "failsafe") == [] and set(log.mode) <= {"running", "stopping"}
    assert log.t[-1] >= 6.5
    first, second = events(log, "perception_rejected")
    assert first.detail["count"] == 1 and second.detail["count"] == 1
    assert "obstacles[1].center [1.7e+308, 1.7e+308] lies outside the perception area" in first.detail["reason"]
    assert "obstacles[1].velocity [1e+308, -1e+308] is faster than 40 m/s" in second.detail["reason"]
    seen = np.flatnonzero(np.all(np.isfinite(log.obstacles["perception:walker"]), axis=1))
    assert len(seen) >= 50                                # the walker kept being used, before and after
    assert log.t[seen[-1]] > second.t
    assert not any(oid.endswith(("far", "fast")) for oid in log.obstacles)
