"""Every registered controller and every platform driver against the declared ports
(``vflpcd.core.ports``): what the runner and the daemon call is there, nothing is probed."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from drivers import PLATFORMS, make_platform
from sim.plants import make_plant
from vflpcd.config.mission import load_mission
from vflpcd.config.scenarios import load_scenario
from vflpcd.base.paths import config_dir
from vflpcd.controllers import CONTROLLERS, make_controller
from vflpcd.core.ports import ControllerBase, ControllerStatus, PlatformBase

SCENARIO = {"ground": "carsim_avoidance", "aerial": "uav_3d"}
REQUIRED = ("connect", "enable", "latest_state", "send", "failsafe", "close")
JOBS = ("take_replan", "install_plan", "replan_failed", "take_refit", "install_model")   # WorkerJobs


@pytest.mark.parametrize("name, platform", [(n, p) for n, (_, ps) in CONTROLLERS.items() for p in ps])
def test_every_registered_controller_keeps_the_controller_port(name, platform):
    scenario = load_scenario(SCENARIO[platform])
    ctl = make_controller(name, scenario)
    assert isinstance(ctl, ControllerBase) and ctl.name == name
    plant = make_plant(scenario, 0)
    ctl.reset()
    ctl.prepare(plant.state, 0.0, ())
    u = np.asarray(ctl.step(plant.state, 0.0, ()), float)
    assert u.shape == (len(plant.control_names),) and np.all(np.isfinite(u))
    ctl.settle()                                   # after the command (the runner and the daemon call it)
    assert isinstance(ctl.status(), ControllerStatus)
    ref = ctl.reference_at(0.0)
    assert ref is None or ref.shape == (scenario.dim,)
    if ctl.jobs is not None:                       # its background work follows WorkerJobs
        assert all(callable(getattr(ctl.jobs, m)) for m in JOBS) and ctl.jobs.planner is not None
    if ctl.planning is not None:                   # its plan is what the safety monitors check
        plan = ctl.planning
        assert plan.current_plan is not None and plan.replans >= 1 and plan.replan_failures == 0
        assert hasattr(plan, "plan_gate")


MISSION = {"can": "vehicle_can.toml", "mavlink": "quad_sitl.toml", "inproc": "vehicle_inproc.toml"}


@pytest.mark.parametrize("kind", sorted(PLATFORMS))
def test_every_driver_keeps_the_platform_port(kind):
    module, factory = PLATFORMS[kind].split(":")
    assert callable(getattr(importlib.import_module(module), factory))
    mission = load_mission(config_dir() / "missions" / MISSION[kind])
    platform = make_platform(kind, mission.scenario, mission.platform.options, mission.file)
    cls = type(platform)
    assert isinstance(platform, PlatformBase)
    for member in REQUIRED:                        # the required members are the driver's own
        assert getattr(cls, member) is not getattr(PlatformBase, member), f"{cls.__name__}.{member}"
    assert platform.safe_action in ("brake_to_stop", "hold_then_land")
    assert (platform.safe_action == "hold_then_land") == ("Z" in platform.state_names)
    if platform.prepares:
        assert cls.prepare is not PlatformBase.prepare
    if platform.injects_faults:
        assert cls.inject is not PlatformBase.inject
    assert platform.state_names and platform.control_names


def test_the_base_classes_defaults_are_safe():
    base = PlatformBase()
    assert base.fault() is None and base.at_rest is None and base.link_stats() == {}
    assert not base.prepares and not base.injects_faults
    with pytest.raises(NotImplementedError):
        base.inject("nan_state")
    ctl = ControllerBase()
    assert ctl.status() == ControllerStatus() and ctl.reference_at(1.0) is None and ctl.jobs is None
    assert ctl.prepare(np.zeros(6), 0.0) is None
