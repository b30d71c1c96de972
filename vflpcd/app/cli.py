"""The ``vflpcd`` command line: the composition root of the application."""

from __future__ import annotations

import argparse
import importlib
import logging
import sys
from dataclasses import replace
from pathlib import Path

from vflpcd.base.errors import LOG_FORMAT, ConfigError, exit_code_of

log = logging.getLogger("vflpcd")


def _simulator(command: str):
    """A command of the simulator package (``sim.commands``), imported only when it runs: the
    production path (run, check, plot, watch) never imports ``sim``."""
    def run(*args):
        return getattr(importlib.import_module("sim.commands"), command)(*args)
    return run


SITL_MOCKS = {"quad": "a PX4-like quadrotor autopilot over MAVLink/UDP",
              "can-ecu": "a drive-by-wire vehicle ECU on a CAN bus (config/can/vehicle.dbc)"}


def _out(bench_parser: argparse.ArgumentParser) -> None:
    """A bench's ``--out``: where its JSON and PNG go."""
    bench_parser.add_argument("--out", type=Path, default=Path("results/bench"),
                              help="output folder (default results/bench)")


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="vflpcd", description="Vector Field-guided Learning Predictive Control")
    parser.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("sim", help="run a scenario in closed loop, offline, as fast as possible")
    p.add_argument("scenario", help="scenario name (config/scenarios/NAME.toml) or path to a TOML file")
    p.add_argument("--controller", default=None,
                   help="controller name (default: pure_pursuit on the ground, pd_tracker in the air)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random source (default 0)")
    p.add_argument("--out", type=Path, default=None,
                   help="output folder for results.json and plot.png (default results/SCENARIO-CONTROLLER-sSEED)")
    p.add_argument("--no-plot", action="store_true", help="skip the PNG")
    p.add_argument("--no-supervisor", action="store_true",
                   help="run without the safety supervisor and monitors (for comparison only)")
    p.set_defaults(func=_simulator("cmd_sim"))

    p = sub.add_parser("collect", add_help=False, help="record seeded random-excitation logs of a simulated plant "
                                                        "(vflpcd collect --help)")
    p.add_argument("args", nargs=argparse.REMAINDER)
    p.set_defaults(func=_simulator("cmd_collect"))

    p = sub.add_parser("train", help="offline training (needs the train extra: torch)")
    train = p.add_subparsers(dest="target", required=True)
    t = train.add_parser("koopman", add_help=False, help="deep Koopman model (vflpcd train koopman --help)")
    t.add_argument("args", nargs=argparse.REMAINDER)
    t.set_defaults(func=cmd_train_koopman)

    p = sub.add_parser("bench", help="benchmarks that measure and print a table (JSON and PNG beside it)")
    bench = p.add_subparsers(dest="target", required=True)
    b = bench.add_parser("guidance", help="guidance planning against Hybrid A* (the paper's planning table)")
    b.add_argument("--scenario", default="dense_static", help="ground scenario (default dense_static)")
    b.add_argument("--repeat", type=int, default=20, help="guidance planning runs (default 20)")
    b.add_argument("--astar-repeat", type=int, default=3, help="Hybrid A* runs (default 3)")
    b.add_argument("--safe-distance", type=float, default=0.0,
                   help="least body clearance that counts as a safe distance, m (default 0)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_guidance"))

    b = bench.add_parser("dynamics", help="learned-model costs and online GP compensation on racing_track")
    b.add_argument("--model", type=Path, default=None,
                   help="vehicle model artifact (default config/models/dynamic_bicycle.npz)")
    b.add_argument("--seed", type=int, default=0, help="seed of the plant's process noise (default 0)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_dynamics"))

    b = bench.add_parser("impc", help="VF-LPC against NMPC (MPC-CBF), Koopman-MPC and pure pursuit "
                                      "(the paper's IMPC table), w/ and w/o ML, and on uav_3d")
    b.add_argument("--scenario", default="carsim_avoidance", help="ground scenario (default carsim_avoidance)")
    b.add_argument("--aerial", default="uav_3d", help="aerial scenario of table 3 (default uav_3d)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_impc"))

    b = bench.add_parser("variants", help="VF-LPC on seeded road variants with moving obstacles (collisions)")
    b.add_argument("--n", type=int, default=50, help="number of variants (default 50)")
    b.add_argument("--first-seed", type=int, default=0, help="seed of the first variant (default 0)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_variants"))

    b = bench.add_parser("ml", help="the paper's model-uncertainty test: racing_track on the exact vehicle with "
                                    "process noise, VF-LPC w/o and w/ the online GP (lap-2 RMS lateral, J_MC, jerk)")
    b.add_argument("--seeds", type=int, default=5, help="seeds of the process noise (default 5)")
    b.add_argument("--laps", type=int, default=2, help="laps per run, at least 2 (default 2)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_ml"))

    b = bench.add_parser("safety", help="every controller behind the safety supervisor on scenes with no or only "
                                        "a tight safe path, with and without it (collisions, stops, impact speeds)")
    b.add_argument("--scene", action="append", default=None,
                   help="a scene of config/scenarios/safety/ (repeatable; default all)")
    b.add_argument("--controller", action="append", default=None,
                   help="a controller (repeatable; default vflpc, nmpc_cbf, koopman_mpc, pure_pursuit)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_safety"))

    b = bench.add_parser("suite", help="every ground controller on the road scenes of config/scenarios/suite/ "
                                       "(outcome, collisions, clearance, J_MC, lateral error, jerk, t_cal; totals)")
    b.add_argument("--only", nargs="+", action="extend", default=None, metavar="NAME",
                   help="scenes of config/scenarios/suite/ to run (default all)")
    b.add_argument("--controllers", default=None, metavar="A,B,...",
                   help="comma-separated ground controllers (default vflpc,nmpc_cbf,nmpc_rti,koopman_mpc,pure_pursuit)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_suite"))

    b = bench.add_parser("jitter", help="a ground controller on jittered copies of the road suite's scenes "
                                        "(obstacles and speeds moved; outcome, collisions, clearance)")
    b.add_argument("--n", type=int, default=3, help="copies of each scene (default 3)")
    b.add_argument("--first-seed", type=int, default=0, help="seed of the first copy (default 0)")
    b.add_argument("--scale", type=float, default=1.0,
                   help="jitter scale: obstacles up to 2 m along and 0.4 m across the route, movers 3 m / 0.3 m "
                        "and 20 %% of their speed, the speeds 15 %%, times this (default 1)")
    b.add_argument("--controller", default="vflpc", help="a ground controller (default vflpc)")
    b.add_argument("--only", nargs="+", action="extend", default=None, metavar="NAME",
                   help="scenes of config/scenarios/suite/ to jitter (default all)")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_jitter"))

    b = bench.add_parser("tick", help="where a VF-LPC tick spends its time (phases in us, vehicle and quadrotor) "
                                      "how ticks and replans scale with static and moving obstacles, and the "
                                      "tick paced at 100 Hz against back to back")
    _out(b)
    b.set_defaults(func=_simulator("cmd_bench_tick"))

    p = sub.add_parser("run", help="run a mission: the daemon (fixed-rate VF-LPC loop, workers, telemetry, log)")
    p.add_argument("mission", type=Path, help="mission file (config/missions/*.toml)")
    p.add_argument("--log-dir", type=Path, default=None, help="flight-log folder (default: the mission's log.dir)")
    p.add_argument("--plot", action="store_true", help="also render the flight log to PNG at the end")
    p.add_argument("--drill", default=None, metavar="KIND@SECONDS",
                   help="inject a fault at a mission time to exercise the failsafe (stall, error, overrun, nan, "
                        "veer, freeze, nan_state, link, stuck)")
    p.add_argument("--with-sitl", action="store_true",
                   help="start the platform's mock first (can: the CAN hub and vflpcd sitl can-ecu; "
                        "mavlink: vflpcd sitl quad) and stop it at the end")
    p.set_defaults(func=cmd_run)

    p = sub.add_parser("compile", help="compile the controllers' loops into numba's on-disk cache (at installation)")
    p.set_defaults(func=cmd_compile)

    p = sub.add_parser("check", help="validate a mission file without running it")
    p.add_argument("mission", type=Path)
    p.set_defaults(func=cmd_check)

    p = sub.add_parser("plot", help="render a flight log (MCAP) to PNG")
    p.add_argument("log", type=Path)
    p.add_argument("--out", type=Path, default=None, help="PNG path (default: beside the log)")
    p.set_defaults(func=cmd_plot)

    p = sub.add_parser("watch", help="live table of a running daemon's telemetry (Zenoh)")
    p.add_argument("vehicle_id")
    p.add_argument("--connect", action="append", default=[], metavar="ENDPOINT",
                   help="Zenoh endpoint to connect to, e.g. tcp/127.0.0.1:7447 (repeatable)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT", help="Zenoh endpoint to listen on")
    p.add_argument("--duration", type=float, default=None, help="seconds to watch (default: until Ctrl-C)")
    p.add_argument("--identity", type=Path, default=None, metavar="FILE",
                   help="TLS identity file (TOML: ca, certificate, private_key, optional daemon; docs/security.md)")
    p.set_defaults(func=cmd_watch)

    p = sub.add_parser("security", help="security tools (docs/security.md)")
    security = p.add_subparsers(dest="target", required=True)
    t = security.add_parser("make-test-ca", help="a test CA and certificates for a bench set-up (bench set-ups only: "
                                                 "unprotected keys)")
    t.add_argument("dir", type=Path, help="folder to write to (created; must not hold the files already)")
    t.add_argument("--daemon-name", default="vflpcd",
                   help="common name of the daemon's certificate, e.g. the vehicle id (default vflpcd)")
    t.add_argument("--host", action="append", default=None, metavar="HOST",
                   help="host name or IP address the daemon is reached at (repeatable; default localhost, 127.0.0.1)")
    t.add_argument("--days", type=int, default=30, help="validity in days (default 30)")
    t.set_defaults(func=cmd_make_test_ca)

    b = bench.add_parser("loop", help="the daemon's loop timing at a fixed rate with telemetry, replans and GP refits")
    b.add_argument("--mission", type=Path, default=None,
                   help="mission (default config/missions/bench_loop.toml: racing_track, VF-LPC with the GP)")
    b.add_argument("--rate", type=float, default=100.0, help="loop rate, Hz (default 100)")
    b.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    b.add_argument("--executor", choices=("process", "thread"), default=None,
                   help="worker executor (default: the mission's)")
    b.add_argument("--baseline", type=float, default=None, metavar="SECONDS",
                   help="seconds of the empty loop run first, the machine's own lateness "
                        "(default: --duration; 0: none)")
    _out(b)
    b.set_defaults(func=cmd_bench_loop)

    p = sub.add_parser("sitl", help="software-in-the-loop mocks of the real platforms")
    sitl = p.add_subparsers(dest="target", required=True)
    for name, help_text in SITL_MOCKS.items():
        t = sitl.add_parser(name, add_help=False, help=f"{help_text} (vflpcd sitl {name} --help)")
        t.add_argument("args", nargs=argparse.REMAINDER)

    p = sub.add_parser("scenarios", help="list the scenarios in config/scenarios")
    p.set_defaults(func=cmd_scenarios)

    argv = sys.argv[1:] if argv is None else list(argv)
    if argv[:1] == ["collect"]:  # commands with parsers of their own get the rest of the line as it is
        return _simulator("cmd_collect")(argparse.Namespace(args=argv[1:]))
    if argv[:2] == ["train", "koopman"]:
        return cmd_train_koopman(argparse.Namespace(args=argv[2:]))
    if argv[:1] == ["sitl"] and argv[1:2] and argv[1] in SITL_MOCKS:
        return _simulator("cmd_sitl")(argv[1], argv[2:], SITL_MOCKS[argv[1]])
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.DEBUG if args.verbose else logging.INFO, stream=sys.stderr, format=LOG_FORMAT)
    return exit_code_of("vflpcd", lambda: args.func(args))


