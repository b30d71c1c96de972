"""Real-time-iteration NMPC: one Gauss-Newton step per tick on the MPC-CBF problem, its fixed point,
closed-loop tracking and avoidance, the compiled and interpreted QP data, config errors."""

import dataclasses

import numpy as np
import pytest

from sim.runner import run_closed_loop
from vflpcd.base.errors import ConfigError
from vflpcd.controllers import make_controller
from vflpcd.controllers.compiled import c_compiler
from vflpcd.controllers.nmpc_cbf import NmpcCbfConfig, make_nmpc_cbf
from vflpcd.controllers.nmpc_rti import NmpcRti, RtiConfig, make_nmpc_rti

from tests.unit.sim.test_nmpc_cbf import BLOCK, assert_commands_in_limits

needs_cc = pytest.mark.skipif(c_compiler() is None, reason="no C compiler on this machine")


def captured_args(ctrl, x, t):
    """The QP step's arguments of one tick of ``ctrl`` at state x, time t."""
    seen = {}
    solve = ctrl._solve

    def spy(args):
        seen["args"] = dict(args)
        return solve(args)

    ctrl._solve = spy
    ctrl.step(x, t)
    ctrl._solve = solve
    return seen["args"]


def test_repeated_iterations_at_one_state_reach_the_converged_nmpc(line_scenario):
    """The real-time iteration is a Gauss-Newton SQP step: iterated at one state it converges to the
    KKT point that IPOPT finds for the same problem (here with the block 12 m ahead active)."""
    s = line_scenario("rti_line", length=50.0, obstacles=BLOCK)
    rti = make_nmpc_rti(s, rti=dataclasses.replace(RtiConfig.load(), tol=1e-8, iter_max=200))
    tight = dataclasses.replace(NmpcCbfConfig.load(), tol=1e-10, acceptable_tol=1e-10, max_iter=500)
    cbf = make_nmpc_cbf(s, tight)
    x = np.array([13.0, 0.3, 0.0, 5.0, 0.0, 0.0])
    args = captured_args(rti, x, 0.0)
    w = np.asarray(args["x0"], float)
    steps = []
    for _ in range(30):
        ok, status, sol = rti._solve({**args, "x0": w})
        assert ok, status
        steps.append(float(np.max(np.abs(sol["x"] - w))))
        w = sol["x"]
    assert steps[-1] < 1e-6 < steps[0]
    cbf.step(x, 0.0)
    U = w[rti._nX:rti._nX + rti._nU].reshape(rti.N, 2)
    np.testing.assert_allclose(U, cbf.plan_controls, atol=1e-4)


def test_tracks_a_line_and_passes_a_block_without_contact(line_scenario):
    s = line_scenario("rti_line", length=50.0, y0=0.5, obstacles=BLOCK)
    ctrl = make_controller("nmpc_rti", s)
    assert isinstance(ctrl, NmpcRti)
    rec = run_closed_loop(s, ctrl)
    assert rec.outcome == "completed" and rec.metrics["collisions"] == 0 and rec.metrics["min_clearance"] > 0.0
    assert ctrl.failures == 0
    assert_commands_in_limits(rec.command, ctrl.config, s.control_period)
    assert abs(rec.lateral[-1]) < 0.1


@needs_cc
def test_the_compiled_qp_data_equal_the_interpreted_ones(line_scenario):
    s = line_scenario("rti_line", length=50.0, obstacles=BLOCK)
    fast = make_controller("nmpc_rti", s)
    slow = make_nmpc_rti(s, rti=dataclasses.replace(RtiConfig.load(), compile="never"))
    assert fast.compiled and not slow.compiled
    x = np.array([10.0, 0.2, 0.05, 5.0, 0.1, 0.02])
    np.testing.assert_allclose(fast.step(x, 0.0), slow.step(x, 0.0), rtol=0.0, atol=1e-9)
    np.testing.assert_allclose(fast.step(x + 0.1, 0.05), slow.step(x + 0.1, 0.05), rtol=0.0, atol=1e-9)


def test_a_failed_qp_falls_back_to_the_shifted_plan(line_scenario, monkeypatch):
    s = line_scenario("rti_line")
    ctrl = make_controller("nmpc_rti", s)
    x = np.array([0.0, 0.3, 0.0, 5.0, 0.0, 0.0])
    ctrl.step(x, 0.0)
    plan = ctrl.plan_controls.copy()
    monkeypatch.setattr(ctrl, "_solve", lambda args: (False, "HPIPM 1", None))
    u = ctrl.step(x, 0.05)
    assert ctrl.failures == 1 and ctrl.last_status == "HPIPM 1"
    np.testing.assert_allclose(u[0], plan[1][0], atol=1e-9)


def test_config_errors_name_the_file_and_the_field(tmp_path, line_scenario, monkeypatch):
    bad = tmp_path / "rti.toml"
    bad.write_text('compile = "sometimes"\n[hpipm]\niter_max = 50\ntol = 1e-6\n')
    with pytest.raises(ConfigError, match=r"rti.toml: compile: .*auto"):
        RtiConfig.load(bad)
    bad.write_text('compile = "auto"\nspeed = 3\n[hpipm]\niter_max = 50\ntol = 1e-6\n')
    with pytest.raises(ConfigError, match=r"rti.toml: .*speed"):
        RtiConfig.load(bad)
    monkeypatch.setenv("CC", "no-such-compiler-here")
    with pytest.raises(ConfigError, match=r"compile: \"always\", but the QP data could not be compiled"):
        make_nmpc_rti(line_scenario("rti_line"), rti=dataclasses.replace(RtiConfig.load(), compile="always"))
    auto = make_nmpc_rti(line_scenario("rti_line"))          # "auto" without a compiler: interpreted
    assert not auto.compiled and np.all(np.isfinite(auto.step(np.array([0.0, 0.0, 0.0, 5.0, 0.0, 0.0]), 0.0)))
