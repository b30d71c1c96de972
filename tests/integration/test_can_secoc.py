"""Attacks on the authenticated CAN link, with real processes on loopback: python-can-remote's hub,
the ECU mock (``vflpcd sitl can-ecu``) and the daemon (``vflpcd run``) on a short straight road
with config/missions/vehicle_can_secoc.toml's platform, plus two bus clients of this test: a tap
that records the traffic (and keeps the frames that authenticate: the car's true positions), and
an attacker that, once the car drives, mixes into the live traffic:

- the recorded commands and their authentication PDUs, in order, and shuffled frame by frame;
- forged commands (steering 0.3 rad left, the right id, a random MAC);
- commands with a valid MAC over an old freshness value (the attacker holds the key: the worst
  case of a replay, built here), steering left;
- plain (unauthenticated) commands steering left;
- spoofed INS positions 3 m to the side: plain, with a forged PDU, and recorded ones replayed.

Without authentication the left turns would take the car off the road (test_can_replay.py). Here
no attack frame is obeyed or used: the ECU counts them by kind and follows the daemon's commands
only (its alive counter sees no foreign frame), the driver counts the spoofed INS frames, and
the mission completes on the road with no failsafe.
"""

from __future__ import annotations

import struct
import time
from pathlib import Path

import can
import numpy as np

from canhub import INS_POSITION, BusTap, PacedSender, can_hub, close_all, ecu_stats, edited_copy
from drivers.can_codec import VehicleCan
from drivers.can_secoc import AUTH_ID_OFFSET, Receiver, auth_pdu, load_key, wall_clock_ms
from processes import Proc
from vflpcd.base.paths import config_dir
from vflpcd.config.scenarios import line_scenario_toml
from vflpcd.log.reader import read_flight_log

MISSION = config_dir() / "missions" / "vehicle_can_secoc.toml"
KEY = load_key(config_dir() / "can" / "demo_secoc.key")
CMD = 0x100
ROUTE_END_X = 22.0           # m: the straight road
RECORD_X = (2.0, 6.0)        # m: the stretch whose traffic is recorded
ATTACK_RATE_HZ = 150.0       # mean; the daemon sends about 60 commands a second
ON_ROAD_M = 0.3              # lateral error the car keeps below (a 3 m spoofed offset or a 0.3 rad turn would not)


def short_road(folder: Path) -> Path:
    path = folder / "straight.toml"
    path.write_text(line_scenario_toml("straight", length=ROUTE_END_X, speed=6.944, t_max=20.0))
    return path


def mission_copy(folder: Path, url: str) -> Path:
    """The shipped authenticated mission on the hub at ``url`` and the short road, telemetry off."""
    path = folder / "vehicle_can_secoc.toml"
    edited_copy(MISSION, path, (('channel = "ws://127.0.0.1:54702/"', f'channel = "{url}"'),
                                ('auth_key = "../can/demo_secoc.key"',
                                 f'auth_key = "{config_dir() / "can" / "demo_secoc.key"}"'),
                                ('scenario = "carsim_avoidance"', f'scenario = "{short_road(folder)}"'),
                                ("[telemetry]\nenabled = true", "[telemetry]\nenabled = false"),
                                ('dir = "logs"', f'dir = "{folder / "logs"}"')))
    return path


class Tap(BusTap):
    """The bus tap with the car's authenticated positions; ``pairs(frame_id)``: the recorded data
    frames with the authentication PDU after them."""

    def __init__(self, url: str) -> None:
        self.positions: list[tuple[float, float]] = []
        self.rejected: list[str] = []
        self.rx = Receiver(KEY, (INS_POSITION,), lambda e: self.rejected.append(e.kind))
        super().__init__(url)

    def on_frame(self, msg: can.Message) -> None:
        ok = self.rx.feed(msg)
        if ok is not None and ok.arbitration_id == INS_POSITION:
            self.positions.append(tuple(np.array(struct.unpack("<ii", bytes(ok.data))) * 1e-3))
            self.x = self.positions[-1][0]

    def pairs(self, frame_id: int, t0: float, t1: float) -> list[tuple[bytes, bytes]]:
        frames = [(i, d) for t, i, d in list(self.frames) if t0 <= t <= t1]
        return [(d, frames[k + 1][1]) for k, (i, d) in enumerate(frames[:-1])
                if i == frame_id and frames[k + 1][0] == frame_id + AUTH_ID_OFFSET]