def cmd_train_koopman(args) -> int:
    try:
        from vflpcd.training.train_koopman import main as train_main
    except ModuleNotFoundError as exc:
        if exc.name != "torch":
            raise
        print("vflpcd: error: training needs torch: pip install -e '.[train]' (pins the CPU build torch==2.13.0)",
              file=sys.stderr)
        return 2
    return train_main(args.args)


def cmd_run(args) -> int:
    from vflpcd.app.drill import Drill
    from vflpcd.log.reader import read_flight_log
    from vflpcd.config.mission import load_mission
    from vflpcd.app.run import run_mission
    from vflpcd.daemon.service import EXIT_COLLISION
    from vflpcd.log.summary import clearances, summary_lines, touched_obstacles

    drill = Drill.parse(args.drill) if args.drill else None
    mission = load_mission(args.mission)
    if args.with_sitl:
        from vflpcd.app.sitl_launch import SitlProcesses

        try:
            with SitlProcesses(mission, args.log_dir or mission.log_dir):
                result = run_mission(mission, drill=drill, log_dir=args.log_dir)
        except OSError as exc:
            print(f"vflpcd: error: {exc}", file=sys.stderr)
            return 1
    else:
        result = run_mission(mission, drill=drill, log_dir=args.log_dir)
    if result.log_path is not None and result.log_path.exists():
        log = read_flight_log(result.log_path)
        touched = touched_obstacles(clearances(log, mission.scenario))
        if touched and result.outcome.code != EXIT_COLLISION:     # contact is never a success
            result.outcome = replace(result.outcome, code=EXIT_COLLISION,
                                     reason=f"collision: touched {', '.join(touched)} ({result.outcome.reason})")
        print("\n".join(summary_lines(log, mission.scenario, result.outcome, result.log_stop)))
        if args.plot:
            from vflpcd.log.plot import plot_flight_log

            print(f"wrote {plot_flight_log(log, result.log_path.with_suffix('.png'))}")
    else:
        print(f"outcome: {result.outcome.reason} (exit code {result.outcome.code})")
    return result.outcome.code


