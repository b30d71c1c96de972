"""MPC-CBF baseline: closed-loop tracking and avoidance, the DCBF at a solution, the fallback, config errors."""

import dataclasses

import numpy as np
import pytest

from vflpcd.controllers import make_controller
from vflpcd.controllers.nmpc_cbf import NmpcCbf, NmpcCbfConfig, obstacle_discs
from sim.runner import run_closed_loop
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Box, Circle, Ellipse
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir

BLOCK = """
[[obstacles]]
id = "block"
shape = "box"
length = 2.0
width = 1.0
center = [25.0, -0.2]
"""


@pytest.fixture(scope="module")
def config():
    return NmpcCbfConfig.load()


def assert_commands_in_limits(commands, cfg, dt):
    lim = cfg.model.limits
    assert np.all(np.isfinite(commands))
    assert np.all(commands[:, 0] >= lim.a_min) and np.all(commands[:, 0] <= lim.a_max)
    assert np.all(np.abs(commands[:, 1]) <= lim.delta_max)
    delta = np.concatenate([[0.0], commands[:, 1]])      # the plant starts with straight wheels
    assert np.all(np.abs(np.diff(delta)) <= lim.delta_rate_max * dt + 1e-9)


def test_converges_to_a_straight_path_from_a_lateral_offset(line_scenario, config):
    s = line_scenario("nmpc_line", y0=0.5)
    ctrl = make_controller("nmpc_cbf", s)
    assert isinstance(ctrl, NmpcCbf) and ctrl.N == round(config.horizon_seconds / s.control_period)
    rec = run_closed_loop(s, ctrl)
    assert rec.outcome == "completed"
    assert abs(rec.lateral[0]) == pytest.approx(0.5)
    assert abs(rec.lateral[-1]) < 0.1
    assert np.max(np.abs(rec.lateral[len(rec.t) // 2:])) < 0.1
    assert_commands_in_limits(rec.command, config, s.control_period)
    assert ctrl.failures == 0


def test_passes_a_static_obstacle_on_the_path_without_contact(line_scenario, config):
    s = line_scenario("nmpc_line", length=50.0, obstacles=BLOCK)
    ctrl = make_controller("nmpc_cbf", s)
    rec = run_closed_loop(s, ctrl)
    m = rec.metrics
    assert rec.outcome == "completed"
    assert m["collisions"] == 0
    assert m["min_clearance"] > 0.0
    assert np.max(np.abs(rec.lateral)) > 1.0          # it went round, not through
    assert_commands_in_limits(rec.command, config, s.control_period)
    assert ctrl.failures == 0


def test_the_dcbf_holds_along_the_plan_of_one_solve(line_scenario, config):
    s = line_scenario("nmpc_line", length=60.0)
    ctrl = NmpcCbf(s.path, s.v_desired, s.a_lat_max, s.control_period, s.footprint, config)
    obs = ObstacleState(id="post", shape=Circle(0.8), center=np.array([7.0, 0.4]), yaw=0.0,
                        velocity=np.array([-0.5, 0.0]), stamp=2.0)
    u = ctrl.step(np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0]), 2.0, [obs])
    assert ctrl.last_status == "Solve_Succeeded" and ctrl.failures == 0
    X = ctrl.plan_states
    assert X.shape == (ctrl.N + 1, 6) and np.all(np.isfinite(u))
    # h of every car disc against the (moving) post, computed here from the plan alone
    t_k = 2.0 + s.control_period * np.arange(ctrl.N + 1)
    c_k = np.array([obs.center_at(t) for t in t_k])
    R = 0.8 + s.footprint.radius + config.margin
    axis = np.stack([np.cos(X[:, 2]), np.sin(X[:, 2])], axis=1)
    discs = X[:, None, :2] + s.footprint.offsets[None, :, None] * axis[:, None, :]   # (N+1, n_discs, 2)
    h = np.sum((discs - c_k[:, None, :]) ** 2, axis=2) - R ** 2                   # (N+1, n_discs)
    g = 1.0 - config.cbf_gamma
    slack = np.max(ctrl.plan_slack)
    assert slack < 1e-3
    tol = slack + 1e-4
    assert np.all(h[1:] >= g * h[:-1] - tol)                                      # h(x_{k+1}) >= (1-gamma) h(x_k)
    assert np.all(h >= g ** np.arange(ctrl.N + 1)[:, None] * h[0] - tol)          # hence >= (1-gamma)^k h(x_0)
    assert np.min(h[1:] - g * h[:-1]) < 1e-3      # and it is active: the post bends the plan


def test_solver_failure_falls_back_to_the_shifted_plan_then_brakes(line_scenario, config, monkeypatch, caplog):
    s = line_scenario("nmpc_line")
    ctrl = NmpcCbf(s.path, s.v_desired, s.a_lat_max, s.control_period, s.footprint,
                   dataclasses.replace(config, max_iter=50))
    x = np.array([0.0, 0.3, 0.0, 5.0, 0.0, 0.0])
    ctrl.step(x, 0.0)
    plan = ctrl.plan_controls.copy()

    def broken(**kwargs):
        raise RuntimeError("forced failure")

    monkeypatch.setattr(ctrl, "_solver", broken)
    lim = config.model.limits
    u = ctrl.step(x, 0.05)
    assert ctrl.failures == 1
    assert np.all(np.isfinite(u)) and lim.a_min <= u[0] <= lim.a_max and abs(u[1]) <= lim.delta_max
    np.testing.assert_allclose(u, np.clip(plan[1], [lim.a_min, -lim.delta_max], [lim.a_max, lim.delta_max]),
                               atol=1e-9)
    assert "forced failure" in caplog.text

    ctrl.reset()                                    # no plan to fall back on: brake, wheels held
    assert ctrl.failures == 0
    u = ctrl.step(x, 0.0)
    assert ctrl.failures == 1
    np.testing.assert_allclose(u, [lim.a_min, 0.0])


def test_non_success_status_counts_as_a_failure(line_scenario, config, monkeypatch):
    s = line_scenario("nmpc_line")
    ctrl = NmpcCbf(s.path, s.v_desired, s.a_lat_max, s.control_period, s.footprint,
                   dataclasses.replace(config, max_iter=1))
    u = ctrl.step(np.array([0.0, 1.5, 0.4, 5.0, 0.0, 0.0]), 0.0)      # one iteration cannot converge
    assert ctrl.failures == 1 and ctrl.last_status == "Maximum_Iterations_Exceeded"
    lim = config.model.limits
    assert np.all(np.isfinite(u)) and lim.a_min <= u[0] <= lim.a_max
    assert abs(u[1]) <= lim.delta_rate_max * s.control_period + 1e-12


def test_obstacle_discs_cover_the_shapes():
    rng = np.random.default_rng(1)
    for shape in (Circle(1.0), Box(4.6, 1.9), Ellipse(2.0, 1.0), Box(1.0, 3.0)):
        centres, r, n = obstacle_discs(shape, 3)
        outline = shape.outline(np.zeros(2), 0.0, 400)
        inside = outline * rng.uniform(0.0, 1.0, size=(400, 1))
        pts = np.vstack([outline, inside])
        d = np.min(np.linalg.norm(pts[:, None, :] - centres[None, :, :], axis=2), axis=1)
        assert np.all(d <= r + 1e-9)
        assert r <= shape.bounding_radius() + 1e-12
    assert obstacle_discs(Box(4.6, 1.9), 3)[1] == pytest.approx(np.hypot(2.3 / 3, 0.95))


def test_config_errors_name_the_file_and_field(tmp_path):
    text = (config_dir() / "controllers" / "nmpc_cbf.toml").read_text()
    bad = tmp_path / "nmpc_cbf.toml"
    bad.write_text(text.replace("[cbf]\n", "[cbf]\nmargn = 0.3\n"))
    with pytest.raises(ConfigError) as err:
        NmpcCbfConfig.load(bad)
    assert err.value.field == "cbf.margn" and str(bad) in str(err.value)

    bad.write_text("horizon_seconds = 0.5\n" + text)
    with pytest.raises(ConfigError, match="horizon_seconds.*at least the shared horizon"):
        NmpcCbfConfig.load(bad)

    bad.write_text(text.replace('model_params = "nominal"', 'model_params = "sporty"'))
    with pytest.raises(ConfigError) as err:
        NmpcCbfConfig.load(bad)
    assert err.value.field == "model_params"

    bad.write_text(text.replace("max_iter = 100", ""))
    with pytest.raises(ConfigError) as err:
        NmpcCbfConfig.load(bad)
    assert err.value.field == "ipopt.max_iter" and "missing" in err.value.message
