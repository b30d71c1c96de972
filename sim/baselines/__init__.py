"""Baseline controllers, all behind the ``Controller`` protocol, chosen by name."""

from __future__ import annotations

from typing import Callable

from vflpcd.core.ports import Controller
from vflpcd.errors import ConfigError


def _pure_pursuit(scenario, **_) -> Controller:
    from sim.baselines.pure_pursuit import PurePursuit, PurePursuitGains
    from sim.plants.dynamic_bicycle import BicycleConfig

    return PurePursuit(scenario.path, scenario.v_desired, scenario.a_lat_max,
                       BicycleConfig.load(scenario.params), PurePursuitGains.load())


def _nmpc_cbf(scenario, **_) -> Controller:
    from sim.baselines.nmpc_cbf import make_nmpc_cbf

    return make_nmpc_cbf(scenario)


def _vflpc(scenario, **options) -> Controller:
    from sim.lpc import make_vflpc

    return make_vflpc(scenario, **options)


def _vflpc_ml(scenario, **options) -> Controller:
    from sim.lpc import make_vflpc

    return make_vflpc(scenario, compensation=True, name="vflpc_ml", **options)


def _koopman_mpc(scenario, **options) -> Controller:
    from sim.baselines.koopman_mpc import KoopmanMPC
    from sim.lpc import load_params, make_vflpc

    return make_vflpc(scenario, solver=KoopmanMPC(load_params(scenario.platform).max_threats), name="koopman_mpc",
                      **options)


def _pd_tracker(scenario, **_) -> Controller:
    from sim.baselines.pd_tracker import PDGains, PDTracker

    return PDTracker(scenario.path, scenario.v_desired, scenario.a_lat_max, PDGains.load())


# name -> (factory(scenario), platforms it drives)
CONTROLLERS: dict[str, tuple[Callable[..., Controller], tuple[str, ...]]] = {
    "pure_pursuit": (_pure_pursuit, ("ground",)),
    "nmpc_cbf": (_nmpc_cbf, ("ground",)),
    "pd_tracker": (_pd_tracker, ("aerial",)),
    "vflpc": (_vflpc, ("ground", "aerial")),
    "vflpc_ml": (_vflpc_ml, ("ground",)),
    "koopman_mpc": (_koopman_mpc, ("ground", "aerial")),
}

DEFAULT_CONTROLLER = {"ground": "pure_pursuit", "aerial": "pd_tracker"}


def make_controller(name: str, scenario, *, source: tuple[str, str] = ("command line", "--controller"),
                    **options) -> Controller:
    """Build controller ``name`` for ``scenario``; ConfigError naming ``source`` (file, field) if
    unknown or for another platform. ``options`` (model_path, period) reach the model-based
    controllers (VF-LPC and its Koopman-MPC twin); the others take none."""
    if name not in CONTROLLERS:
        raise ConfigError(*source, f"unknown controller {name!r} (available: {', '.join(sorted(CONTROLLERS))})")
    factory, platforms = CONTROLLERS[name]
    if scenario.platform not in platforms:
        raise ConfigError(*source, f"{name} drives {'/'.join(platforms)} robots but scenario {scenario.name!r} is "
                                   f"{scenario.platform} (try {DEFAULT_CONTROLLER[scenario.platform]})")
    return factory(scenario, **options)
