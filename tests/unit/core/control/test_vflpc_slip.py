"""VF-LPC's reference in the road's bends: the car's heading and body velocities at its steady slip
(``VFLPC._road_slip``), with the parameter set the controller knows, not the simulated plant's."""

import dataclasses

import numpy as np
import pytest

from sim.plants import make_plant
from vflpcd.config.scenarios import load_scenario
from vflpcd.config.vehicles import BicycleConfig
from vflpcd.controllers.vflpc import make_vflpc, planner_body
from vflpcd.core.guidance.tighten import Body
from vflpcd.core.obstacle_world import ObstacleWorld
from vflpcd.base.paths import config_dir

RING = config_dir() / "scenarios" / "suite" / "roundabout.toml"


def _reference_after_a_step(scenario):
    ctrl = make_vflpc(scenario)
    plant = make_plant(scenario, 0)
    ctrl.step(plant.state, 0.0)
    names = list(ctrl.model.state_names)
    ref = ctrl._reference(0.0)
    return ctrl, ref[:, names.index("psi")], ref[:, names.index("vx")], ref[:, names.index("vy")]


def test_on_a_ring_the_reference_turns_the_heading_off_the_course_by_the_steady_slip():
    """A 15 m ring driven to the left at 5 m/s, no obstacle: the reference's body velocity points
    beta = asin(kappa (lr - K v^2)) left of its heading, the heading lies beta right of the path's
    course, and the speed along the course is the plan's."""
    ring = dataclasses.replace(load_scenario(RING), obstacles=())
    ctrl, psi, vx, vy = _reference_after_a_step(ring)
    course = ctrl.current_plan.trajectory.sample(ctrl._horizon_offsets, ("psi", "v"))
    beta = ctrl._body.slip_angle(1.0 / 15.0, course["v"])
    assert np.all(beta > 0.09)                                   # ~0.1 rad: the SUV at 5 m/s on 15 m
    ring_on = slice(3, None)                                     # the road's bend is 1 m wide: it rises over the ring's first metre
    np.testing.assert_allclose(np.arctan2(vy, vx)[ring_on], beta[ring_on], atol=2e-3)
    np.testing.assert_allclose((course["psi"] - psi)[ring_on], beta[ring_on], atol=2e-3)
    np.testing.assert_allclose(np.hypot(vx, vy), course["v"], rtol=1e-12)


def test_a_swerve_on_a_straight_road_keeps_the_course():
    """double_lane_change's road is straight and its plan swerves round the boxes: the reference
    keeps the path's course and no lateral body velocity there (the road's bend, not the swerve's)."""
    sc = load_scenario(config_dir() / "scenarios" / "suite" / "double_lane_change.toml")
    ctrl = make_vflpc(sc)
    plant = make_plant(sc, 0)
    world = ObstacleWorld(sc.obstacles)
    swerving = 0
    for k in range(240):                      # 12 s: past the truck at 55 m
        u = ctrl.step(plant.state, k * 0.05, world.snapshot(k * 0.05))
        plant.step(u, 0.05)
        course = ctrl.current_plan.trajectory.sample(k * 0.05 + ctrl._horizon_offsets, ("psi", "kappa", "v"))
        if np.max(np.abs(course["kappa"])) > 0.02:
            swerving += 1
            names = list(ctrl.model.state_names)
            ref = ctrl._reference(k * 0.05)
            np.testing.assert_array_equal(ref[:, names.index("vy")], 0.0)
            np.testing.assert_allclose(ref[:, names.index("psi")], course["psi"], atol=1e-12)
            np.testing.assert_allclose(ref[:, names.index("vx")], course["v"], atol=1e-12)
    assert swerving > 10


def test_the_controller_knows_its_own_parameter_set_not_the_plants():
    """The model-uncertainty runs drive the "exact" car; the controller's slip comes from the
    parameter set of its [vehicle] table (nominal), as the NMPC's model does."""
    exact = dataclasses.replace(load_scenario("racing_track"), params="exact")
    ctrl = make_vflpc(exact)
    nominal, mismatched = BicycleConfig.load("nominal").params, BicycleConfig.load("exact").params
    assert ctrl.params.vehicle_params == "nominal"
    assert ctrl._body.slip_gain == pytest.approx(nominal.m * nominal.lf / (2.0 * nominal.Car * nominal.wheelbase))
    assert planner_body(exact, "exact").slip_gain == pytest.approx(
        mismatched.m * mismatched.lf / (2.0 * mismatched.Car * mismatched.wheelbase))
    assert planner_body(exact, "exact").slip_gain != pytest.approx(ctrl._body.slip_gain)


def test_slip_angle_signs_its_lever_and_a_body_that_does_not_slip():
    body = Body(np.zeros(1), 1.0, rear_axle=1.8, slip_gain=0.01)
    assert body.slip_angle(0.1, 0.0) == pytest.approx(np.arcsin(0.18))
    assert body.slip_angle(-0.1, 0.0) == pytest.approx(-np.arcsin(0.18))
    assert body.slip_angle(0.1, 20.0) == 0.0                  # lr - K v^2 < 0: held at 0
    assert Body(np.zeros(1), 1.0).slip_angle(0.1, 5.0) == 0.0
    np.testing.assert_allclose(body.slip_angle(np.array([0.05, 0.0]), np.array([3.0, 3.0])),
                               [np.arcsin(0.05 * (1.8 - 0.09)), 0.0])


def test_a_sharp_corner_of_a_polyline_road_turns_the_reference_no_more_than_the_car_can(tmp_path):
    """A road of waypoints with a 60 degree corner and no radius: the road's bend there is at most
    the car's curvature limit (its heading's change over a metre would be 1 1/m), so the slip in
    the reference stays at most asin(lr kappa_limit) whatever the road's drawing."""
    text = (config_dir() / "scenarios" / "suite" / "roundabout.toml").read_text()
    head, rest = text.split("[path]", 1)
    rest = rest.split("[start]", 1)[1]
    corner = "[path]\nkind = \"waypoints\"\npoints = [[0.0, 0.0], [12.0, 0.0], [30.0, 31.18]]\n\n[start]" + rest
    path = tmp_path / "corner.toml"
    path.write_text(head + corner)
    sc = dataclasses.replace(load_scenario(path), obstacles=())
    ctrl = make_vflpc(sc)
    plant = make_plant(sc, 0)
    ctrl.step(plant.state, 0.0)
    slip = ctrl._road_slip(ctrl.current_plan)
    bound = np.arcsin(ctrl._body.rear_axle * ctrl.planner.kappa_limit)
    assert np.max(np.abs(slip)) > 0.5 * bound                   # the corner is in the plan
    assert np.max(np.abs(slip)) <= bound + 1e-12
