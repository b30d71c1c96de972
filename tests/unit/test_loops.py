"""Core's loops compiled with numba: once per process, and in memory where no cache can be written."""

import dataclasses
import logging

import pytest

numba = pytest.importorskip("numba")

from vflpcd.controllers import loops  # noqa: E402


def test_the_loop_is_compiled_once_per_process():
    loops.ebrhrl_loop.cache_clear()
    first = loops.ebrhrl_loop()
    assert first is not None and loops.ebrhrl_loop() is first
    assert first.__name__ == "solve_loop" and hasattr(first, "signatures")      # a numba dispatcher


def test_without_a_writable_cache_it_compiles_in_memory(monkeypatch, caplog):
    real = numba.njit

    def njit(*args, cache=False, **kw):
        if cache:
            raise RuntimeError("cannot cache function 'solve_loop': no locator available")
        return real(*args, cache=cache, **kw)

    monkeypatch.setattr(numba, "njit", njit)
    loops.ebrhrl_loop.cache_clear()
    try:
        with caplog.at_level(logging.WARNING, logger="vflpcd.controllers.loops"):
            loop = loops.ebrhrl_loop()
        assert loop is not None and "event=loop_cache_unavailable" in caplog.text
    finally:
        loops.ebrhrl_loop.cache_clear()


def test_the_loop_is_loaded_before_the_first_tick_for_the_types_the_solver_passes(tmp_path):
    """ebrhrl_loop() compiles the signature that VF-LPC's solver calls with: its first step adds none."""
    import numpy as np

    from vflpcd.config.scenarios import line_scenario_toml, load_scenario
    from vflpcd.controllers import make_controller

    loops.ebrhrl_loop.cache_clear()
    loop = loops.ebrhrl_loop()
    assert len(loop.signatures) == 1
    f = tmp_path / "line.toml"
    f.write_text(line_scenario_toml("line"))
    ctrl = make_controller("vflpc", load_scenario(f))
    assert ctrl.solver.loop is loop
    ctrl.step(np.array([0.0, 0.3, 0.0, 5.0, 0.0, 0.0]), 0.0)
    assert len(loop.signatures) == 1


def test_the_tick_and_gp_loops_are_warmed_for_the_types_a_learning_run_passes():
    """A run of VF-LPC with the online GP (its samples tested and folded in, its window and lift,
    linearisation, GP correction, increment form, command clip, reference rows and horizon compiled), a
    refit's model coming back from a worker, a quadrotor's run, a car behind a slow car (the barrier's
    safety points) and a perceived mover (read-only arrays) add no signature to the warmed loops: none
    compiles in a tick."""
    import dataclasses
    import pickle

    import numpy as np

    from sim.runner import run_closed_loop
    from vflpcd.base.paths import config_dir
    from vflpcd.config.scenarios import load_scenario
    from vflpcd.controllers import make_controller
    from vflpcd.core.obstacles import ObstacleState
    from vflpcd.core.shapes import Circle

    gp, tick, ald = loops.gp_add_loop(), loops.tick_loops(), loops.ald_loop()
    compiled = (gp, tick.window, tick.linearisation, tick.correction, tick.increment, tick.command, tick.reference,
                ald, tick.horizon, tick.lift, tick.barrier, loops.encoder_loop())
    before = tuple(len(loop.signatures) for loop in compiled)
    assert before == (1, 1, 1, 1, 2, 1, 1, 1, 1, 1, 1, 1)   # the increment form: a nominal B and a scheduled one
    scenario = dataclasses.replace(load_scenario("racing_track"), t_max=6.0)
    ctrl = make_controller("vflpc_ml", scenario)
    run_closed_loop(scenario, ctrl, 0)
    model = ctrl.compensator.model
    assert model is not None and model.n > 10                  # samples were folded in
    back = pickle.loads(pickle.dumps(model))                    # a refit comes back from a worker process
    back.add_sample(np.zeros(back.n_z), np.zeros(back.n_y), gp)
    U = np.zeros((ctrl.N + 1, ctrl.model.n_K))
    ctrl.errors.comp.corrected_next(U[1:], U[:-1], np.zeros((ctrl.N, ctrl.model.n_u)), back, tick.correction)
    ctrl._tick_horizon.begin(ctrl._last[0], np.zeros(ctrl.model.n_u), back).solve(ctrl.rate, ctrl.solver, None)
    assert ctrl.rate.loop is tick.increment and ctrl._command_loop is tick.command
    assert ctrl._horizon._loop is tick.reference and ctrl._tick_horizon.loop is tick.horizon
    quad = dataclasses.replace(load_scenario("uav_3d"), t_max=1.0)      # its horizon without an increment form
    run_closed_loop(quad, make_controller("vflpc", quad), 0)
    slow_car = dataclasses.replace(load_scenario(config_dir() / "scenarios" / "suite" / "follow_slow_car.toml"),
                                   t_max=8.0)                              # a mover threatening: the barrier on
    car = make_controller("vflpc", slow_car)
    threats = []
    in_window = car.errors.safety_points_in_window

    def counted(frame, obstacle, *args):
        threats.append(obstacle.id)
        return in_window(frame, obstacle, *args)

    car.errors.safety_points_in_window = counted
    run_closed_loop(slow_car, car, 0)
    assert len(threats) > 20                                              # the barrier's points, compiled
    frame = car._last[0]
    centre, velocity = np.array([3.0, 0.5]), np.array([1.0, 0.0])
    centre.flags.writeable = velocity.flags.writeable = False             # as ``perception`` hands them over
    perceived = ObstacleState("ped", Circle(0.3), centre, 0.0, velocity, 0.0)
    out = np.empty((2, car.N + 1, 2))
    car.errors.safety_points_in_window(frame, perceived, np.zeros((car.N + 1, 2)), np.arange(car.N + 1) * 0.05, 1.0,
                                       out[0], out[1])
    assert tuple(len(loop.signatures) for loop in compiled) == before


