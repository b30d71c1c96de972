"""Replayed VehicleCmd frames mixed into the live CAN traffic, with real processes on loopback:
python-can-remote's hub, the ECU mock (``vflpcd sitl can-ecu``) and the daemon (``vflpcd run``) on
config/missions/vehicle_can.toml, plus a bus client of this test that records the daemon's own
commands while it swerves left around the parked car and plays them back, bytes unchanged (alive
counter and checksum as recorded), for the rest of the run.

The ECU's alive counter re-synchronises on every frame, so a replayed frame that follows another
replayed one passes its checks: without defences the ECU follows the recorded left turn most of
the time and the car leaves the road (about 30 m off it). Three layers catch it now: the driver
sees VehicleCmd frames that are not its own (the bus does not echo them) and reports a link
fault at once; the ECU's end-to-end supervision takes the vehicle over after repeated counter
errors; and the safety monitors would see a vehicle that does not answer its commands. The car
brakes to a standstill near the route while the replay goes on, and the daemon exits with code 3.

The replay's send times are random (exponential gaps, seeded): a strictly periodic replay locks to
the daemon's 20 ms cycle, and depending on the phase either every frame of both senders breaks the
counter (the ECU's command timeout takes over) or the replay always wins.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import can
import numpy as np

from canhub import BusTap, PacedSender, can_hub, close_all, ecu_stats, edited_copy
from drivers.can_codec import VehicleCan
from processes import Proc, descendants, wait_gone
from vflpcd.config.scenarios import load_scenario
from vflpcd.log.reader import read_flight_log
from vflpcd.base.paths import config_dir

MISSION = config_dir() / "missions" / "vehicle_can.toml"
CMD, STATUS, INS_POSITION = 0x100, 0x200, 0x300
RECORD_X = (20.0, 30.0)      # m: the stretch where the daemon steers left around the parked car
REPLAY_RATE_HZ = 80.0        # mean; the daemon sends about 60 frames/s while it drives
STANDSTILL = 0.05            # m/s
FAILSAFE_WITHIN_S = 0.5      # after the replay starts: the driver sees the first foreign frame
DEVIATION_AT_STOP_M = 5.0    # from the route (measured 3.2 m: the avoidance, then braking with the steering held; about 30 m without defences)


def mission_copy(folder: Path, url: str) -> Path:
    """The shipped mission on the hub at ``url``, telemetry off, logs in folder/logs."""
    path = folder / "vehicle_can.toml"
    edited_copy(MISSION, path, (('channel = "ws://127.0.0.1:54701/"', f'channel = "{url}"'),
                                ("[telemetry]\nenabled = true", "[telemetry]\nenabled = false"),
                                ('dir = "logs"', f'dir = "{folder / "logs"}"')))
    return path


class Replay(PacedSender):
    """Sends ``frames`` (data bytes of VehicleCmd) in a loop, at exponential gaps of mean 1 / rate_hz."""

    def __init__(self, url: str, frames: list[bytes], rate_hz: float, seed: int = 7) -> None:
        self.frames = frames
        super().__init__(url, rate_hz, seed, "can-replay")

    def rounds(self):
        k = 0
        while True:
            yield "replay", [(CMD, self.frames[k % len(self.frames)])]
            k += 1


def test_replayed_commands_trip_the_failsafe_and_the_car_stops_near_the_route(tmp_path):
    codec = VehicleCan()
    route = load_scenario("carsim_avoidance").path
    status = codec.message("VehicleStatus")
    with can_hub() as (url, _):
        mission = mission_copy(tmp_path, url)
        ecu = Proc("sitl", "can-ecu", str(mission))
        daemon = tap = replay = None
        try:
            ecu.wait_line("event=ecu_started", 20)
            daemon = Proc("run", str(mission))
            tap = BusTap(url)
            daemon.wait_line("event=ready", 60)
            workers = descendants(daemon.p.pid)          # the process pool: it must end with the daemon

            # The daemon's own commands while it swerves left around the parked car.
            t_from = tap.wait_x(RECORD_X[0], 30)
            t_to = tap.wait_x(RECORD_X[1], 10)
            recorded = [d for _, d in tap.since(CMD, t_from, t_to)]
            steer = [codec.decode(can.Message(arbitration_id=CMD, data=d, is_extended_id=False))
                     .signals["SteerAngleCmd"] for d in recorded]
            assert len(recorded) > 40 and np.mean(steer) > 0.02, (len(recorded), np.mean(steer))

            replay = Replay(url, recorded, REPLAY_RATE_HZ)
            t_failsafe = daemon.wait_line("event=failsafe", 20, after=replay.started)
            rc = daemon.wait(30)
            t_exit = time.monotonic()
            assert replay.running and replay.error is None, replay.error     # the replay went on to the end
            t_replay_end = replay.stop()
            # Without commands the ECU takes over (command timeout) or holds the brakes (ready).
            deadline, last = time.monotonic() + 3.0, []
            while time.monotonic() < deadline:
                last = tap.since(STATUS, t_replay_end + 0.3)
                if last:
                    break
                time.sleep(0.05)
            ecu.stop()
            daemon_text = daemon.text()
        finally:
            close_all(replay, tap, daemon, ecu)
    assert tap.error is None, f"the bus tap failed: {tap.error!r}"

    # The failsafe, soon after the replay started; exit code 3.
    assert rc == 3, daemon_text[-3000:]
    (log_file,) = (tmp_path / "logs").glob("suv1-*.mcap")
    log = read_flight_log(log_file)
    (event,) = [e for e in log.events if e.kind == "failsafe"]
    reason = event.detail["reason"]
    assert reason.startswith(("link_lost: another sender's VehicleCmd frames", "link_lost: the ECU took over",
                              "unresponsive", "tracking_error")), reason
    (line,) = [line for _, line in daemon.lines_with("event=failsafe")]
    assert f"reason={reason}" in line and "at_rest" in [e.kind for e in log.events]
    time_to_failsafe = t_failsafe - replay.started
    assert time_to_failsafe < FAILSAFE_WITHIN_S, time_to_failsafe

    # The car stopped near the route while the replay went on.
    statuses = [(t, status.decode(d)) for t, d in tap.since(STATUS, replay.started)]
    stop_t = next(t for t, s in statuses if t >= t_failsafe and s["Speed"] < STANDSTILL)
    assert stop_t < t_exit <= t_replay_end
    positions = [(t, np.array(struct.unpack("<ii", d)) * 1e-3) for t, d in tap.since(INS_POSITION, replay.started)]
    lateral = [(t, abs(route.project(p).lateral)) for t, p in positions]
    deviation_at_stop = next(e for t, e in lateral if t >= stop_t)
    most = max(e for _, e in lateral)
    assert most < DEVIATION_AT_STOP_M and deviation_at_stop < DEVIATION_AT_STOP_M, (most, deviation_at_stop)
    # It stayed stopped: the replayed frames move it no more than a creep.
    assert max(s["Speed"] for t, s in statuses if stop_t <= t <= t_replay_end) < 0.5

    # The ECU rejected part of the replay by its counter and ends braked: ready (brakes held) or stopped.
    stats = ecu_stats(ecu)
    assert stats["bad_frames"]["counter"] > 100 and stats["mode"] in ("ready", "stopped"), stats
    assert last and all(status.decode(d)["Speed"] < STANDSTILL for _, d in last), last[-1:]

    # Nothing outlives the test.
    assert daemon.p.returncode is not None and ecu.p.returncode is not None
    assert wait_gone(workers, 5.0) == []
    timeout_bits = [s["FaultCmdTimeout"] for t, s in statuses if t <= t_exit]
    takeovers = sum(1 for a, b in zip(timeout_bits, timeout_bits[1:]) if b and not a)   # ECU command timeouts
    print(f"time_to_failsafe_s={time_to_failsafe:.2f} reason={reason[:60]!r} stop_after_failsafe_s="
          f"{stop_t - t_failsafe:.2f} deviation_at_stop_m={deviation_at_stop:.2f} max_deviation_m={most:.2f} "
          f"ecu_counter_errors={stats['bad_frames']['counter']} ecu_commands_ok={stats['commands_ok']} "
          f"ecu_timeouts={stats['timeouts']} ecu_takeovers_before_exit={takeovers} replayed={len(replay.log)}")
