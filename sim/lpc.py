"""Builds VF-LPC (and its OSQP Koopman-MPC twin) for a scenario from the shipped configuration."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.plants import make_plant
from vflpcd.core.control.error_model import Limits
from vflpcd.core.dynamics.compensation import KoopmanCompensation, OnlineCompensator
from vflpcd.core.dynamics.koopman import load_koopman
from vflpcd.core.dynamics.sparse_gp import SEHyper
from vflpcd.core.guidance.planner import GuidancePlanner
from vflpcd.core.guidance.planner3d import GuidancePlanner3D
from vflpcd.core.vflpc import VFLPC, VFLPCParams
from vflpcd.paths import config_dir
from vflpcd.tomlread import Table, load_toml

MODELS = {"ground": "dynamic_bicycle.npz", "aerial": "quadrotor.npz"}


def load_params(platform: str, path: str | Path | None = None) -> VFLPCParams:
    path = Path(path) if path is not None else config_dir() / "controllers" / "vflpc.toml"
    return VFLPCParams.from_table(Table(load_toml(path), path), platform)


def limits_for(scenario, dt: float) -> Limits:
    """Actuator limits of the scenario's plant, the rate limit per control step."""
    if scenario.platform == "ground":
        from sim.plants.dynamic_bicycle import BicycleConfig

        lim = BicycleConfig.load(scenario.params).limits
        return Limits(np.array([lim.a_min, -lim.delta_max]), np.array([lim.a_max, lim.delta_max]),
                      np.array([np.inf, lim.delta_rate_max * dt]))
    from sim.plants.quadrotor import QuadrotorParams

    a = QuadrotorParams.from_toml().accel_max
    return Limits(np.full(3, -a), np.full(3, a), np.full(3, np.inf))


def curvature_limit(scenario) -> float:
    """The robot's geometric path-curvature limit: tan(delta_max) / L for the car, none (inf) for
    the quadrotor."""
    if scenario.platform != "ground":
        return np.inf
    from sim.plants.dynamic_bicycle import BicycleConfig

    cfg = BicycleConfig.load(scenario.params)
    return float(np.tan(cfg.limits.delta_max) / cfg.params.wheelbase)


def compensator_for(model) -> OnlineCompensator:
    """GP on [vx, vy, omega] (B_d = [0_3 I_3 0]^T, paper section "Model Uncertainties Learning"),
    input z = [vx, vy, omega, rho_e, u]."""
    names = model.state_names
    rows = [names.index(n) for n in ("vx", "vy", "omega")]
    B_d = np.zeros((model.n_K, 3))
    B_d[rows, [0, 1, 2]] = 1.0
    z_index = rows + list(range(model.n_x, model.n_K - 1))
    comp = KoopmanCompensation(model.A, model.B, B_d, z_index)
    hyp = SEHyper(ell=np.full(3, 3.0), sf2=np.full(3, 0.05), sn2=np.full(3, 1e-4))
    return OnlineCompensator(comp, hyp, nu=0.05, m_max=48, n_max=400)


def make_vflpc(scenario, *, compensation: bool = False, solver=None, name: str = "vflpc",
               model_path: str | Path | None = None, period: float | None = None) -> VFLPC:
    """VF-LPC for ``scenario`` with the shipped model (or ``model_path``) and config; ``solver``
    replaces Eb-RHRL; ``period``: the control tick period (default the model's dt)."""
    params = load_params(scenario.platform)
    model = load_koopman(model_path or config_dir() / "models" / MODELS[scenario.platform])
    period = model.dt if period is None else float(period)
    planner_cls = GuidancePlanner if scenario.dim == 2 else GuidancePlanner3D
    planner = planner_cls(scenario.path, scenario.guidance, scenario.v_desired, scenario.a_lat_max,
                          scenario.footprint.radius, model.dt, kappa_limit=curvature_limit(scenario))
    if compensation and not np.isclose(scenario.control_period, model.dt):
        raise ValueError(f"GP compensation learns one-model-step transitions: scenario {scenario.name!r} runs "
                         f"every {scenario.control_period} s, the model steps {model.dt} s")
    return VFLPC(planner, model, params, limits_for(scenario, period), scenario.footprint.radius,
                 scenario.guidance.safety_margin, solver=solver,
                 compensator=compensator_for(model) if compensation else None, name=name,
                 state_names=make_plant(scenario, 0).state_names, period=period)