def test_the_safety_loops_are_warmed_for_the_types_a_supervised_run_passes():
    """Supervised runs of the car among parked and cutting-in cars and of the quadrotor among its
    obstacles (the supervisor's clearance test, pre-filter and manoeuvre, the plan monitor's search)
    add no signature to the warmed loops: none compiles in a tick."""
    from sim.bench.safety import scene
    from sim.runner import run_closed_loop
    from vflpcd.config.scenarios import load_scenario
    from vflpcd.controllers import make_controller

    sup = loops.supervisor_loops()
    compiled = (*dataclasses.astuple(sup), loops.polyline_loop())
    before = tuple(len(loop.signatures) for loop in compiled)
    assert before == (1, 1, 1, 1)
    for scenario in (dataclasses.replace(scene("cut_in"), t_max=4.0),
                     dataclasses.replace(load_scenario("uav_3d"), t_max=2.0)):
        record = run_closed_loop(scenario, make_controller("vflpc", scenario), supervised=True)
        assert (record.t_sup > 0).sum() > 30
    assert tuple(len(loop.signatures) for loop in compiled) == before


def test_the_path_loop_is_compiled_once_and_warmed_for_the_types_the_path_passes():
    import numpy as np

    loops.path_loop.cache_clear()
    loop = loops.path_loop()
    assert loop is not None and loops.path_loop() is loop and loop.__name__ == "nearest_arc_length"
    assert len(loop.signatures) == 1
    from vflpcd.core.path import ReferencePath

    path = ReferencePath.arc([0.0, 0.0], 20.0, 0.0, 2 * np.pi)
    path.arc_length_of(np.array([0.5, 0.2]), 3.0, loop=loop)
    path.arc_length_of(np.array([0.5, 0.2, 1.0])[:2], None, loop=loop)
    assert len(loop.signatures) == 1


def test_the_3d_steps_are_warmed_for_the_types_the_3d_planner_passes():
    """A quadrotor run's replans add no signature to the warmed 3-D steps: a worker that loads
    them from the cache compiles nothing at its first replan (a second signature, for the spline
    pieces in another memory layout, compiled for seconds beside a real-time loop)."""
    import dataclasses

    from sim.runner import run_closed_loop
    from vflpcd.config.scenarios import load_scenario
    from vflpcd.controllers import make_controller

    loop = loops.integrate3d_loop()
    assert loop is not None and loops.guidance_loops().steps3d is loop
    before = len(loop.signatures)
    assert before == 1
    scenario = dataclasses.replace(load_scenario("uav_3d"), t_max=17.0)
    ctrl = make_controller("vflpc", scenario)
    record = run_closed_loop(scenario, ctrl, 0)
    assert record.t_background.max() > 0.0                    # a replan ran
    assert len(loop.signatures) == before


