"""VF-LPC as a Controller: tracking on the shipped model, input checks, the LQR fallback."""

import dataclasses

import numpy as np
import pytest

from vflpcd.controllers.vflpc import make_vflpc
from sim.plants import make_plant
from vflpcd.config.scenarios import load_scenario
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Circle
from vflpcd.core.jobs import run_inline


@pytest.fixture(scope="module")
def straight():
    sc = load_scenario("carsim_avoidance")
    return dataclasses.replace(sc, obstacles=())


def test_tracks_the_guidance_reference_without_fallbacks(straight):
    ctrl = make_vflpc(straight)
    plant = make_plant(straight, 0)
    for k in range(80):                       # 4 s on the first straight
        u = ctrl.step(plant.state, k * 0.05)
        assert np.all(np.isfinite(u))
        plant.step(u, 0.05)
    proj = straight.path.project(plant.position())
    assert abs(proj.lateral) < 0.1
    assert abs(plant.state[3] - straight.v_desired) < 0.3
    assert ctrl.fallbacks == 0 and ctrl.last_info.converged


def test_bad_state_and_obstacles_are_rejected(straight):
    ctrl = make_vflpc(straight)
    with pytest.raises(ValueError, match="finite"):
        ctrl.step(np.array([0.0, 0.0, 0.0, np.nan, 0.0, 0.0]), 0.0)
    bad = ObstacleState("ghost", Circle(1.0), np.array([np.inf, 0.0]), 0.0, np.zeros(2), 0.0)
    with pytest.raises(ValueError, match="ghost"):
        ctrl.step(make_plant(straight, 0).state, 0.0, [bad])


def test_diverging_solver_falls_back_to_the_terminal_lqr(straight):
    ctrl = make_vflpc(straight)
    plant = make_plant(straight, 0)

    class Broken:
        def solve(self, problem, barrier, bounds=None):
            return np.full((problem.N, problem.n_u), np.nan), None

        def shift(self):
            pass

        def reset(self):
            Broken.resets += 1

    Broken.resets = 0
    ctrl.solver = Broken()
    ctrl._cruise_mode = (ctrl.rate, ctrl.solver)            # the cruise weights' solver (``_select_mode``)
    ctrl._light_mode = (ctrl._light_mode[0], Broken())     # the light weights' solver fails too (tried first)
    u = ctrl.step(plant.state, 0.0)
    # one reset as the light weights are entered, one per failed solve (light, then heavy)
    assert np.all(np.isfinite(u)) and ctrl.fallbacks == 2 and Broken.resets == 3
    assert np.all(u >= ctrl.limits.u_min) and np.all(u <= ctrl.limits.u_max)


def test_a_due_replan_waits_for_the_background_and_the_next_step_uses_it(straight):
    ctrl = make_vflpc(straight)
    plant = make_plant(straight, 0)
    ctrl.step(plant.state, 0.0)
    assert ctrl.replans == 1                       # the first reference is planned at once
    walker = ObstacleState("walker", Circle(0.4), np.array([30.0, 4.0]), 0.0, np.array([0.0, -1.0]), 0.05)
    first = ctrl._plan
    ctrl.step(plant.state, 0.05, [walker])        # the obstacle picture changed: a replan is due ...
    assert ctrl.replans == 1 and ctrl._plan is first
    assert run_inline(ctrl.jobs) == 1             # ... and runs as worker work
    assert ctrl.replans == 2 and ctrl._plan is not first
    assert run_inline(ctrl.jobs) == 0             # nothing more is due
    assert ctrl.replans == 2


def test_the_quadrotor_state_is_picked_by_name():
    sc = load_scenario("uav_3d")
    ctrl = make_vflpc(sc)
    plant = make_plant(sc, 0)
    assert len(plant.state) == 13 and ctrl.model.n_x == 6
    u = ctrl.step(plant.state, 0.0)
    assert u.shape == (3,) and np.all(np.isfinite(u))
    with pytest.raises(ValueError, match="13 finite numbers"):
        ctrl.step(plant.state[:6], 0.05)



def test_a_failed_solve_goes_on_with_the_last_plan_before_the_terminal_lqr(straight):
    ctrl = make_vflpc(straight)
    plan = np.arange(2.0 * ctrl.N).reshape(ctrl.N, 2)

    class Flaky:
        ok = True

        def solve(self, problem, barrier, bounds=None):
            return (plan.copy() if Flaky.ok else np.full((problem.N, problem.n_u), np.nan)), None

        def shift(self):
            pass

        def reset(self):
            pass

    class Horizon:                                   # a tick's horizon: its problem solved, its start
        problem = dataclasses.make_dataclass("P", ["x0", "N", "n_u"])(np.ones(3), ctrl.N, 2)

        def solve(self, rate, solver, barrier, bounded=False):
            return solver.solve(self.problem, barrier)

        def start(self, rate):
            return self.problem.x0

    ctrl.solver = Flaky()
    rate = dataclasses.make_dataclass("Rate", ["K_terminal"])(np.full((2, 3), 1.0))
    ctrl._ticks = 7
    assert ctrl._solve(Horizon(), rate, None).tolist() == plan[0].tolist()
    Flaky.ok = False
    for k in range(1, ctrl.N):                       # the plan's step k, k ticks after it was solved
        ctrl._ticks = 7 + k
        assert ctrl._solve(Horizon(), rate, None).tolist() == plan[k].tolist()
    ctrl._ticks = 7 + ctrl.N                         # its steps spent: the rate form's terminal LQR law
    assert ctrl._solve(Horizon(), rate, None).tolist() == [-3.0, -3.0]
    assert ctrl.fallbacks == ctrl.N


