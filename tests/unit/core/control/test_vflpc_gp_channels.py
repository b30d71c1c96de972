"""The GP's channels (config/controllers/vflpc.toml [compensation]): it learns the residual of the
window frame's lateral pose rows (Y, psi) as well as the velocities', and its input leaves the pose
out (in the window frame of a sample the pose is zero)."""

import dataclasses

import numpy as np
import pytest

from vflpcd.config.scenarios import load_scenario
from vflpcd.controllers.vflpc import compensator_for, load_params, make_vflpc
from vflpcd.core.dynamics.lifted import to_window_frame
from sim.plants import make_plant

DT = 0.05


@pytest.fixture(scope="module")
def straight():
    return dataclasses.replace(load_scenario("carsim_avoidance"), obstacles=())


def transitions(scenario, model, steps: int, seed: int):
    """(U_k, u_k, U_next) of the plant driven straight at its start speed with a small random
    steering, in the window frame of each step's first state (as ``VFLPC._observe`` offers them)."""
    rng = np.random.default_rng(seed)
    plant = make_plant(scenario, seed)
    out = []
    for _ in range(steps):
        x = plant.state.copy()
        u = np.array([0.0, 0.01 * rng.standard_normal()])
        plant.step(u, DT)
        pair = to_window_frame(np.vstack([x, plant.state]), model.state_names)
        U = model.lift(pair)
        out.append((U[0], u, U[1]))
    return out


def test_the_gp_outputs_the_lateral_pose_rows_and_its_input_leaves_the_pose_out(straight):
    ctrl = make_vflpc(straight)
    names = ctrl.model.state_names
    params = load_params("ground")
    assert {"Y", "psi"} <= set(params.gp_channels)
    comp = compensator_for(ctrl.model, params).comp
    rows = [names.index(n) for n in params.gp_channels]
    np.testing.assert_array_equal(np.argmax(comp.B_d, axis=0), rows)
    pose = {names.index(n) for n in ("X", "Y", "psi")}
    assert pose.isdisjoint(comp.z_index.tolist())
    assert set(range(ctrl.model.n_x, ctrl.model.n_K - 1)) <= set(comp.z_index.tolist())   # the encoder's


@pytest.mark.parametrize("channels, learns_y", [(("Y", "psi", "vx", "vy", "omega"), True),
                                                (("vx", "vy", "omega"), False)])
def test_the_gp_removes_the_models_lateral_drift_only_with_the_pose_rows(straight, channels, learns_y):
    """Driving straight, the shipped model moves Y by a few mm a step where the car does not: a
    drift that a GP on the velocities alone cannot correct (a steady lateral offset in the loop)."""
    ctrl = make_vflpc(straight)
    model = ctrl.model
    y = model.state_names.index("Y")
    params = dataclasses.replace(load_params("ground"), gp_channels=channels)
    comp = compensator_for(model, params)
    for U, u, U_next in transitions(straight, model, 200, seed=0):
        comp.observe(U, u, U_next)
    gp = comp.refit()
    assert gp is not None
    test = transitions(straight, model, 50, seed=1)
    U, u, U_next = (np.array(a) for a in zip(*test))
    nominal = np.abs(comp.comp.predict(U, u, None)[:, y] - U_next[:, y]).mean()
    corrected = np.abs(comp.comp.predict(U, u, gp)[:, y] - U_next[:, y]).mean()
    assert nominal > 5e-4                                  # the model's drift, m per step
    if learns_y:
        assert corrected < 0.25 * nominal
    else:
        assert corrected == pytest.approx(nominal, rel=0.05)


def test_a_channel_that_is_not_a_state_is_named(straight):
    model = make_vflpc(straight).model
    params = dataclasses.replace(load_params("ground"), gp_channels=("Y", "vz"))
    with pytest.raises(ValueError, match=r"\['vz'\] are not states"):
        compensator_for(model, params)
