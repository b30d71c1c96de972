"""PX4's flight modes in the quadrotor SITL (``sim.sitl.quad``): their encoding, which of them it
flies, the reason it gives for each it does not, and the path of its return to home (AUTO.RTL).

PX4 carries a mode as a main mode and a sub mode: in HEARTBEAT's and SET_MODE's ``custom_mode``
as ``(sub << 24) | (main << 16)``, in MAV_CMD_DO_SET_MODE as param2 = main, param3 = sub, with
param1 (the base mode) carrying MAV_MODE_FLAG_CUSTOM_MODE_ENABLED. Main modes: MANUAL 1, ALTCTL 2,
POSCTL 3, AUTO 4 (sub modes READY 1, TAKEOFF 2, LOITER 3, MISSION 4, RTL 5, LAND 6), ACRO 5,
OFFBOARD 6, STABILIZED 7.

Flown: OFFBOARD, AUTO.LOITER, AUTO.TAKEOFF (entered by MAV_CMD_NAV_TAKEOFF), AUTO.LAND, AUTO.RTL,
POSCTL and ALTCTL. With no pilot's sticks, POSCTL and ALTCTL hold the position and altitude at
which they were entered (PX4 with centred sticks; the plant knows no wind, so ALTCTL holds the
horizontal position too). Refused as unsupported, each with its reason: AUTO.MISSION (it keeps no
missions), MANUAL, STABILIZED and ACRO (they fly by the sticks), AUTO.TAKEOFF as a mode change, the
other sub modes, unknown main modes, and a base mode without the custom-mode flag.
"""

from __future__ import annotations

import math

import numpy as np

MAIN = {"MANUAL": 1, "ALTCTL": 2, "POSCTL": 3, "AUTO": 4, "ACRO": 5, "OFFBOARD": 6, "STABILIZED": 7}
AUTO_SUB = {"READY": 1, "TAKEOFF": 2, "LOITER": 3, "MISSION": 4, "RTL": 5, "LAND": 6}
CUSTOM_MODE_ENABLED = 1                                 # MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
STATUSTEXT_LEN = 50                                     # a STATUSTEXT's text, bytes

# the modes it flies: name -> (main, sub)
FLOWN = {"AUTO.LOITER": (4, 3), "AUTO.TAKEOFF": (4, 2), "AUTO.LAND": (4, 6), "AUTO.RTL": (4, 5),
         "POSCTL": (3, 0), "ALTCTL": (2, 0), "OFFBOARD": (6, 0)}
# the modes a ground station may set
SETTABLE = ("AUTO.LOITER", "AUTO.LAND", "AUTO.RTL", "POSCTL", "ALTCTL", "OFFBOARD")
NO_MISSIONS = "missions not supported by this SITL"
REFUSED = {"AUTO.MISSION": f"AUTO.MISSION: {NO_MISSIONS}",
           "AUTO.TAKEOFF": "AUTO.TAKEOFF by mode unsupported: use NAV_TAKEOFF",
           **{name: f"{name}: stick mode, unsupported by this SITL" for name in ("MANUAL", "STABILIZED", "ACRO")}}
NOT_CUSTOM = "only PX4 custom modes are supported by this SITL"


def custom_mode(name: str) -> int:
    """HEARTBEAT's custom_mode of a flown mode."""
    main, sub = FLOWN[name]
    return (sub << 24) | (main << 16)


def split_custom_mode(value: int) -> tuple[int, int]:
    """(main, sub) of a custom_mode value."""
    return (value >> 16) & 0xFF, (value >> 24) & 0xFF


def mode_name(main: int, sub: int) -> str:
    """PX4's name of (main, sub): ``AUTO.<SUB>`` for the auto modes, ``main M sub S`` when unknown."""
    for name, (m, s) in FLOWN.items():
        if (m, s) == (main, sub):
            return name
    if main == MAIN["AUTO"]:
        sub_name = next((n for n, s in AUTO_SUB.items() if s == sub), None)
        if sub_name is not None:
            return f"AUTO.{sub_name}"
    elif sub == 0:
        known = next((n for n, m in MAIN.items() if m == main), None)
        if known is not None:
            return known
    return f"main {main} sub {sub}"


def requested_mode(base_mode: int, main: int, sub: int) -> tuple[str | None, str]:
    """The mode a DO_SET_MODE (or SET_MODE) asks for: (name, "") when it may be set, else (None, the
    reason it is not supported, short enough for one STATUSTEXT)."""
    if not base_mode & CUSTOM_MODE_ENABLED:
        return None, NOT_CUSTOM
    name = mode_name(main, sub)
    if name in SETTABLE:
        return name, ""
    return None, REFUSED.get(name, f"{name}: not supported by this SITL")


class Return:
    """AUTO.RTL's path from ``position`` (ENU, m): climb where it is to ``return_alt`` above
    ``home`` (or stay at its altitude if higher), fly level to above home, then descend onto home.
    A phase ends when the vehicle is within ``alt_radius`` of the return altitude (the climb) or
    within ``xy_radius`` of home horizontally (the flight back)."""

    CLIMB, BACK, DESCEND = "climb", "back", "descend"

    def __init__(self, position, home, *, return_alt: float, alt_radius: float, xy_radius: float) -> None:
        self.home = np.array(home, dtype=float)
        self.altitude = max(float(position[2]), self.home[2] + return_alt)
        self.alt_radius, self.xy_radius = alt_radius, xy_radius
        self._entry = np.array(position[:2], dtype=float)
        self.phase = self.CLIMB

    def advance(self, position) -> bool:
        """Move on to the next phase(s) the vehicle at ``position`` has reached; whether it moved on."""
        before = self.phase
        if self.phase == self.CLIMB and position[2] >= self.altitude - self.alt_radius:
            self.phase = self.BACK
        if self.phase == self.BACK and math.hypot(*(self.home[:2] - position[:2])) <= self.xy_radius:
            self.phase = self.DESCEND
        return self.phase != before

    def target(self) -> np.ndarray:
        """The ENU position the phase flies to (the descent's height is the ground's: home's)."""
        if self.phase == self.CLIMB:
            return np.array([*self._entry, self.altitude])
        if self.phase == self.BACK:
            return np.array([*self.home[:2], self.altitude])
        return self.home.copy()
