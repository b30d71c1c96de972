"""Physics checks of the simulated quadrotor (sim/plants/quadrotor.py) with config/plants/quadrotor.toml."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from sim.plants.quadrotor import Quadrotor

from vflpcd.config.vehicles import QuadrotorParams
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir

DT = 0.02          # control step, s
HOVER = np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def params() -> QuadrotorParams:
    return QuadrotorParams.from_toml()


def simulate(plant: Quadrotor, u, duration: float, dt: float = DT) -> dict[str, np.ndarray]:
    """Hold u for duration; per control step: t, v (after the step), tilt, applied, thrust."""
    n = round(duration / dt)
    out = {"t": np.arange(1, n + 1) * dt, "v": [], "tilt": [], "applied": [], "thrust": [], "b3": []}
    v0 = plant.velocity_world()
    for _ in range(n):
        plant.step(np.asarray(u, dtype=float), dt)
        out["v"].append(plant.velocity_world())
        out["tilt"].append(plant.tilt())
        out["applied"].append(plant.applied_control)
        out["thrust"].append(plant.actuators[0])
        out["b3"].append(plant.rotation()[:, 2])
    res = {k: np.asarray(v) for k, v in out.items()}
    # world acceleration over each control step by finite difference of velocity
    res["acc"] = np.diff(np.vstack([v0, res["v"]]), axis=0) / dt
    return res


# ---------------------------------------------------------------------- configuration
def test_config_file_is_read(params):
    assert params.mass == 1.5 and params.gravity == 9.81
    assert params.inertia == (0.029, 0.029, 0.055)
    assert params.thrust_max == pytest.approx(2.0 * 1.5 * 9.81)
    assert 0.0 < params.thrust_min < params.mass * params.gravity
    # the roll/pitch loop: wn = sqrt(k_R / J) in 15..25 rad/s, zeta = k_Omega / (2 sqrt(k_R J)) in 0.8..1
    for i in (0, 1):
        wn = math.sqrt(params.k_R[i] / params.inertia[i])
        zeta = params.k_Omega[i] / (2.0 * math.sqrt(params.k_R[i] * params.inertia[i]))
        assert 15.0 <= wn <= 25.0 and 0.8 <= zeta <= 1.0


# ---------------------------------------------------------------------- hover and attitude loop
def test_hover_holds_position_and_level_attitude(params):
    plant = Quadrotor(params, HOVER)
    r = simulate(plant, [0.0, 0.0, 0.0], 10.0)
    assert np.max(np.abs(plant.position() - HOVER[:3])) < 0.01
    assert np.max(np.abs(r["v"])) < 1e-3
    assert np.max(r["tilt"]) < 1e-6
    assert np.allclose(r["thrust"], params.mass * params.gravity, rtol=1e-9)   # T = m g
    assert np.allclose(r["applied"], 0.0, atol=1e-12)
    roll, pitch, yaw = plant.euler()
    assert abs(roll) < 1e-6 and abs(pitch) < 1e-6 and abs(yaw) < 1e-6


def test_attitude_loop_levels_a_tilted_vehicle_quickly_and_without_overshoot(params):
    # without drag: with it the vehicle would end up tilted against the drag of the drift
    # velocity picked up while tilted (that steady tilt is tested below)
    params = dataclasses.replace(params, drag_coefficient=0.0)
    roll0 = 0.1
    x0 = np.zeros(13)
    x0[2] = 2.0
    x0[6:10] = [math.cos(roll0 / 2), math.sin(roll0 / 2), 0.0, 0.0]
    plant = Quadrotor(params, x0)
    rolls = []
    for _ in range(round(1.0 / 0.002)):
        plant.step(np.zeros(3), 0.002)
        rolls.append(plant.euler()[0])
    rolls = np.asarray(rolls)
    # wn = 20 rad/s, zeta = 0.9: ~2 % left after 0.25 s, overshoot ~0.15 %
    assert abs(rolls[round(0.25 / 0.002) - 1]) < 0.03 * roll0
    assert np.min(rolls) > -0.005 * roll0
    assert abs(rolls[-1]) < 1e-4
    assert abs(plant.yaw_setpoint - plant.heading()) < 1e-4


def test_drag_is_compensated_so_zero_command_holds_velocity(params):
    v0 = 2.0
    plant = Quadrotor(params, np.array([0.0, 0.0, 2.0, v0, 0.0, 0.0]))
    r = simulate(plant, [0.0, 0.0, 0.0], 5.0)
    # it starts level, so drag slows it until the attitude loop has tilted (~0.1 s); then it holds
    assert abs(plant.velocity_world()[0] - v0) < 0.02
    assert np.max(np.abs(r["v"][r["t"] > 0.5, 0] - plant.velocity_world()[0])) < 1e-3
    # steady tilt balances drag: tan(theta) = c_d v / (m g)
    expected = math.atan(params.drag_coefficient * v0 / (params.mass * params.gravity))
    assert r["tilt"][-1] == pytest.approx(expected, rel=0.01)


# ---------------------------------------------------------------------- acceleration tracking
@pytest.mark.parametrize("drag", [None, 0.0], ids=["config-drag", "no-drag"])
@pytest.mark.parametrize("axis", [0, 1, 2], ids=["x", "y", "z"])
def test_acceleration_step_is_tracked(params, axis, drag):
    if drag is not None:
        params = dataclasses.replace(params, drag_coefficient=drag)
    m, g, cd = params.mass, params.gravity, params.drag_coefficient
    u = np.zeros(3)
    u[axis] = 1.0
    plant = Quadrotor(params, HOVER)
    r = simulate(plant, u, 3.0)
    late = r["t"] > 0.5 + 1e-9
    acc = r["acc"][late]
    assert np.all(np.abs(acc[:, axis] - 1.0) < 0.05)
    others = [i for i in range(3) if i != axis]
    assert np.all(np.abs(acc[:, others]) < 0.05)
    assert np.allclose(r["applied"], u, atol=1e-9)        # no limit binds
    if axis < 2:
        # the thrust carries m a plus the drag feed-forward horizontally and m g vertically,
        # so tan(tilt) = (m * 1 + c_d v) / (m g); atan(1 / g) when c_d = 0
        expected = np.arctan((m * 1.0 + cd * r["v"][late, axis]) / (m * g))
        assert np.all(np.abs(r["tilt"][late] / expected - 1.0) < 0.05)
        if cd == 0.0:
            assert np.all(np.abs(r["tilt"][late] / math.atan(1.0 / g) - 1.0) < 0.05)
        # the body z axis leans towards the commanded direction
        assert np.all(r["b3"][late, axis] > 0.09)
    else:
        assert np.max(r["tilt"]) < 1e-9
        assert np.allclose(r["thrust"][late], m * (g + 1.0) + cd * r["v"][late, 2], rtol=1e-3)
    # v = a t, less the attitude loop's lag for x/y: a second-order loop tracks a step with
    # an integrated error of 2 zeta / wn; thrust along z acts at once
    if axis < 2:
        wn = math.sqrt(params.k_R[axis] / params.inertia[axis])
        zeta = params.k_Omega[axis] / (2.0 * math.sqrt(params.k_R[axis] * params.inertia[axis]))
        expected_v = 1.0 * (3.0 - 2.0 * zeta / wn)
    else:
        expected_v = 3.0
    assert plant.velocity_world()[axis] == pytest.approx(expected_v, abs=0.03)


# ---------------------------------------------------------------------- limits
def test_large_x_command_is_clipped_and_tilt_stays_within_limit(params):
    plant = Quadrotor(params, HOVER)
    r = simulate(plant, [20.0, 0.0, 0.0], 3.0)
    assert np.max(r["tilt"]) <= params.tilt_max + 0.005
    assert np.all(np.abs(r["applied"]) <= params.accel_max + 1e-9)
    assert r["applied"][0, 0] == pytest.approx(params.accel_max)      # clipped to accel_max at first
    # later the drag feed-forward pushes against tilt_max, which then binds:
    # applied_x = (F_z tan(tilt_max) - c_d v_x) / m with F_z = m g + c_d v_z
    m, g, cd = params.mass, params.gravity, params.drag_coefficient
    v = r["v"][-1]
    expected_ax = ((m * g + cd * v[2]) * math.tan(params.tilt_max) - cd * v[0]) / m
    assert r["applied"][-1, 0] == pytest.approx(expected_ax, abs=0.01)
    assert r["tilt"][-1] == pytest.approx(params.tilt_max, abs=0.005)
    # the vehicle realises what applied_control reports
    late = r["t"] > 0.5
    assert np.all(np.abs(r["acc"][late, 0] - r["applied"][late, 0]) < 0.1)
    assert np.all(np.abs(r["acc"][late, 1:]) < 0.05)


def test_diagonal_command_hits_tilt_limit_keeping_direction(params):
    plant = Quadrotor(params, HOVER)
    r = simulate(plant, [20.0, 20.0, 0.0], 2.0)
    assert np.max(r["tilt"]) <= params.tilt_max + 0.005
    late = r["t"] > 0.5
    assert np.all(np.abs(r["tilt"][late] - params.tilt_max) < 0.005)
    a = r["applied"]
    assert np.all(np.abs(a) <= params.accel_max + 1e-9)
    assert a[0, 0] == pytest.approx(a[0, 1], abs=1e-8)               # 45 degrees kept
    assert np.allclose(a[:, 0], a[:, 1], atol=2e-3)                   # (drag of v_x, v_y differs slightly)
    assert np.allclose(a[:, 2], 0.0, atol=1e-9)                      # altitude has priority
    # at the start (v = 0) the horizontal demand m * 6 * sqrt(2) exceeds m g tan(tilt_max)
    assert np.hypot(a[0, 0], a[0, 1]) == pytest.approx(params.gravity * math.tan(params.tilt_max), rel=1e-3)
    assert np.all(np.abs(r["acc"][late, 2]) < 0.05)


def test_large_descent_command_never_reverses_thrust_or_beats_free_fall(params):
    plant = Quadrotor(params, HOVER)
    r = simulate(plant, [0.0, 0.0, -20.0], 2.0)
    assert np.all(r["thrust"] >= params.thrust_min - 1e-12)
    assert np.all(r["thrust"] > 0.0)
    assert np.all(r["v"][:, 2] >= -params.gravity * r["t"] - 1e-9)    # no faster than free fall
    assert np.allclose(r["applied"][:, 2], -params.accel_max)
    assert np.all(np.abs(r["acc"][:, 2] + params.accel_max) < 0.05)


def test_descent_below_minus_g_is_held_at_minimum_thrust(params):
    p = dataclasses.replace(params, accel_max=20.0)
    plant = Quadrotor(p, HOVER)
    r = simulate(plant, [0.0, 0.0, -20.0], 2.0)
    assert np.allclose(r["thrust"], p.thrust_min)
    m, g, cd = p.mass, p.gravity, p.drag_coefficient
    vz = r["v"][:, 2]
    # falls with thrust_min: a_z = T_min / m - g - c_d v_z / m, slower than free fall
    assert np.all(np.abs(r["acc"][1:, 2] - (p.thrust_min / m - g - cd * vz[1:] / m)) < 0.02)
    assert np.all(vz >= -g * r["t"])
    assert np.allclose(r["applied"][:, 2], r["acc"][:, 2], atol=0.02)
    assert np.all(r["applied"][:, 2] > -20.0)


# ---------------------------------------------------------------------- yaw
def test_yaw_setpoint_is_reached_and_held(params):
    plant = Quadrotor(params, HOVER)
    plant.set_yaw_setpoint(0.5)
    simulate(plant, [0.0, 0.0, 0.0], 2.0)
    assert abs(plant.heading() - 0.5) < 0.01
    r = simulate(plant, [0.0, 0.0, 0.0], 3.0)
    assert abs(plant.heading() - 0.5) < 1e-4
    assert np.max(np.abs(plant.position() - HOVER[:3])) < 0.01       # yawing does not move it
    assert np.max(r["tilt"]) < 1e-3


def test_reset_yaw_is_held_while_accelerating_in_world_frame(params):
    yaw0 = 2.0
    plant = Quadrotor(params, np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0, yaw0]))
    assert plant.yaw_setpoint == pytest.approx(yaw0)
    r = simulate(plant, [1.0, 0.0, 0.0], 3.0)
    late = r["t"] > 0.5
    assert np.all(np.abs(r["acc"][late, 0] - 1.0) < 0.05)            # world x, whatever the yaw
    assert np.all(np.abs(r["acc"][late, 1:]) < 0.05)
    assert plant.heading() == pytest.approx(yaw0, abs=1e-3)


def test_heading_is_wrapped(params):
    plant = Quadrotor(params, np.array([0.0, 0.0, 2.0, 0.0, 0.0, 0.0, 3.5]))
    assert plant.heading() == pytest.approx(3.5 - 2.0 * math.pi)
    plant.set_yaw_setpoint(-4.0)
    assert plant.yaw_setpoint == pytest.approx(-4.0 + 2.0 * math.pi)


# ---------------------------------------------------------------------- state handling
def test_reset_shapes_and_state_copy(params):
    plant = Quadrotor(params)
    assert plant.state.shape == (13,) and len(plant.state_names) == 13
    assert plant.control_names == ("ax", "ay", "az")
    assert np.allclose(plant.state[6:10], [1.0, 0.0, 0.0, 0.0])
    s = plant.state
    s[:] = 99.0
    assert np.all(plant.state[:3] == 0.0)
    x0 = np.zeros(13)
    x0[6:10] = [2.0, 0.0, 0.0, 0.0]
    x0[10:13] = [0.1, -0.2, 0.3]
    plant.reset(x0)
    assert np.allclose(plant.state[6:10], [1.0, 0.0, 0.0, 0.0])       # renormalised
    assert np.allclose(plant.state[10:13], [0.1, -0.2, 0.3])
    assert plant.position().shape == (3,) and plant.velocity_world().shape == (3,)


def test_quaternion_stays_unit_norm_over_long_aggressive_flight(params):
    rng = np.random.default_rng(7)
    plant = Quadrotor(params, HOVER, seed=1)
    for k in range(3000):                                              # 60 s
        if k % 50 == 0:
            u = rng.uniform(-8.0, 8.0, size=3)
            plant.set_yaw_setpoint(rng.uniform(-math.pi, math.pi))
        x = plant.step(u, DT)
        assert abs(np.linalg.norm(x[6:10]) - 1.0) < 1e-12
    assert np.all(np.isfinite(plant.state))
    assert plant.tilt() <= params.tilt_max + 0.05


# ---------------------------------------------------------------------- bad inputs
@pytest.mark.parametrize("u", [[np.nan, 0.0, 0.0], [0.0, np.inf, 0.0], [0.0, 0.0, -np.inf], [1.0, 2.0]])
def test_bad_command_is_rejected(params, u):
    plant = Quadrotor(params, HOVER)
    before = plant.state
    with pytest.raises(ValueError):
        plant.step(np.asarray(u), DT)
    assert np.array_equal(plant.state, before)


@pytest.mark.parametrize("x0", [np.zeros(5), np.zeros(12), np.zeros((2, 6)), np.array([0, 0, np.nan, 0, 0, 0.0]),
                                np.zeros(13)])
def test_bad_initial_state_is_rejected(params, x0):
    # np.zeros(13) has a zero quaternion
    with pytest.raises(ValueError):
        Quadrotor(params, x0)


def test_bad_dt_and_yaw_setpoint_are_rejected(params):
    plant = Quadrotor(params, HOVER)
    with pytest.raises(ValueError):
        plant.step(np.zeros(3), 0.0)
    with pytest.raises(ValueError):
        plant.set_yaw_setpoint(float("nan"))


def _write_params(tmp_path: Path, replace: dict[str, str | None] | None = None, extra: str = "") -> Path:
    """Copy the shipped file with some `key = value` lines replaced (None removes the line)."""
    lines = []
    for line in (config_dir() / "plants" / "quadrotor.toml").read_text().splitlines():
        key = line.split("=", 1)[0].strip() if "=" in line and not line.startswith("#") else None
        if replace and key in replace:
            if replace[key] is not None:
                lines.append(f"{key} = {replace[key]}")
            continue
        lines.append(line)
    path = tmp_path / "quadrotor.toml"
    path.write_text("\n".join(lines) + "\n" + extra)
    return path


def test_copied_params_file_reads_like_the_shipped_one(tmp_path, params):
    assert QuadrotorParams.from_toml(_write_params(tmp_path)) == params


@pytest.mark.parametrize("replace, extra, field", [
    ({"mass": None}, "", "mass"),
    ({"mass": "-1.5"}, "", "mass"),
    ({"gravity": "0"}, "", "gravity"),
    ({"inertia": "[0.029, 0.029]"}, "", "inertia"),
    ({"inertia": "[0.029, -0.029, 0.055]"}, "", "inertia"),
    ({"k_R": "[11.6, 0.0, 1.98]"}, "", "k_R"),
    ({"tilt_max": "1.6"}, "", "tilt_max"),
    ({"thrust_to_weight": "0.9"}, "", "thrust_to_weight"),
    ({"thrust_min_fraction": "1.0"}, "", "thrust_min_fraction"),
    ({"drag_coefficient": "-0.1"}, "", "drag_coefficient"),
    ({"max_step": "\"fast\""}, "", "max_step"),
    ({}, "masss = 1.5\n", "masss"),
])
def test_bad_params_file_names_the_field(tmp_path, replace, extra, field):
    path = _write_params(tmp_path, replace, extra)
    with pytest.raises(ConfigError) as err:
        QuadrotorParams.from_toml(path)
    assert err.value.field == f"quadrotor.{field}"
    assert field in str(err.value) and str(path) in str(err.value)


def test_missing_params_file_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="file not found"):
        QuadrotorParams.from_toml(tmp_path / "nope.toml")
