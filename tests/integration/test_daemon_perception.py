"""Moving obstacles from perception reach the controller through a live Zenoh session, invalid
messages become events, and stale ones are dropped."""

import json
import threading
import time

import numpy as np
import zenoh

from vflpcd.flightlog import read_flight_log
from vflpcd.mission import load_mission
from vflpcd.run import run_mission


def publisher(port: int):
    cfg = zenoh.Config()
    cfg.insert_json5("mode", '"peer"')
    cfg.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    cfg.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(cfg)


def test_perceived_walker_is_used_then_dropped_when_stale(mission_file, port):
    mission = load_mission(mission_file(rate_hz=20.0, telemetry_port=port,
                                        telemetry_extra="perception = true\nperception_max_age_s = 0.5"))

    def perceive():
        time.sleep(3.0)                                   # the daemon listens by then
        session = publisher(port)
        key = "vflpc/t1/perception/obstacles"
        for i in range(40):                               # 2 s at 20 Hz: a walker 40 m ahead, crossing slowly
            msg = {"stamp": time.time(), "obstacles": [
                {"id": "walker", "shape": {"kind": "circle", "radius": 0.4},
                 "center": [60.0, 6.0 - 0.05 * i], "velocity": [0.0, -1.0]}]}
            session.put(key, json.dumps(msg))
            time.sleep(0.05)
        session.put(key, json.dumps({"stamp": time.time(), "obstacles": [{"id": "x"}]}))   # invalid
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
    rejected = [e for e in log.events if e.kind == "perception_rejected"]
    assert len(rejected) == 1 and "obstacles[0]" in rejected[0].detail["reason"]