FIT_AT = 40     # the step after which ``_learning_run`` fits the GP (every later sample is folded into it)


def _learning_run(scenario, settle: bool, steps: int = 60, compensation: bool = True):
    """Commands and GP sample counts of a VF-LPC driven on the plant, with ``settle`` called after
    each command or left to the next step; a learning one's GP is fitted after step ``FIT_AT`` (its
    pending sample settled first in both cases), so that the later commands use the samples."""
    ctrl = make_vflpc(scenario, compensation=compensation)
    plant = make_plant(scenario, 0)
    commands, samples = [], []
    for k in range(steps):
        before = ctrl.compensator.n_buffered if compensation else 0
        u = ctrl.step(plant.state, k * 0.05)
        if compensation:
            samples.append((before, ctrl.compensator.n_buffered))
            if settle:
                ctrl.settle()
                samples[-1] += (ctrl.compensator.n_buffered,)
            if k == FIT_AT:
                ctrl.settle()
                assert ctrl.compensator.refit() is not None
        commands.append(u)
        plant.step(u, 0.05)
    return np.array(commands), samples


def test_the_gp_sample_of_a_step_is_taken_after_its_command_by_settle_or_at_the_next_step(straight):
    """The command does not wait for the sample of the transition it saw: ``settle`` takes it after
    the command (one sample a step from the second on), and a caller that never settles gets the
    same commands, the sample taken at the next step's start, before the step's problem: once the
    GP is fitted each command depends on the samples folded into it (it differs from the
    commands without a GP)."""
    settled, with_settle = _learning_run(straight, settle=True)
    unsettled, without = _learning_run(straight, settle=False)
    plain, _ = _learning_run(straight, settle=True, compensation=False)
    assert all(step == before for before, step, _ in with_settle)                  # step itself adds none
    assert [after - step for _, step, after in with_settle] == [0] + [1] * (len(with_settle) - 1)
    assert [step - before for before, step in without[FIT_AT + 2:]] == [1] * (len(without) - FIT_AT - 2)  # the one before's
    assert without[-1][1] == with_settle[-1][2] - 1                                 # the last one still pending
    np.testing.assert_array_equal(unsettled, settled)
    assert np.all(settled[FIT_AT + 2:] != plain[FIT_AT + 2:])                      # the fitted GP steers them


def test_the_solvers_warm_start_is_shifted_after_the_command_once(straight):
    """The step's solver's weights move one step along the horizon in ``settle`` (after the command,
    before the next solve), once; a step whose settle was not called shifts them first."""
    ctrl = make_vflpc(straight)
    plant = make_plant(straight, 0)
    ctrl.step(plant.state, 0.0)
    solver = ctrl.solver
    solver.W_a[:] = np.random.default_rng(0).normal(size=solver.W_a.shape)
    W = solver.W_a.copy()
    ctrl.settle()
    assert np.array_equal(solver.W_a[:-1], W[1:]) and np.array_equal(solver.W_a[-1], W[-1])
    ctrl.settle()                                    # nothing left to shift
    assert np.array_equal(solver.W_a[:-1], W[1:])
    ctrl.step(plant.state, ctrl.dt)
    solver.W_a[:] = W
    shifted = []
    real = solver.shift
    solver.shift = lambda: shifted.append(True) or real()
    ctrl.step(plant.state, 2 * ctrl.dt)              # its settle, left out, runs before the solve
    assert shifted == [True]


def test_each_steps_arc_length_is_found_once_after_its_command_or_when_a_replan_asks(straight):
    """The path's arc length of a step's position (a replan's start) is not searched before the
    command: ``settle`` finds it, searching near the last one; a replan asked before that finds it."""
    ctrl = make_vflpc(straight)
    plant = make_plant(straight, 0)
    path = ctrl.planner.path
    u = ctrl.step(plant.state, 0.0)
    ctrl.settle()
    for k in range(1, 6):
        plant.step(u, ctrl.dt)
        before = ctrl._s
        u = ctrl.step(plant.state, k * ctrl.dt)
        assert ctrl._s == before                                  # the command did not wait for it
        expect = path.arc_length_of(plant.state[:2], before, loop=ctrl._path_loop)
        if k % 2:
            ctrl.settle()
            assert ctrl._s == expect and ctrl.take_replan(force_at=k * ctrl.dt).s == expect
        else:                                                     # a replan before the settle
            assert ctrl.take_replan(force_at=k * ctrl.dt).s == expect
            ctrl.settle()
            assert ctrl._s == expect                              # found once
    assert expect > 1.0
