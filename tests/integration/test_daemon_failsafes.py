"""Each failsafe with an injected fault (``--drill``), through the real daemon in this process:
the fault is named in a failsafe event, the platform's safe action takes over within two ticks
of the detection, the vehicle comes to rest, and the daemon exits with code 3."""

import numpy as np
import pytest

from vflpcd.app.drill import Drill
from vflpcd.log.reader import read_flight_log
from vflpcd.config.mission import load_mission
from vflpcd.app.run import run_mission

RATE = 50.0
PERIOD_NS = 1e9 / RATE

# fault -> (reason kind, detection delay after the fault starts, ns, besides the two ticks)
CASES = {
    "error": ("controller_error", 0.0),
    "nan": ("nonfinite_command", 0.0),
    "overrun": ("overrun_streak", 5 * 1.5 * PERIOD_NS),
    "stall": ("stall", 0.4e9 + 0.05e9),           # failsafe.stall + the health monitor's period
    "freeze": ("stale_state", 0.1e9 + PERIOD_NS),   # failsafe.state_max_age + one tick
    "nan_state": ("nonfinite_state", 5e6),          # the next physics step publishes it
    "link": ("link_lost", 0.0),
}


@pytest.mark.parametrize("fault", list(CASES))
def test_failsafe_fires_within_two_ticks_and_the_vehicle_stops(fault, mission_file):
    mission = load_mission(mission_file(rate_hz=RATE, hold=1.5, state_max_age=0.1))
    result = run_mission(mission, drill=Drill(fault, 1.0))
    loop, outcome = result.outcome.loop, result.outcome
    platform, drill = loop.platform, loop.controller
    kind, delay_ns = CASES[fault]

    assert outcome.code == 3 and outcome.reason.startswith(kind)
    assert platform.failsafe_reason.startswith(kind)
    assert drill.fired_ns is not None
    latency = platform.failsafe_stamp_ns - drill.fired_ns
    assert 0 < latency <= delay_ns + 2 * PERIOD_NS, f"safe action {latency / 1e6:.1f} ms after the fault"
    assert platform.at_rest                                     # braked to a stop
    log = read_flight_log(result.log_path)
    events = [e for e in log.events if e.kind == "failsafe"]
    assert len(events) == 1 and events[0].detail["reason"].startswith(kind)
    assert events[0].detail["action"] == "brake_to_stop"
    after = log.t > events[0].t + 2 / RATE
    assert np.all(np.isnan(log.command[after])), "no command may be sent after the failsafe"
    assert np.all(log.mode[after] == "failsafe")


def test_quadrotor_link_loss_holds_then_lands(mission_file):
    mission = load_mission(mission_file(route="uav_3d", rate_hz=RATE, hold=5.0,
                                        platform_extra="hold_s = 0.5\nland_speed = 1.0"))
    result = run_mission(mission, drill=Drill("link", 2.0))
    platform = result.outcome.loop.platform
    assert result.outcome.code == 3 and platform.failsafe_reason.startswith("link_lost")
    assert platform.landed and abs(platform.plant.position()[2]) < 0.1
    log = read_flight_log(result.log_path)
    assert [e.detail["action"] for e in log.events if e.kind == "failsafe"] == ["hold_then_land"]