def cmd_compile(args) -> int:
    """Compile the loops (``vflpcd.controllers.loops.compile_all``) and say which run interpreted."""
    from vflpcd.controllers.loops import compile_all

    for name, compiled in compile_all().items():
        print(f"{name}: {'compiled' if compiled else 'interpreted (numba is not installed)'}")
    return 0


def cmd_check(args) -> int:
    from vflpcd.config.mission import build_controller, load_mission

    mission = load_mission(args.mission)
    from vflpcd.app.run import build_platform

    controller = build_controller(mission)
    platform = build_platform(mission)
    for warning in platform.link_warnings():
        print(f"{mission.file}: warning: {warning}", file=sys.stderr)
    print(f"{mission.file}: ok: vehicle {mission.vehicle_id}, {mission.platform.kind} platform, route "
          f"{mission.scenario.name} ({mission.scenario.platform}), controller {controller.name} at "
          f"{mission.loop.rate_hz:g} Hz, {mission.workers.executor} workers, telemetry "
          f"{'on' if mission.telemetry.enabled else 'off'}, log in {mission.log_dir}")
    return 0


def cmd_plot(args) -> int:
    from vflpcd.log.plot import main as plot_main

    plot_main(args.log, args.out)
    return 0


def cmd_watch(args) -> int:
    from vflpcd.app.watch import watch

    return watch(args.vehicle_id, connect=tuple(args.connect), listen=tuple(args.listen), duration_s=args.duration,
                 identity=args.identity)


