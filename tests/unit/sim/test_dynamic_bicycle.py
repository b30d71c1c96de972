import numpy as np
import pytest

from sim.plants.dynamic_bicycle import DynamicBicycle, bicycle_derivative

from vflpcd.config.vehicles import BicycleConfig
from vflpcd.base.errors import ConfigError


@pytest.fixture(scope="module")
def nominal():
    return BicycleConfig.load("nominal")


def linear_bicycle_yaw_rate_gain(p, vx):
    """Steady-state omega / delta of the linear bicycle with axle stiffness C = 2 C_a per axle:
    vx / (L + K vx^2), understeer gradient K = m (l_r C_r - l_f C_f) / (L C_f C_r)."""
    L, Cf, Cr = p.lf + p.lr, 2 * p.Caf, 2 * p.Car
    K = p.m * (p.lr * Cr - p.lf * Cf) / (L * Cf * Cr)
    return vx / (L + K * vx ** 2)


def test_paper_parameter_table_is_the_nominal_set(nominal):
    p = nominal.params
    assert (p.m, p.Iz, p.lf, p.lr, p.Caf, p.Car) == (2257.0, 3524.9, 1.33, 1.81, 66900.0, 62700.0)
    e = BicycleConfig.load("exact").params
    assert (e.m, e.Iz, e.Caf, e.Car) == (1257.0, 1524.9, 8790.0, 30400.0)


@pytest.mark.parametrize("param_set", ["nominal", "exact"])
def test_steady_state_yaw_rate_matches_linear_bicycle_gain(param_set):
    cfg = BicycleConfig.load(param_set)
    car = DynamicBicycle(cfg, [0.0, 0.0, 0.0, 10.0])
    delta = 0.01
    for _ in range(200):  # 10 s: the lateral/yaw transients have long settled
        car.step([0.0, delta], 0.05)
    vx, omega = car.state[3], car.state[5]
    expected = linear_bicycle_yaw_rate_gain(cfg.params, vx) * delta
    assert abs(vx - 10.0) < 0.05  # the small vy*omega term barely changes the speed
    assert omega == pytest.approx(expected, rel=0.02)


def test_straight_line_keeps_lateral_states_zero(nominal):
    car = DynamicBicycle(nominal, [1.0, 2.0, 0.3, 10.0])
    for _ in range(200):
        x = car.step([0.0, 0.0], 0.05)
    assert x[4] == 0.0 and x[5] == 0.0
    assert x[2] == pytest.approx(0.3, abs=1e-15)
    assert x[:2] == pytest.approx([1.0 + 100.0 * np.cos(0.3), 2.0 + 100.0 * np.sin(0.3)], abs=1e-9)


def test_stopped_car_with_steering_does_not_move(nominal):
    car = DynamicBicycle(nominal, [0.0, 0.0, 0.0, 0.0])
    for _ in range(100):
        x = car.step([0.0, 0.4], 0.05)
    assert np.all(x == 0.0)
    assert car.applied_control[1] == pytest.approx(0.4)


def test_braking_stops_without_reversing(nominal):
    car = DynamicBicycle(nominal, [0.0, 0.0, 0.0, 2.0])
    for _ in range(40):
        x = car.step([-6.0, 0.0], 0.05)
    assert x[3] == 0.0
    assert x[0] == pytest.approx(2.0 ** 2 / (2 * 6.0), abs=0.01)  # stopping distance v^2 / 2a


def test_low_speed_turn_follows_kinematic_radius(nominal):
    car = DynamicBicycle(nominal, [0.0, 0.0, 0.0, 0.5])
    delta = 0.2
    for _ in range(100):
        x = car.step([0.0, delta], 0.05)
    L = nominal.params.wheelbase
    assert x[5] == pytest.approx(x[3] * np.tan(delta) / L, rel=1e-3)  # omega = v tan(delta) / L
    assert x[4] == pytest.approx(nominal.params.lr * x[5], rel=1e-3)


def test_blend_is_continuous_at_both_ends(nominal):
    p = nominal.params
    for v in (nominal.v_kinematic, nominal.v_dynamic):
        lo = bicycle_derivative(np.array([0, 0, 0, v - 1e-7, 0.05, 0.1]), np.array([0.0, 0.1]), p,
                                nominal.v_kinematic, nominal.v_dynamic, nominal.tau_kinematic)
        hi = bicycle_derivative(np.array([0, 0, 0, v + 1e-7, 0.05, 0.1]), np.array([0.0, 0.1]), p,
                                nominal.v_kinematic, nominal.v_dynamic, nominal.tau_kinematic)
        assert np.allclose(lo, hi, atol=1e-4)


def test_actuator_limits_and_steering_rate(nominal):
    lim = nominal.limits
    car = DynamicBicycle(nominal, [0.0, 0.0, 0.0, 5.0])
    car.step([50.0, 1.0], 0.05)
    a, d = car.applied_control
    assert a == lim.a_max
    assert d == pytest.approx(lim.delta_rate_max * 0.05)
    for _ in range(100):
        car.step([-50.0, 1.0], 0.05)
    assert car.applied_control[0] == lim.a_min
    assert car.applied_control[1] == pytest.approx(lim.delta_max)


def test_process_noise_is_seeded_and_has_the_configured_std(nominal):
    runs = []
    for _ in range(2):
        car = DynamicBicycle(nominal, [0.0, 0.0, 0.0, 10.0], process_noise=True, seed=7)
        runs.append(np.array([car.step([0.0, 0.0], 0.05) for _ in range(2000)]))
    assert np.array_equal(runs[0], runs[1])
    # Y follows the noise as a random walk (vy, omega noise also feed it): its increments'
    # spread is dominated by the direct noise term.
    steps = np.diff(runs[0][:, 3])  # vx: a random walk with increments ~ N(0, sigma^2)
    assert np.std(steps) == pytest.approx(nominal.process_noise_std, rel=0.1)


def test_bad_commands_and_states_are_rejected(nominal):
    car = DynamicBicycle(nominal)
    with pytest.raises(ValueError, match="finite"):
        car.step([np.nan, 0.0], 0.05)
    with pytest.raises(ValueError):
        car.step([0.0], 0.05)
    with pytest.raises(ValueError):
        car.reset([0.0, 0.0, 0.0, -1.0])


def test_unknown_parameter_set_names_the_field():
    with pytest.raises(ConfigError, match="params.sporty"):
        BicycleConfig.load("sporty")


def test_bad_parameter_file_names_file_and_field(tmp_path):
    from vflpcd.base.paths import config_dir

    text = (config_dir() / "plants" / "dynamic_bicycle.toml").read_text().replace("m = 2257.0", "m = -2257.0")
    f = tmp_path / "bike.toml"
    f.write_text(text)
    with pytest.raises(ConfigError) as err:
        BicycleConfig.load("nominal", f)
    assert str(err.value).startswith(str(f)) and "params.nominal.m" in str(err.value)
