"""Platform drivers behind the ``Platform`` port, chosen by a mission's ``platform.kind`` through
one lazy table (``PLATFORMS``: kind -> ``"module:factory"``, as python-can's interface table does).

A factory takes the route (scenario), the mission's ``[platform]`` table without ``kind``, the
mission file (for errors) and the flight log's path (drivers that record their link write beside
it). ``inproc`` is the simulator's in-process plant: it needs the ``sim`` package, a vehicle does
not.
"""

from __future__ import annotations

import importlib

PLATFORMS: dict[str, str] = {
    "can": "drivers.can_vehicle:can_vehicle_from_scenario",
    "mavlink": "drivers.mavlink_quad:mavlink_quad_from_scenario",
    "inproc": "sim.inproc:inproc_from_scenario",
}


def make_platform(kind: str, scenario, options: dict, file=None, flight_log=None):
    """The driver of platform ``kind`` (a key of ``PLATFORMS``; the mission loader checked it)."""
    module, factory = PLATFORMS[kind].split(":")
    return getattr(importlib.import_module(module), factory)(scenario, options, file, flight_log)
