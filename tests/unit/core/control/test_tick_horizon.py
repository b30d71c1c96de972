"""The tick's horizon in one compiled call (``CompiledHorizon``, ``horizon_kernel``) against the same
horizon built call by call (``ProblemHorizon``): the same commands, bit for bit, in closed loop with
the GP's correction on, with a mover's barrier on, for the quadrotor's problem without an increment
form, and when every solve is thrown away (the held plan, then the terminal law)."""

import dataclasses

import numpy as np
import pytest

from sim.runner import run_closed_loop
from vflpcd.config.scenarios import load_scenario
from vflpcd.controllers import loops, make_controller
from vflpcd.core.control.tick_horizon import CompiledHorizon, ProblemHorizon

pytestmark = pytest.mark.skipif(loops.tick_loops() is None, reason="numba is not installed (no compiled horizon)")


def _pair(scenario, name):
    compiled, calls = make_controller(name, scenario), make_controller(name, scenario)
    assert isinstance(compiled._tick_horizon, CompiledHorizon)
    calls._tick_horizon = ProblemHorizon(calls.errors, calls._command_loop)
    return compiled, calls


def _threatened_ticks(ctrl) -> list:
    seen = []
    real = ctrl._barrier

    def barrier(*a):
        b = real(*a)
        seen.append(b.count)
        return b

    ctrl._barrier = barrier
    return seen


@pytest.mark.parametrize("scene, name, t_max", [("racing_track", "vflpc_ml", 8.0),
                                                ("config/scenarios/suite/pedestrian_appears.toml", "vflpc", None),
                                                ("uav_3d", "vflpc", 5.0)])
def test_the_compiled_horizon_commands_what_the_calls_one_by_one_do(scene, name, t_max):
    scenario = load_scenario(scene)
    if t_max is not None:
        scenario = dataclasses.replace(scenario, t_max=t_max)
    compiled, calls = _pair(scenario, name)
    threats = _threatened_ticks(compiled)
    a, b = run_closed_loop(scenario, compiled, 0), run_closed_loop(scenario, calls, 0)
    assert len(a.command) > 90 and np.array_equal(a.command, b.command)
    assert compiled.fallbacks == calls.fallbacks == 0
    if name == "vflpc_ml":
        assert compiled.compensator.model is not None and compiled.compensator.model.n > 10    # the GP corrected
    if "pedestrian" in scene:
        assert sum(c > 0 for c in threats) > 10                                                 # the barrier was on
    if scene == "uav_3d":
        assert compiled.rate is None                                                            # no increment form


def test_solves_thrown_away_go_on_alike_with_the_held_plan_and_the_terminal_law():
    """With a divergence bound that every solve exceeds, both horizons command the held plan's
    steps and then the terminal LQR law (built call by call: the compiled call made neither)."""
    scenario = dataclasses.replace(load_scenario("carsim_avoidance"), t_max=2.0)
    compiled, calls = _pair(scenario, "vflpc")
    for ctrl in (compiled, calls):
        ctrl._divergence_bound = [1e-9] * len(ctrl._divergence_bound)
    a, b = run_closed_loop(scenario, compiled, 0), run_closed_loop(scenario, calls, 0)
    assert compiled.fallbacks == calls.fallbacks > 20
    assert np.array_equal(a.command, b.command) and np.all(np.isfinite(a.command))
