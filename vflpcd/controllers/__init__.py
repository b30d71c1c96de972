"""The controllers, all behind the ``Controller`` protocol, chosen by name through one lazy table.

``CONTROLLERS`` maps a name to ``"module:factory"`` and the platforms it drives (as python-can's
interface table does): a controller's module, and its solver (CasADi, OSQP), is imported only
when it is built. A factory takes the scenario (the route and the vehicle) and the options
``model_path`` and ``period`` (the model-based ones use them, the others ignore them).
"""

from __future__ import annotations

import importlib

from vflpcd.base.errors import ConfigError
from vflpcd.core.ports import Controller

CONTROLLERS: dict[str, tuple[str, tuple[str, ...]]] = {
    "vflpc": ("vflpcd.controllers.vflpc:make_vflpc", ("ground", "aerial")),
    "vflpc_ml": ("vflpcd.controllers.vflpc:make_vflpc_ml", ("ground",)),
    "koopman_mpc": ("vflpcd.controllers.koopman_mpc:make_koopman_mpc", ("ground", "aerial")),
    "nmpc_cbf": ("vflpcd.controllers.nmpc_cbf:make_nmpc_cbf", ("ground",)),
    "nmpc_rti": ("vflpcd.controllers.nmpc_rti:make_nmpc_rti", ("ground",)),
    "pure_pursuit": ("vflpcd.controllers.pure_pursuit:make_pure_pursuit", ("ground",)),
    "pd_tracker": ("vflpcd.controllers.pd_tracker:make_pd_tracker", ("aerial",)),
}

DEFAULT_CONTROLLER = {"ground": "pure_pursuit", "aerial": "pd_tracker"}


def make_controller(name: str, scenario, *, source: tuple[str, str] = ("command line", "--controller"),
                    **options) -> Controller:
    """Build controller ``name`` for ``scenario``; ConfigError naming ``source`` (file, field) if
    unknown or for another platform. ``options`` (model_path, period) reach the model-based
    controllers (VF-LPC and its Koopman-MPC twin); the others take none."""
    if name not in CONTROLLERS:
        raise ConfigError(*source, f"unknown controller {name!r} (available: {', '.join(sorted(CONTROLLERS))})")
    target, platforms = CONTROLLERS[name]
    if scenario.platform not in platforms:
        raise ConfigError(*source, f"{name} drives {'/'.join(platforms)} robots but scenario {scenario.name!r} is "
                                   f"{scenario.platform} (try {DEFAULT_CONTROLLER[scenario.platform]})")
    module, factory = target.split(":")
    return getattr(importlib.import_module(module), factory)(scenario, **options)
