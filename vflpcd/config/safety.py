"""The safety layer for a route: config/safety.toml (with a mission's ``[safety]`` overrides) and
the vehicle's limits turned into a ``SafetyGuard`` (vflpcd/core/safety/)."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import numpy as np

from vflpcd.core.safety.guard import SafetyGuard
from vflpcd.core.safety.monitors import MonitorConfig, PlanLimits
from vflpcd.core.safety.supervisor import (AerialSupervisor, CarLimits, GroundSupervisor, QuadLimits,
                                           SupervisorConfig)
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import Table, load_table

_POSITIVE = {"margin", "release_margin", "decel_factor", "max_step_m", "plan_timeout", "tracking_bound",
             "route_bound", "response_window", "response_accel_tol", "response_yaw_min", "blocked_s", "hold_kp",
             "hold_kd", "hold_speed", "plan_lookahead_m", "mover_wait_s"}


def _read(cls, table: Table, over: Table | None):
    values = {}
    for f in fields(cls):
        src = over if over is not None and over.has(f.name) else table
        if f.type == "int":
            values[f.name] = src.integer(f.name, min=1)
        elif f.type == "tuple":
            pair = src.vector(f.name, 2)
            if not 0.0 <= pair[0] < pair[1]:
                raise src.error(f.name, f"expected [low, high] with 0 <= low < high, got {pair.tolist()}")
            values[f.name] = (float(pair[0]), float(pair[1]))
        elif f.name in _POSITIVE:
            values[f.name] = src.number(f.name, positive=True)
        else:
            values[f.name] = src.number(f.name, min=0.0)
    return cls(**values)


def safety_settings(platform: str, overrides: Table | None = None,
                    path: str | Path | None = None) -> tuple[SupervisorConfig, MonitorConfig]:
    """The supervisor and monitor settings of ``platform`` ("ground" | "aerial"); ``overrides``: a
    mission's [safety] table (any field of either). ConfigError naming the file and the field."""
    path = Path(path) if path is not None else config_dir() / "safety.toml"
    root = load_table(path)
    root.check_known({"ground", "aerial"})
    plat = root.table(platform)
    plat.check_known({"supervisor", "monitors"})
    sup_t, mon_t = plat.table("supervisor"), plat.table("monitors")
    sup_t.check_known({f.name for f in fields(SupervisorConfig)})
    mon_t.check_known({f.name for f in fields(MonitorConfig)})
    if overrides is not None:
        overrides.check_known({f.name for f in fields(SupervisorConfig)} | {f.name for f in fields(MonitorConfig)})
    sup, mon = _read(SupervisorConfig, sup_t, overrides), _read(MonitorConfig, mon_t, overrides)
    if sup.release_margin < sup.margin:
        src = overrides if overrides is not None and overrides.has("release_margin") else sup_t
        raise src.error("release_margin", f"must be at least margin ({sup.margin:g} m)")
    if sup.decel_factor > 1.0:
        src = overrides if overrides is not None and overrides.has("decel_factor") else sup_t
        raise src.error("decel_factor", f"must be in (0, 1], got {sup.decel_factor:g}")
    return sup, mon


def guard_for(scenario, period: float, state_names,
              settings: tuple[SupervisorConfig, MonitorConfig] | None = None) -> SafetyGuard:
    """The safety guard of a route's vehicle (its plant's limits and body), ticking every ``period`` s;
    ``settings``: from ``safety_settings`` (default: config/safety.toml as it is)."""
    from vflpcd.controllers.loops import polyline_loop, supervisor_loops

    sup_cfg, mon_cfg = settings if settings is not None else safety_settings(scenario.platform)
    if scenario.platform == "ground":
        from vflpcd.config.vehicles import BicycleConfig

        bike = BicycleConfig.load(scenario.params)
        lim = bike.limits
        car = CarLimits(wheelbase=bike.params.wheelbase, a_min=lim.a_min, a_max=lim.a_max,
                        delta_max=lim.delta_max, delta_rate_max=lim.delta_rate_max)
        sup = GroundSupervisor(sup_cfg, scenario.footprint, car, period, state_names, loops=supervisor_loops())
        plan_limits = PlanLimits(kappa_max=float(np.tan(lim.delta_max) / car.wheelbase), a_lat_max=scenario.a_lat_max)
    else:
        from vflpcd.config.vehicles import QuadrotorParams

        quad = QuadrotorParams.from_toml()
        sup = AerialSupervisor(sup_cfg, scenario.footprint.radius, QuadLimits(quad.accel_max), period, state_names,
                               loops=supervisor_loops())
        plan_limits = PlanLimits(kappa_max=np.inf, a_lat_max=scenario.a_lat_max)
    return SafetyGuard(sup, mon_cfg, plan_limits, period, nearest=polyline_loop())