def cmd_make_test_ca(args) -> int:
    from vflpcd.app.testca import DEFAULT_HOSTS, make_test_ca, mission_snippet

    hosts = tuple(args.host or DEFAULT_HOSTS)
    folder = make_test_ca(args.dir, daemon_name=args.daemon_name, hosts=hosts, days=args.days)
    print(f"wrote a test CA and certificates to {folder} (for bench set-ups only: the keys are not protected)")
    print(mission_snippet(folder, args.daemon_name, hosts))
    return 0


def cmd_bench_loop(args) -> int:
    if not (1.0 <= args.rate <= 200.0) or args.duration <= 0:
        raise ConfigError("command line", "--rate", "expected a rate in [1, 200] Hz and a positive duration")
    if args.baseline is not None and not (args.baseline == 0.0 or 1.0 <= args.baseline <= 600.0):
        raise ConfigError("command line", "--baseline",
                          f"expected 0 (none) or 1 to 600 seconds, got {args.baseline:g}")
    from vflpcd.app.benchloop import bench_loop

    return bench_loop(args.mission, args.rate, args.duration, args.executor, args.out, args.baseline)


def cmd_scenarios(args) -> int:
    from vflpcd.config.scenarios import available_scenarios, load_scenario

    for name in available_scenarios():
        s = load_scenario(name)
        print(f"{name:18s} {s.platform:6s} {s.path.length:7.1f} m  {len(s.obstacles):2d} obstacles  {s.description}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
