"""The ``vflpcd`` commands that simulate: ``sim``, ``sitl``, ``collect`` and the benches.

``vflpcd.app.cli`` defines their arguments and calls these by name when they run, so that the
production path (``run``, ``check``, ``plot``, ``watch``) never imports the simulator.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from pathlib import Path

from vflpcd.base.errors import LOG_FORMAT, ConfigError, exit_code_of


def cmd_sim(args) -> int:
    from vflpcd.controllers import DEFAULT_CONTROLLER, make_controller
    from sim.report import metrics_table, write_results
    from sim.runner import OUTCOME_EXIT, run_closed_loop
    from vflpcd.config.scenarios import load_scenario

    scenario = load_scenario(args.scenario)
    name = args.controller or DEFAULT_CONTROLLER[scenario.platform]
    controller = make_controller(name, scenario)
    record = run_closed_loop(scenario, controller, seed=args.seed, supervised=not args.no_supervisor)
    out = args.out or Path("results") / f"{scenario.name}-{name}-s{args.seed}"
    out.mkdir(parents=True, exist_ok=True)
    print(metrics_table(record, scenario))
    files = [write_results(record, scenario, out / "results.json")]
    if not args.no_plot:
        from sim.plot import plot_run

        files.append(plot_run(record, scenario, out / "plot.png"))
    for f in files:
        print(f"wrote {f}")
    return OUTCOME_EXIT[record.outcome]


def cmd_sitl(name: str, argv: list[str], description: str) -> int:
    """``vflpcd sitl NAME ARGS``: the mock's own parser gets the rest of the line."""
    if name == "quad":
        from sim.sitl import quad as mock
    else:
        from sim.sitl import can_ecu as mock
    parser = argparse.ArgumentParser(prog=f"vflpcd sitl {name}", description=description)
    mock.add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=args.log_level.upper(), stream=sys.stderr, format=LOG_FORMAT)
    return exit_code_of(f"vflpcd sitl {name}", lambda: mock.run(args))


def cmd_collect(args) -> int:
    from sim.collect import main as collect_main

    return collect_main(args.args)


def cmd_bench_guidance(args) -> int:
    from sim.bench.guidance import bench_guidance
    from vflpcd.config.scenarios import load_scenario

    scenario = load_scenario(args.scenario, stop_at_goal=True)     # both planners' query ends at the goal
    if scenario.platform != "ground":
        raise ConfigError("command line", "--scenario", f"the planning comparison needs a ground scenario, "
                          f"{scenario.name!r} is {scenario.platform}")
    if args.repeat < 1 or args.astar_repeat < 1:
        raise ConfigError("command line", "--repeat", "expected at least one run")
    bench_guidance(scenario, args.out, args.repeat, args.astar_repeat, args.safe_distance)
    return 0


def cmd_bench_impc(args) -> int:
    from vflpcd.config.scenarios import load_scenario

    for option, name, platform in (("--scenario", args.scenario, "ground"), ("--aerial", args.aerial, "aerial")):
        found = load_scenario(name).platform
        if found != platform:
            raise ConfigError("command line", option, f"expected a {platform} scenario, {name!r} is {found}")
    import importlib.util

    missing = [m for m in ("casadi", "osqp") if importlib.util.find_spec(m) is None]
    if missing:
        print(f"vflpcd: error: the IMPC benchmark needs {' and '.join(missing)}: pip install -e '.[bench]'",
              file=sys.stderr)
        return 2
    from sim.bench.impc import bench_impc

    bench_impc(args.out, args.scenario, args.aerial)
    return 0


def cmd_bench_variants(args) -> int:
    if args.n < 1 or args.first_seed < 0:
        raise ConfigError("command line", "--n", "expected at least one variant and a seed >= 0")
    from sim.bench.variants import bench_variants

    bench_variants(args.out, args.n, args.first_seed)
    return 0


def cmd_bench_ml(args) -> int:
    if args.seeds < 1 or args.laps < 2:
        raise ConfigError("command line", "--seeds/--laps", "expected at least one seed and two laps (lap 2 is measured)")
    from sim.bench.ml import bench_ml

    bench_ml(args.out, args.seeds, args.laps)
    return 0


