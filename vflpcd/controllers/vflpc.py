"""Builds VF-LPC (and its OSQP Koopman-MPC twin) for a scenario from the shipped configuration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from vflpcd.core.control.error_model import Limits
from vflpcd.core.dynamics.compensation import KoopmanCompensation, OnlineCompensator, channel_rows
from vflpcd.config.koopman_file import load_koopman
from vflpcd.core.dynamics.sparse_gp import SEHyper
from vflpcd.core.guidance.planner import GuidancePlanner
from vflpcd.core.guidance.planner3d import GuidancePlanner3D
from vflpcd.core.guidance.tighten import Body
from vflpcd.config.params import vflpc_params
from vflpcd.core.vflpc import VFLPC, VFLPCParams
from vflpcd.controllers.loops import (ald_loop, ebrhrl_loop, encoder_loop, gp_add_loop, guidance_loops, path_loop,
                                     scheduled_problem_loop, tick_loops)
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table
from vflpcd.config.vehicles import state_names

MODELS = {"ground": "dynamic_bicycle.npz", "aerial": "quadrotor.npz"}
BODY_DISCS = 6   # covering discs of the car body for the tight path (6: 8 cm over the sides of the SUV)


def planner_body(scenario, param_set: str = "nominal") -> Body:
    """The body the guidance's tight path keeps clear and the reference's heading follows: the
    footprint's covering discs, yawed in bends by the car's steady slip angle (``Body.rear_axle``,
    ``Body.slip_gain``) with the parameter set ``param_set`` of config/plants/dynamic_bicycle.toml:
    what the controller knows of the car ([vehicle] params of vflpc.toml), not the simulated plant's
    own set (the "exact" car of the model-uncertainty runs)."""
    f = scenario.footprint.with_discs(BODY_DISCS)
    if scenario.platform != "ground":
        return Body(np.asarray(f.offsets, float), float(f.radius))
    from vflpcd.config.vehicles import BicycleConfig

    p = BicycleConfig.load(param_set).params
    slip_gain = p.m * p.lf / (2.0 * p.Car * p.wheelbase)       # m lf / (C_r L), C_r = 2 Car (per tyre)
    return Body(np.asarray(f.offsets, float), float(f.radius), float(p.lr), float(slip_gain))


def load_params(platform: str, path: str | Path | None = None) -> VFLPCParams:
    path = Path(path) if path is not None else config_dir() / "controllers" / "vflpc.toml"
    return vflpc_params(load_table(path), platform)


def limits_for(scenario, dt: float) -> Limits:
    """Actuator limits of the scenario's plant, the rate limit per control step."""
    if scenario.platform == "ground":
        from vflpcd.config.vehicles import BicycleConfig

        lim = BicycleConfig.load(scenario.params).limits
        return Limits(np.array([lim.a_min, -lim.delta_max]), np.array([lim.a_max, lim.delta_max]),
                      np.array([np.inf, lim.delta_rate_max * dt]))
    from vflpcd.config.vehicles import QuadrotorParams

    a = QuadrotorParams.from_toml().accel_max
    return Limits(np.full(3, -a), np.full(3, a), np.full(3, np.inf))


def curvature_limit(scenario) -> float:
    """The robot's geometric path-curvature limit: tan(delta_max) / L for the car, none (inf) for
    the quadrotor."""
    if scenario.platform != "ground":
        return np.inf
    from vflpcd.config.vehicles import BicycleConfig

    cfg = BicycleConfig.load(scenario.params)
    return float(np.tan(cfg.limits.delta_max) / cfg.params.wheelbase)


def curvature_rate_limit(scenario) -> float:
    """The robot's steering rate limit as a rate of path curvature: delta_rate_max / L for the car
    (1/(m s), at small steering angles, where it binds most), none (inf) for the quadrotor."""
    if scenario.platform != "ground":
        return np.inf
    from vflpcd.config.vehicles import BicycleConfig

    cfg = BicycleConfig.load(scenario.params)
    return float(cfg.limits.delta_rate_max / cfg.params.wheelbase)


def compensator_for(model, params: VFLPCParams) -> OnlineCompensator:
    """The GP on the channels of ``[compensation]`` (config/controllers/vflpc.toml; B_d selects them,
    paper section "Model Uncertainties Learning"), input z = [channels, rho_e, u] without the pose
    channels (a sample's pose is the origin of its window frame: zero), its sizes, initial
    hyper-parameters and the refits' bounds on them from the same table."""
    rows, inputs = channel_rows(model.state_names, params.gp_channels)
    n_y = len(rows)
    B_d = np.zeros((model.n_K, n_y))
    B_d[rows, range(n_y)] = 1.0
    z_index = inputs + list(range(model.n_x, model.n_K - 1))
    comp = KoopmanCompensation(model.A, model.B, B_d, z_index, B_s=model.B_s if model.scheduled else None,
                               schedule=model.schedule_index)
    hyp = SEHyper(ell=np.full(n_y, params.gp_ell), sf2=np.full(n_y, params.gp_sf2), sn2=np.full(n_y, params.gp_sn2))
    bounds = tuple((float(np.log(lo)), float(np.log(hi))) for lo, hi in params.gp_bounds)
    return OnlineCompensator(comp, hyp, nu=params.gp_nu, m_max=params.gp_m_max, n_max=params.gp_n_max, bounds=bounds,
                             add_loop=gp_add_loop(), ald_loop=ald_loop())


def make_vflpc(scenario, *, compensation: bool = False, solver=None, name: str = "vflpc",
               model_path: str | Path | None = None, period: float | None = None) -> VFLPC:
    """VF-LPC for ``scenario`` with the shipped model (or ``model_path``) and config; ``solver``
    replaces Eb-RHRL; ``period``: the control tick period (default the model's dt)."""
    params = load_params(scenario.platform)
    model = load_koopman(model_path or config_dir() / "models" / MODELS[scenario.platform])
    model.compile_encoder(encoder_loop())
    period = model.dt if period is None else float(period)
    planner_cls = GuidancePlanner if scenario.dim == 2 else GuidancePlanner3D
    planner = planner_cls(scenario.path, scenario.guidance, scenario.v_desired, scenario.a_lat_max,
                          scenario.footprint.radius, model.dt, kappa_limit=curvature_limit(scenario),
                          body=planner_body(scenario, params.vehicle_params), loops=guidance_loops,
                          kappa_rate_limit=curvature_rate_limit(scenario))
    planner.warm()          # the compiled loops loaded now, not in the first tick's plan
    if compensation and not np.isclose(scenario.control_period, model.dt):
        raise ValueError(f"GP compensation learns one-model-step transitions: scenario {scenario.name!r} runs "
                         f"every {scenario.control_period} s, the model steps {model.dt} s")
    return VFLPC(planner, model, params, limits_for(scenario, period), scenario.footprint.radius,
                 scenario.guidance.safety_margin, solver=solver,
                 compensator=compensator_for(model, params) if compensation else None, name=name,
                 state_names=state_names(scenario.platform), period=period, solve_loop=ebrhrl_loop(),
                 path_loop=path_loop(), problem_loop=scheduled_problem_loop() if model.scheduled else None,
                 tick_loops=tick_loops())


def make_vflpc_ml(scenario, **options) -> VFLPC:
    """VF-LPC with the online GP compensation (paper section IV, "Model Uncertainties Learning")."""
    return make_vflpc(scenario, compensation=True, name="vflpc_ml", **options)
