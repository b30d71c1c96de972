"""A stop the speed plan asks for: the throttle eases into it ahead of the reference's braking
(its increments are the command's own, ``command_increments_ground``) and the car stops at the goal."""

from line_road import vflpc_on_a_line
from vflpcd.core.jobs import run_inline


def test_the_car_brakes_ahead_of_a_planned_stop_and_stops_at_the_goal(tmp_path):
    sc, ctl, plant = vflpc_on_a_line(tmp_path, 80.0, 6.0, stop=True)
    dt = sc.control_period
    vx = ctl.model.state_names.index("vx")
    braking = reference_braking = None
    for k in range(int(30.0 / dt)):
        t = k * dt
        u = ctl.step(plant.state, t)
        v_ref = float(ctl._horizon.at(t)[0][vx])          # the reference speed now
        if braking is None and u[0] < -0.5:
            braking = t
        if reference_braking is None and v_ref < 5.9:
            reference_braking = t
        plant.step(u, dt)
        run_inline(ctl)
        if braking is not None and abs(plant.state[vx]) < 1e-3:
            break
    assert braking is not None and reference_braking is not None
    assert braking < reference_braking - 0.3                  # eased in ahead of the plan's braking
    overshoot = plant.state[0] - 80.0
    assert -0.3 <= overshoot <= 0.05 and abs(plant.state[1]) < 0.05, plant.state