def test_the_path_grid_fill_is_warmed_for_the_types_the_planner_passes():
    """A plan on a bent road with a parked car fills its path grid's blocks through the warmed loop
    and adds no signature to it (a worker compiles nothing at its first replan)."""
    import numpy as np

    from vflpcd.config.scenarios import default_guidance
    from vflpcd.core.guidance.planner import GuidancePlanner
    from vflpcd.core.obstacles import ObstacleState
    from vflpcd.core.path import ReferencePath
    from vflpcd.core.shapes import Box

    loop = loops.path_fill_loop()
    assert loop is not None and loops.guidance_loops().path_fill is loop
    before = len(loop.signatures)
    assert before == 1
    path = ReferencePath.from_waypoints(np.array([[0.0, 0.0], [30.0, 0.0], [60.0, 8.0]]))
    planner = GuidancePlanner(path, default_guidance(), 6.0, 3.0, 1.0, 0.05, loops=loops.guidance_loops)
    car = ObstacleState(id="car", shape=Box(4.5, 1.9), center=np.array([25.0, 0.4]), yaw=0.0,
                        velocity=np.zeros(2), stamp=0.0)
    prepared = planner.prepare(0.0, [car])
    planner.plan(prepared, np.zeros(2), 0.0, 6.0, heading=0.0)
    assert prepared.grid.path.loop is loop and sum(map(sum, prepared.grid.path.filled)) > 5
    assert len(loop.signatures) == before


WORKER = """
import pickle, sys, time
planner = pickle.load(open(sys.argv[1], "rb"))
t0 = time.perf_counter()
planner.warm()
got = planner._loops()
caches = {type(loop._cache).__name__ for loop in (got.active_set, got.steps, got.half_planes)}
print("/".join(sorted(caches)), time.perf_counter() - t0)
"""


def test_a_planner_sent_to_a_worker_process_loads_its_compiled_loops_from_the_cache(tmp_path):
    """The planner goes to the worker processes by pickle. Sent as a compiled dispatcher, its
    active-set loop arrived without numba's cache and compiled again at the first replan (6.7 s
    measured: the car stopped at the end of its first plan meanwhile); sent as the function that
    returns them, they are loaded from the cache when the worker warms up (another process here)."""
    import pickle
    import subprocess
    import sys

    from vflpcd.config.scenarios import load_scenario
    from vflpcd.controllers import make_controller

    loops.guidance_loops()                      # the caches exist (this process compiled or loaded them)
    blob = tmp_path / "planner.pkl"
    blob.write_bytes(pickle.dumps(make_controller("vflpc", load_scenario("carsim_avoidance")).planner))
    run = subprocess.run([sys.executable, "-c", WORKER, str(blob)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    cache, seconds = run.stdout.split()
    assert "NullCache" not in cache and float(seconds) < 3.0, run.stdout


def test_vflpcd_compile_compiles_every_loop_and_says_so(capsys):
    """``vflpcd compile`` (run by ``make`` at set-up) loads or compiles each loop and prints one line
    per loop; the loops are then the process's compiled ones."""
    from vflpcd.app.cli import main

    assert main(["compile"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines == [f"{name}: compiled" for name in
                     ("ebrhrl_loop", "scheduled_problem_loop", "tick_loops", "encoder_loop", "gp_add_loop", "ald_loop",
                      "path_loop",
                      "polyline_loop", "supervisor_loops", "guidance_loops")]
    assert all(hasattr(fn(), "signatures") for fn in (loops.ebrhrl_loop, loops.scheduled_problem_loop, loops.path_loop,
                                                      loops.encoder_loop))
    assert loops.guidance_loops().active_set is loops.active_set_loop()
    assert all(hasattr(fn, "signatures") for fn in dataclasses.astuple(loops.supervisor_loops()))


def test_vflpcd_compile_says_which_loops_run_interpreted_without_numba(monkeypatch, capsys):
    from vflpcd.app.cli import main

    monkeypatch.setattr(loops, "compile_all", lambda: {"ebrhrl_loop": False, "path_loop": True})
    assert main(["compile"]) == 0
    assert capsys.readouterr().out.splitlines() == ["ebrhrl_loop: interpreted (numba is not installed)",
                                                    "path_loop: compiled"]
