"""Record seeded random-excitation logs of a simulated plant for learning its dynamics.

``collect(plant_name, minutes, seed, out_dir)`` drives ``dynamic_bicycle`` or ``quadrotor``
with random commands inside the input limits (the processes and ranges are in
``config/collect.toml``), samples every ``dt`` = 0.05 s, splits the run into logs of
``log_seconds`` = 60 s and writes them with ``save_log`` as
``<out>/<plant>_<seed>_<k>.npz`` (k zero-padded to three digits, counted from 0).

Row k of a log holds the state x_k before the step and the control the plant actually
applied over [t_k, t_k + dt) (``applied_control``, after its limits), so x_{k+1} = f(x_k, u_k).

Excitation:

* bicycle: a_x = k_speed (v_target - vx) + OU noise, v_target drawn in [v_min, v_max] and
  held for a random time (the speed-holding term keeps the car in a useful speed range);
  delta_f an OU process, clipped to the plant's delta_max and to the steering angle that gives
  the lateral acceleration lat_accel_max at the current speed; heading unwrapped in the log;
* quadrotor: a = k_vel (v_ref - v) + OU noise per axis, v_ref = k_pos (p_target - p) shortened
  to speed_max, p_target drawn in the box and held for a random time; clipped to accel_limit.

The command line ``collect PLANT --minutes M [--seed S] [--out DIR]`` is :func:`main`.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vflpcd.core.angles import wrap_angle
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import Table, load_table
from vflpcd.training.datasets import Log, save_log

log = logging.getLogger("sim.collect")

PLANTS = ("dynamic_bicycle", "quadrotor")
QUAD_STATE_NAMES = ("X", "Y", "Z", "vx", "vy", "vz")

_BICYCLE_FIELDS = ("param_set", "v_start", "v_min", "v_max", "hold_min", "hold_max", "k_speed",
                   "accel_noise_std", "accel_noise_tau", "steer_std", "steer_tau", "lat_accel_max")
_QUAD_FIELDS = ("start", "box_min", "box_max", "hold_min", "hold_max", "speed_max", "k_pos", "k_vel",
                "accel_noise_std", "accel_noise_tau", "accel_limit")


@dataclass(frozen=True)
class CollectConfig:
    """``config/collect.toml``: dt (s), log_seconds (s) and one table per plant (raw Table)."""

    dt: float
    log_seconds: float
    bicycle: Table
    quadrotor: Table

    @classmethod
    def load(cls, path: str | Path | None = None) -> "CollectConfig":
        path = Path(path) if path is not None else config_dir() / "collect.toml"
        root = load_table(path)
        root.check_known({"common", *PLANTS})
        common = root.table("common")
        common.check_known({"dt", "log_seconds"})
        dt = common.number("dt", positive=True)
        log_seconds = common.number("log_seconds", positive=True)
        if log_seconds < 2 * dt:
            raise common.error("log_seconds", f"expected at least two samples (>= {2 * dt:g} s), got {log_seconds:g}")
        bic, quad = root.table("dynamic_bicycle"), root.table("quadrotor")
        bic.check_known(set(_BICYCLE_FIELDS))
        quad.check_known(set(_QUAD_FIELDS))
        return cls(dt, log_seconds, bic, quad)


class _OU:
    """Ornstein-Uhlenbeck process of stationary std sigma and correlation time tau, sampled every dt."""

    def __init__(self, rng: np.random.Generator, sigma: float, tau: float, dt: float, size: int = 1) -> None:
        self.rng, self.sigma, self.size = rng, sigma, size
        self.a = math.exp(-dt / tau)
        self.value = np.zeros(size)

    def step(self) -> np.ndarray:
        self.value = self.a * self.value + self.sigma * math.sqrt(1.0 - self.a ** 2) * self.rng.standard_normal(self.size)
        return self.value


def _hold_range(t: Table) -> tuple[float, float]:
    lo, hi = t.number("hold_min", positive=True), t.number("hold_max", positive=True)
    if hi < lo:
        raise t.error("hold_max", f"expected a time >= hold_min ({lo:g} s), got {hi:g}")
    return lo, hi


def _run_bicycle(cfg: CollectConfig, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    from sim.plants.dynamic_bicycle import DynamicBicycle
    from vflpcd.config.vehicles import BicycleConfig

    t = cfg.bicycle
    plant_cfg = BicycleConfig.load(t.string("param_set"))
    lim, p = plant_cfg.limits, plant_cfg.params
    v_min, v_max = t.number("v_min", positive=True), t.number("v_max", positive=True)
    if v_max <= v_min:
        raise t.error("v_max", f"expected a speed above v_min ({v_min:g} m/s), got {v_max:g}")
    hold_min, hold_max = _hold_range(t)
    k_speed, a_lat = t.number("k_speed", positive=True), t.number("lat_accel_max", positive=True)
    dt = cfg.dt
    accel_noise = _OU(rng, t.number("accel_noise_std", min=0.0), t.number("accel_noise_tau", positive=True), dt)
    steer = _OU(rng, t.number("steer_std", min=0.0), t.number("steer_tau", positive=True), dt)
    plant = DynamicBicycle(plant_cfg, [0.0, 0.0, 0.0, t.number("v_start", min=0.0)])
    states, controls = np.empty((n, 6)), np.empty((n, 2))
    v_target, hold_left = 0.0, 0.0
    psi = 0.0  # unwrapped heading
    for k in range(n):
        x = plant.state
        if k == 0:
            psi = x[2]
        else:
            psi += wrap_angle(x[2] - wrap_angle(psi))
        if hold_left <= 0.0:
            v_target = rng.uniform(v_min, v_max)
            hold_left = rng.uniform(hold_min, hold_max)
        hold_left -= dt
        vx = x[3]
        a_x = float(np.clip(k_speed * (v_target - vx) + accel_noise.step()[0], lim.a_min, lim.a_max))
        d_lim = min(lim.delta_max, math.atan(a_lat * p.wheelbase / max(vx, 1e-3) ** 2))
        delta = float(np.clip(steer.step()[0], -d_lim, d_lim))
        plant.step([a_x, delta], dt)
        states[k] = x
        states[k, 2] = psi
        controls[k] = plant.applied_control
    return states, controls, ("X", "Y", "psi", "vx", "vy", "omega"), DynamicBicycle.control_names


def _run_quadrotor(cfg: CollectConfig, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, tuple, tuple]:
    from sim.plants.quadrotor import Quadrotor
    from vflpcd.config.vehicles import QuadrotorParams

    t = cfg.quadrotor
    params = QuadrotorParams.from_toml()
    lo, hi = t.vector("box_min", 3), t.vector("box_max", 3)
    if np.any(hi <= lo):
        raise t.error("box_max", f"expected every coordinate above box_min {lo.tolist()}, got {hi.tolist()}")
    start = t.vector("start", 3)
    hold_min, hold_max = _hold_range(t)
    v_max, k_pos, k_vel = t.number("speed_max", positive=True), t.number("k_pos", positive=True), t.number("k_vel", positive=True)
    a_lim = t.number("accel_limit", positive=True)
    if a_lim > params.accel_max:
        raise t.error("accel_limit", f"expected at most the plant's accel_max {params.accel_max:g} m/s^2, got {a_lim:g}")
    dt = cfg.dt
    noise = _OU(rng, t.number("accel_noise_std", min=0.0), t.number("accel_noise_tau", positive=True), dt, size=3)
    plant = Quadrotor(params, np.concatenate([start, np.zeros(3)]))
    states, controls = np.empty((n, 6)), np.empty((n, 3))
    target, hold_left = start.copy(), 0.0
    for k in range(n):
        x = plant.state[:6]
        if hold_left <= 0.0:
            target = rng.uniform(lo, hi)
            hold_left = rng.uniform(hold_min, hold_max)
        hold_left -= dt
        v_ref = k_pos * (target - x[:3])
        sp = float(np.linalg.norm(v_ref))
        if sp > v_max:
            v_ref *= v_max / sp
        a = np.clip(k_vel * (v_ref - x[3:6]) + noise.step(), -a_lim, a_lim)
        plant.step(a, dt)
        states[k] = x
        controls[k] = plant.applied_control
    return states, controls, QUAD_STATE_NAMES, Quadrotor.control_names


def collect(plant_name: str, minutes: float, seed: int, out_dir: str | Path,
            config_path: str | Path | None = None) -> list[Path]:
    """Simulate ``minutes`` of seeded random excitation of ``plant_name`` and write it as logs of
    ``log_seconds`` each (the last one shorter if the time does not divide; dropped if under two
    samples). Returns the written paths in order. ValueError on an unknown plant or
    non-positive minutes; ConfigError on a bad configuration."""
    if plant_name not in PLANTS:
        raise ValueError(f"unknown plant {plant_name!r} (have: {', '.join(PLANTS)})")
    if not (math.isfinite(minutes) and minutes > 0.0):
        raise ValueError(f"minutes must be a positive number, got {minutes!r}")
    cfg = CollectConfig.load(config_path)
    n_total = int(round(minutes * 60.0 / cfg.dt))
    per_log = int(round(cfg.log_seconds / cfg.dt))
    if n_total < 2:
        raise ValueError(f"{minutes} min is less than two samples of {cfg.dt} s")
    rng = np.random.default_rng(seed)
    run = _run_bicycle if plant_name == "dynamic_bicycle" else _run_quadrotor
    log.info("collecting %g min of %s (seed %d, %d samples of %g s)", minutes, plant_name, seed, n_total, cfg.dt)
    states, controls, snames, cnames = run(cfg, n_total, rng)
    out = Path(out_dir)
    paths = []
    for k, a in enumerate(range(0, n_total, per_log)):
        b = min(a + per_log, n_total)
        if b - a < 2:
            break
        name = f"{plant_name}_{seed}_{k:03d}"
        lg = Log(name, states[a:b], controls[a:b], cfg.dt, snames, cnames)
        paths.append(save_log(lg, out / f"{name}.npz"))
    log.info("collected %d logs of %s in %s", len(paths), plant_name, out)
    return paths


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line on stderr, exit code 2
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def main(argv: list[str] | None = None) -> int:
    """``collect PLANT --minutes M [--seed S] [--out DIR] [--config FILE]``; returns the exit code
    (0 done, 2 bad arguments or configuration, with one line on stderr)."""
    parser = _Parser(prog="vflpcd collect", description="record seeded random-excitation logs of a simulated plant")
    parser.add_argument("plant", help=f"plant to drive: {', '.join(PLANTS)}")
    parser.add_argument("--minutes", type=float, required=True, help="simulated time, min (> 0)")
    parser.add_argument("--seed", type=int, default=0, help="seed of every random source (default 0)")
    parser.add_argument("--out", type=Path, default=Path("results/collect"),
                        help="output folder (default results/collect)")
    parser.add_argument("--config", type=Path, default=None, help="excitation file (default config/collect.toml)")
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    if args.plant not in PLANTS:
        print(f"vflpcd collect: error: unknown plant {args.plant!r} (have: {', '.join(PLANTS)})", file=sys.stderr)
        return 2
    if not (math.isfinite(args.minutes) and args.minutes > 0.0):
        print(f"vflpcd collect: error: --minutes must be positive, got {args.minutes:g}", file=sys.stderr)
        return 2
    try:
        paths = collect(args.plant, args.minutes, args.seed, args.out, args.config)
    except (ConfigError, ValueError) as exc:
        print(f"vflpcd collect: error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(paths)} logs ({args.minutes:g} min of {args.plant}, seed {args.seed}) to {args.out}")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    sys.exit(main())
