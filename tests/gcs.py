"""A pymavlink ground station on loopback for the tests of the quadrotor SITL (``sim.sitl.quad``):
it listens on a UDP port the autopilot sends to, as QGroundControl or MAVProxy do."""

from __future__ import annotations

import math
import os
import time

os.environ.setdefault("MAVLINK20", "1")
from pymavlink import mavutil  # noqa: E402

mav = mavutil.mavlink


def px4_mode(main: int, sub: int = 0) -> int:
    """HEARTBEAT's custom_mode of PX4's (main, sub)."""
    return (sub << 24) | (main << 16)


LOITER, LAND, RTL, POSCTL = px4_mode(4, 3), px4_mode(4, 6), px4_mode(4, 5), px4_mode(3)


class Gcs:
    def __init__(self, port):
        self.c = mavutil.mavlink_connection(f"udpin:127.0.0.1:{port}", source_system=245, source_component=190,
                                            dialect="common")
        self.heartbeats = []                     # every HEARTBEAT read, whoever waited for what
        self.texts = []                          # every STATUSTEXT read
        self.last = {}                           # the newest message read of each type

    def _read(self, blocking: bool):
        m = self.c.recv_match(blocking=blocking, timeout=0.1)
        if m is not None:
            self.last[m.get_type()] = m
        if m is not None and m.get_type() == "HEARTBEAT":
            self.heartbeats.append(m)
        elif m is not None and m.get_type() == "STATUSTEXT":
            self.texts.append(m.text)
        return m

    def recv(self, kind, timeout=3.0, cond=lambda m: True):
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            m = self._read(True)
            if m is not None and m.get_type() == kind and cond(m):
                return m
        raise AssertionError(f"no {kind} within {timeout} s")

    def latest(self, kind):
        """The newest ``kind`` message: the backlog is read first."""
        last = None
        while (m := self._read(False)) is not None:
            if m.get_type() == kind:
                last = m
        return last or self.recv(kind)

    def shown(self, custom_mode, timeout=2.0):
        """Wait until a HEARTBEAT (one read already, or the next) shows ``custom_mode``: the autopilot
        sends one on each change, before the ACK of the command that made it."""
        if not any(m.custom_mode == custom_mode for m in self.heartbeats):
            self.recv("HEARTBEAT", timeout, lambda m: m.custom_mode == custom_mode)

    def command(self, cmd, *p, target=1):
        p = list(p) + [0.0] * (7 - len(p))
        self.c.mav.command_long_send(target, 1, cmd, 0, *p)
        return self.recv("COMMAND_ACK", cond=lambda m: m.command == cmd)

    def set_mode(self, main, sub=0):
        """MAV_CMD_DO_SET_MODE with PX4's custom mode (as pymavlink's ``set_mode_px4`` sends it); its ACK."""
        return self.command(mav.MAV_CMD_DO_SET_MODE, mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, main, sub)

    def mode(self, name):
        """pymavlink's ``set_mode(name)`` (what MAVProxy's ``mode NAME`` sends to a PX4); its ACK."""
        self.c.set_mode(name)
        return self.recv("COMMAND_ACK", cond=lambda m: m.command == mav.MAV_CMD_DO_SET_MODE)

    def accel(self, n, e, d):
        self.c.mav.set_position_target_local_ned_send(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 3135, 0, 0, 0, 0, 0, 0,
                                                      n, e, d, 0, 0)

    def velocity(self, n, e, d, yaw=0.0):
        self.c.mav.set_position_target_local_ned_send(0, 1, 1, mav.MAV_FRAME_LOCAL_NED, 2503, 0, 0, 0, n, e, d,
                                                      0, 0, 0, yaw, 0)

    def takeoff(self, timeout=10.0):
        assert self.command(400, 1).result == 0
        assert self.command(22, *[math.nan] * 7).result == 0
        self.recv("HEARTBEAT", timeout, lambda m: m.custom_mode == LOITER)   # AUTO.LOITER after take-off

    def close(self):
        self.c.close()