class Attacker(PacedSender):
    """Sends attack frames in rounds, at exponential gaps of mean 1 / rate_hz; counts what it sent by attack."""

    def __init__(self, url: str, cmds: list[tuple[bytes, bytes]], ins: list[tuple[bytes, bytes]], rate_hz: float,
                 seed: int = 5) -> None:
        self.cmds, self.ins = cmds, ins
        self.codec = VehicleCan()
        super().__init__(url, rate_hz, seed, "can-attacker")

    def _left(self, counter: int) -> bytes:
        return bytes(self.codec.encode("VehicleCmd", {"AccelCmd": 2.0, "SteerAngleCmd": 0.3, "Enable": 1,
                                                      "AliveCounter": counter % 16}).data)

    def rounds(self):
        shuffled = [f for pair in self.cmds for f in ((CMD, pair[0]), (CMD + AUTH_ID_OFFSET, pair[1]))]
        old_fv = wall_clock_ms() - 3000                                # 3 s old
        k = 0
        while True:
            k += 1
            d, a = self.cmds[k % len(self.cmds)]
            yield "replay_in_order", [(CMD, d), (CMD + AUTH_ID_OFFSET, a)]
            yield "replay_shuffled", [shuffled[i] for i in self.rng.integers(0, len(shuffled), 2)]
            left = self._left(k)
            yield "forged", [(CMD, left), (CMD + AUTH_ID_OFFSET, bytes(self.rng.integers(0, 256, 8, dtype=np.uint8)))]
            yield "old_freshness", [(CMD, left), (CMD + AUTH_ID_OFFSET, bytes(auth_pdu(CMD, old_fv + k, KEY, left).data))]
            yield "plain", [(CMD, left)]
            d, a = self.ins[k % len(self.ins)]
            x, y = struct.unpack("<ii", d)
            spoof = struct.pack("<ii", x, y + 3000)                    # 3 m to the left
            yield "ins_plain", [(INS_POSITION, spoof)]
            yield "ins_forged", [(INS_POSITION, spoof),
                                 (INS_POSITION + AUTH_ID_OFFSET, bytes(self.rng.integers(0, 256, 8, dtype=np.uint8)))]
            yield "ins_replayed", [(INS_POSITION, d), (INS_POSITION + AUTH_ID_OFFSET, a)]


def test_replayed_forged_and_spoofed_frames_are_rejected_and_counted_and_the_car_keeps_its_road(tmp_path):
    with can_hub() as (url, _):
        mission = mission_copy(tmp_path, url)
        ecu = Proc("sitl", "can-ecu", str(mission))
        daemon = tap = attacker = None
        try:
            ecu.wait_line("event=ecu_started", 20)
            tap = Tap(url)
            daemon = Proc("run", str(mission))
            daemon.wait_line("event=ready", 60)
            t_from = tap.wait_x(RECORD_X[0], 20)
            t_to = tap.wait_x(RECORD_X[1], 10)
            cmds, ins = tap.pairs(CMD, t_from, t_to), tap.pairs(INS_POSITION, t_from, t_to)
            assert len(cmds) > 20 and len(ins) > 40, (len(cmds), len(ins))
            attacker = Attacker(url, cmds, ins, ATTACK_RATE_HZ)
            rc = daemon.wait(30)
            t_counted = daemon.lines_with("event=can_stats")[0][0]     # the driver's counters end about here
            assert attacker.running and attacker.error is None, attacker.error        # it attacked to the end
            attacker.stop()
            ecu.stop()
            daemon_text = daemon.text()
        finally:
            close_all(attacker, tap, daemon, ecu)
    assert tap.error is None, f"the bus tap failed: {tap.error!r}"
    assert daemon.p.returncode is not None and ecu.p.returncode is not None

    # The mission completes, no failsafe.
    assert rc == 0 and "mission_complete (exit code 0)" in "\n".join(daemon.out), daemon_text[-3000:]
    (log_file,) = (tmp_path / "logs").glob("suv1-*.mcap")
    log = read_flight_log(log_file)
    assert not [e for e in log.events if e.kind == "failsafe"]
    (link,) = [e.detail for e in log.events if e.kind == "link_stats"]

    # The ECU obeyed the daemon's commands only: none of the attacks reached its alive counter.
    sent = attacker.sent()
    assert all(sent.get(k, 0) > 20 for k in ("replay_in_order", "forged", "old_freshness", "plain", "ins_forged")), sent
    stats = ecu_stats(ecu)
    bad = stats["bad_frames"]
    cmd_attacks = sent["replay_in_order"] + sent["old_freshness"]          # pairs whose MAC verifies: stale
    assert bad["replayed"] >= cmd_attacks and bad["forged"] >= sent["forged"], (bad, sent)
    assert bad["unauthenticated"] >= sent["plain"], (bad, sent)
    assert bad["counter"] == 0 and stats["counter_errors"] == 0 and stats["timeouts"] == 0, stats
    # (the driver's counters are logged after its close, the hand-back frame included)
    assert link["frames_sent"] - 2 <= stats["commands_ok"] <= link["frames_sent"], (stats, link)

    # The driver rejected every spoofed position and counted it; it saw no foreign command fault.
    sent = attacker.sent(t_counted)
    cmd_attacks = sent["replay_in_order"] + sent["old_freshness"]
    ins_rounds = sent["ins_plain"] + sent["ins_forged"] + sent["ins_replayed"]       # one InsPosition frame each
    assert link["authenticated"] and link["foreign_commands"] == 0, link
    assert link["auth_rejected"]["InsPosition"] >= 0.9 * ins_rounds, (link, sent)
    assert link["bad_frames"]["replayed"] >= 0.9 * (sent["ins_replayed"] + cmd_attacks), (link, sent)

    # The car kept its road: its true (authenticated) positions, to the end of the road.
    ys = np.array([y for _, y in tap.positions])
    xs = np.array([x for x, _ in tap.positions])
    assert xs.max() > ROUTE_END_X - 2.0 and np.abs(ys).max() < ON_ROAD_M, (xs.max(), np.abs(ys).max())
    assert tap.rejected.count("replayed") >= sent["ins_replayed"]
    print(f"attacks={attacker.sent()} ecu_bad={bad} ecu_commands_ok={stats['commands_ok']} daemon_sent={link['frames_sent']} "
          f"driver_bad={link['bad_frames']} driver_auth_rejected={link['auth_rejected']} "
          f"max_lateral_m={np.abs(ys).max():.3f}")