def cmd_bench_safety(args) -> int:
    from sim.bench.safety import CONTROLLERS, SCENES, bench_safety

    scenes = tuple(args.scene or SCENES)
    for name in scenes:
        if name not in SCENES:
            raise ConfigError("command line", "--scene", f"no such scene {name!r} (have: {', '.join(SCENES)})")
    controllers = tuple(args.controller or CONTROLLERS)
    for name in controllers:
        if name not in CONTROLLERS:
            raise ConfigError("command line", "--controller",
                              f"expected one of {', '.join(CONTROLLERS)} (ground controllers), got {name!r}")
    bench_safety(args.out, scenes, controllers)
    return 0


def _suite_only(only) -> tuple[str, ...] | None:
    """``--only``: suite scenes, each checked to exist (ConfigError naming it), duplicates dropped."""
    from sim.bench.suite import suite_names

    names = suite_names()
    for name in only or ():
        if name not in names:
            raise ConfigError("command line", "--only", f"no such suite scenario {name!r} (have: {', '.join(names)})")
    return tuple(dict.fromkeys(only)) if only else None


def _ground_controllers(controllers, option: str) -> list[str]:
    """Check that every name is a ground controller (ConfigError naming ``option`` otherwise);
    returns what the missing solvers are ("nmpc_rti needs casadi"), empty when none is."""
    import importlib.util

    from vflpcd.controllers import CONTROLLERS as KNOWN

    ground = [c for c, (_, platforms) in KNOWN.items() if "ground" in platforms]
    for name in controllers:
        if name not in ground:
            raise ConfigError("command line", option, f"expected ground controllers from {', '.join(ground)}, "
                                                      f"got {name!r}")
    solver = {"nmpc_cbf": "casadi", "nmpc_rti": "casadi", "koopman_mpc": "osqp"}
    return [f"{c} needs {solver[c]}" for c in controllers if c in solver and importlib.util.find_spec(solver[c]) is None]


def _missing(solvers: list[str]) -> int:
    print(f"vflpcd: error: {', '.join(solvers)}: pip install -e '.[bench]'", file=sys.stderr)
    return 2


def cmd_bench_jitter(args) -> int:
    if args.n < 1 or args.first_seed < 0:
        raise ConfigError("command line", "--n", "expected at least one copy and a seed >= 0")
    if not (math.isfinite(args.scale) and 0.0 <= args.scale <= 5.0):
        raise ConfigError("command line", "--scale", f"expected a scale from 0 to 5, got {args.scale}")
    only = _suite_only(args.only)
    missing = _ground_controllers([args.controller], "--controller")
    if missing:
        return _missing(missing)
    from sim.bench.jitter import bench_jitter

    bench_jitter(args.out, args.n, args.first_seed, args.scale, args.controller, only)
    return 0


def cmd_bench_suite(args) -> int:
    from sim.bench.suite import CONTROLLERS

    only = _suite_only(args.only)
    controllers = tuple(dict.fromkeys(c.strip() for c in args.controllers.split(","))) if args.controllers \
        else CONTROLLERS
    missing = _ground_controllers(controllers, "--controllers")
    if missing:
        return _missing(missing)
    from sim.bench.suite import bench_suite

    bench_suite(args.out, controllers, only)
    return 0


def cmd_bench_tick(args) -> int:
    from sim.bench.tick import bench_tick

    bench_tick(args.out)
    return 0


def cmd_bench_dynamics(args) -> int:
    from sim.bench.dynamics import bench_dynamics
    from vflpcd.config.koopman_file import load_koopman
    from vflpcd.base.paths import config_dir
    from vflpcd.controllers.loops import encoder_loop

    path = args.model or config_dir() / "models" / "dynamic_bicycle.npz"
    model = load_koopman(path, state_names=("X", "Y", "psi", "vx", "vy", "omega"), control_names=("a_x", "delta_f"))
    model.compile_encoder(encoder_loop())        # the lift as a controller runs it
    bench_dynamics(model, args.out, args.seed)
    return 0
