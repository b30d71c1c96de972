"""The tunable numbers of config/ read into core's dataclasses: the guidance (config/guidance.toml,
a scenario's [guidance] table) and VF-LPC (config/controllers/vflpc.toml). Errors name the file
and the field (``ConfigError`` through ``Table``)."""

from __future__ import annotations

from dataclasses import fields, replace

import numpy as np

from vflpcd.base.errors import ConfigError
from vflpcd.base.tomlread import Table
from vflpcd.core.guidance.params import GuidanceParams, VirtualObstacleSpec
from vflpcd.core.vflpc import VFLPCParams

_POSITIVE = ("k_p", "k_r", "l1", "l2", "k_c", "beta", "grid_resolution", "corridor", "epsilon", "reactive_margin",
             "horizon", "a_accel", "a_decel", "a_yield", "virtual_buffer", "curvature_use", "recovery_reactive_margin")


def guidance_params(t: Table, base: GuidanceParams | None = None) -> GuidanceParams:
    """Every field from table t, or, with ``base``, only the fields t sets (an override)."""
    names = {f.name for f in fields(GuidanceParams)}
    t.check_known(names)
    values = {}
    for name in names - {"virtual", "virtual_obstacles"}:
        if base is None or t.has(name):
            values[name] = t.number(name, positive=name in _POSITIVE, min=0.0)
    if base is None or t.has("virtual"):
        values["virtual"] = t.string("virtual", choices=("auto", "off"))
    if t.has("virtual_obstacles"):
        values["virtual_obstacles"] = tuple(_virtual(v) for v in t.tables("virtual_obstacles"))
    return replace(base, **values) if base is not None else GuidanceParams(**values)


def _virtual(t: Table) -> VirtualObstacleSpec:
    t.check_known({"center", "radius", "c", "parent", "gamma"})
    c = t.number("c")
    if not -1.0 < c < 0.0:
        raise t.error("c", f"expected a repulsive level -1 < c < 0 (c_i < 0), got {c:g}")
    gamma = t.integer("gamma", 0)
    if gamma not in (-1, 0, 1):
        raise t.error("gamma", f"expected -1, 1 or 0 (automatic), got {gamma}")
    return VirtualObstacleSpec(center=t.vector("center", 2), radius=t.number("radius", positive=True), c=c,
                               parent=t.string("parent"), gamma=gamma)


def _bounds(t: Table, key: str, default: tuple[float, float]) -> tuple[float, float]:
    """A [low, high] pair of positive numbers, low < high."""
    lo, hi = t.vector(key, 2) if t.has(key) else default
    if not (0.0 < lo < hi and np.isfinite(hi)):
        raise t.error(key, f"expected [low, high] with 0 < low < high, got [{lo:g}, {hi:g}]")
    return float(lo), float(hi)


def vflpc_params(root: Table, platform: str) -> VFLPCParams:
    root.check_known({"cost", "horizon", "solver", "features", "barrier", "replan", "compensation", "vehicle"})
    cost, hor, sol = root.table("cost"), root.table("horizon"), root.table("solver")
    feat, bar, rep = root.table("features"), root.table("barrier"), root.table("replan")
    vehicle = root.table("vehicle", {})
    vehicle.check_known({"params"})
    vehicle_params = vehicle.string("params", "nominal")
    if platform == "ground":            # the car's parameter set, named here when the plant file lacks it
        from vflpcd.config.vehicles import BicycleConfig

        try:
            BicycleConfig.load(vehicle_params)
        except ConfigError as exc:
            if exc.field.startswith("params."):
                raise vehicle.error("params", exc.message) from None
            raise
    cost.check_known({"q_ground", "r_ground", "r_rate_ground", "q_aerial", "r_aerial", "r_rate_aerial", "q_lift",
                      "gamma", "r_rate_threat_ground", "r_rate_threat_aerial",
                      "r_rate_light_ground", "r_rate_light_aerial", "light_hold", "light_speeds", "light_offsets",
                      "slow_speeds", "speed_scaled_increments_ground", "speed_scaled_increments_aerial",
                      "command_increments_ground", "command_increments_aerial"})
    hor.check_known({"seconds"})
    sol.check_known({"i_max", "tol", "eta_a", "divergence"})
    feat.check_known({"error_std_ground", "error_std_aerial", "samples", "size", "nu", "ell_factor", "seed"})
    bar.check_known({"mu", "length", "l_safe", "max_threats"})
    rep.check_known({"end_margin", "velocity_change", "join_tolerance", "stale_distance"})
    comp = root.table("compensation", {})
    comp.check_known({"refit_every", "min_samples", "channels", "ell", "sf2", "sn2", "nu", "m_max", "n_max",
                      "linearisation", "sf2_bounds", "ell_bounds", "sn2_bounds"})
    q, r = cost.vector(f"q_{platform}"), cost.vector(f"r_{platform}")
    if np.any(q < 0) or np.any(r <= 0):
        raise cost.error(f"q_{platform}", "state weights must be >= 0 and control weights > 0")
    r_rate = cost.vector(f"r_rate_{platform}", len(r)) if cost.has(f"r_rate_{platform}") else None
    if r_rate is not None and np.any(r_rate <= 0):
        raise cost.error(f"r_rate_{platform}", "increment weights must be > 0")
    key = f"r_rate_threat_{platform}"
    r_threat = cost.vector(key, len(r)) if cost.has(key) else None
    if r_threat is not None and (r_rate is None or np.any(r_threat <= 0)):
        raise cost.error(key, f"increment weights must be > 0, and r_rate_{platform} must be given too")
    key = f"r_rate_light_{platform}"
    r_light = cost.vector(key, len(r)) if cost.has(key) else None
    if r_light is not None and (r_rate is None or np.any(r_light <= 0)):
        raise cost.error(key, f"increment weights must be > 0, and r_rate_{platform} must be given too")
    light_speeds = cost.vector("light_speeds", 2) if cost.has("light_speeds") else np.array([0.0, np.inf])
    if not (0.0 <= light_speeds[0] < light_speeds[1]):
        raise cost.error("light_speeds", f"expected [low, high] m/s with 0 <= low < high, got {light_speeds.tolist()}")
    light_offsets = cost.vector("light_offsets", 2) if cost.has("light_offsets") else np.array([np.inf, np.inf])
    if not (0.0 < light_offsets[0] <= light_offsets[1]):
        raise cost.error("light_offsets", f"expected [take up, keep] m with 0 < take up <= keep, got {light_offsets.tolist()}")
    slow_speeds = cost.vector("slow_speeds") if cost.has("slow_speeds") else np.zeros(0)
    if np.any(slow_speeds <= 0.0) or np.any(np.diff(slow_speeds) <= 0.0) or np.any(slow_speeds >= light_speeds[0]):
        raise cost.error("slow_speeds", f"expected increasing speeds in (0, light_speeds[0] = {light_speeds[0]:g}) m/s, "
                                        f"got {slow_speeds.tolist()}")
    key = f"speed_scaled_increments_{platform}"
    speed_scaled = tuple(cost.strings(key, choices=_inputs(platform))) if cost.has(key) else ()
    if speed_scaled and (r_rate is None or not len(slow_speeds)):
        raise cost.error(key, f"needs r_rate_{platform} and slow_speeds")
    gamma = cost.number("gamma", min=0.0)
    if not (0.0 < gamma <= 1.0):
        raise cost.error("gamma", f"must lie in (0, 1], got {gamma}")
    eta_a = sol.number("eta_a", positive=True)
    if eta_a > 1.0:
        raise sol.error("eta_a", f"must lie in (0, 1], got {eta_a}")
    std = feat.vector(f"error_std_{platform}", len(q))
    if np.any(std <= 0):
        raise feat.error(f"error_std_{platform}", "must be positive")
    return VFLPCParams(Q_x=q, R=np.diag(r), q_lift=cost.number("q_lift", min=0.0), gamma=gamma,
               horizon_s=hor.number("seconds", positive=True), i_max=sol.integer("i_max", min=1),
               tol=sol.number("tol", min=0.0), eta_a=eta_a, divergence=sol.number("divergence", positive=True),
               error_std=std, samples=feat.integer("samples", min=1), size=feat.integer("size", min=1),
               nu=feat.number("nu", positive=True), ell_factor=feat.number("ell_factor", positive=True),
               seed=feat.integer("seed", min=0), mu=bar.number("mu", min=0.0),
               barrier_length=bar.number("length", positive=True), l_safe=bar.number("l_safe", min=0.0),
               max_threats=bar.integer("max_threats", min=0), end_margin=rep.number("end_margin", min=0.0),
               velocity_change=rep.number("velocity_change", positive=True),
               join_tolerance=rep.number("join_tolerance", 0.5, min=0.0),
               stale_distance=rep.number("stale_distance", 1.0, positive=True),
               refit_every=comp.integer("refit_every", 100, min=1),
               refit_min_samples=comp.integer("min_samples", 60, min=1),
               gp_channels=tuple(comp.strings("channels", ("Y", "psi", "vx", "vy", "omega"))),
               gp_ell=comp.number("ell", 3.0, positive=True), gp_sf2=comp.number("sf2", 0.05, positive=True),
               gp_sn2=comp.number("sn2", 1e-4, positive=True), gp_nu=comp.number("nu", 0.05, positive=True),
               gp_m_max=comp.integer("m_max", 48, min=1), gp_n_max=comp.integer("n_max", 400, min=2),
               gp_linearisation=comp.string("linearisation", "nominal", choices=("nominal", "gp")),
               gp_bounds=tuple(_bounds(comp, k, d) for k, d in (("sf2_bounds", (1e-6, 0.1)), ("ell_bounds", (0.3, 10.0)),
                                                                 ("sn2_bounds", (1e-6, 1e-3)))),
               R_rate=None if r_rate is None else np.diag(r_rate),
               R_rate_threat=None if r_threat is None else np.diag(r_threat),
               R_rate_light=None if r_light is None else np.diag(r_light),
               light_hold=cost.number("light_hold", 2.0, min=0.0),
               light_speeds=(float(light_speeds[0]), float(light_speeds[1])),
               light_offsets=(float(light_offsets[0]), float(light_offsets[1])),
               slow_speeds=tuple(float(v) for v in slow_speeds), speed_scaled=speed_scaled,
               command_increments=(cost.strings(f"command_increments_{platform}", choices=_inputs(platform))
                                   if cost.has(f"command_increments_{platform}") else ()),
               vehicle_params=vehicle_params)


def _inputs(platform: str) -> tuple[str, ...]:
    """The control inputs of a platform's models (the names ``command_increments_<platform>`` takes)."""
    from vflpcd.config.vehicles import CONTROL_NAMES, QUAD_CONTROL_NAMES

    return CONTROL_NAMES if platform == "ground" else QUAD_CONTROL_NAMES
