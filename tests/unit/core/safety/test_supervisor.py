"""The safety supervisor against the simulated plants: stops before what it knows, lets safe
commands through, and handles movers, impossible stops and the quadrotor's hold."""

import numpy as np
import pytest

from sim.plants.dynamic_bicycle import DynamicBicycle

from vflpcd.config.vehicles import BicycleConfig
from sim.plants.quadrotor import Quadrotor
from vflpcd.config.vehicles import QuadrotorParams
from vflpcd.core.footprint import Footprint
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.safety.supervisor import (AerialSupervisor, CarLimits, GroundSupervisor, QuadLimits,
                                           SupervisorConfig)
from vflpcd.core.shapes import Box, Circle, Sphere

DT = 0.05
CFG = SupervisorConfig()


def car(speed: float, y: float = 0.0, yaw: float = 0.0):
    cfg = BicycleConfig.load("nominal")
    lim = cfg.limits
    limits = CarLimits(cfg.params.wheelbase, lim.a_min, lim.a_max, lim.delta_max, lim.delta_rate_max)
    body = Footprint.rectangle(cfg.body.length, cfg.body.width, cfg.body.rear_overhang + cfg.params.lr)
    plant = DynamicBicycle(cfg, np.array([0.0, y, yaw, speed]))
    return plant, GroundSupervisor(CFG, body, limits, DT), body


def obstacle(oid, shape, center, velocity=(0.0, 0.0), stamp=0.0):
    return ObstacleState(oid, shape, np.array(center, float), 0.0, np.array(velocity, float), stamp)


def drive(plant, sup, body, obstacles, command, seconds, moving=False):
    """Closed loop: the same controller command every tick through the supervisor; returns the least
    exact clearance, the speed at the first contact (None) and the interventions."""
    least, impact = np.inf, None
    for k in range(int(seconds / DT)):
        t = k * DT
        now = [obstacle(o.id, o.shape, o.center_at(t), o.velocity, t) for o in obstacles] if moving else obstacles
        v = sup.filter(plant.state, np.array(command, float), now, t)
        plant.step(v.command, DT)
        gap = min(body.clearance(o.shape, o.center_at(t + DT), 0.0, plant.position(), plant.heading())
                  for o in obstacles)
        if gap <= 0.0 and impact is None:
            impact = float(np.hypot(*plant.velocity_world()))
        least = min(least, gap)
    return least, impact, sup.interventions


@pytest.mark.parametrize("speed", [3.0, 7.0, 12.0])
def test_a_car_driven_at_a_wall_stops_before_it_and_not_far_from_it(speed):
    plant, sup, body = car(speed)
    wall = obstacle("wall", Box(1.0, 10.0), [30.0, 0.0])
    least, impact, interventions = drive(plant, sup, body, [wall], [3.0, 0.0], 20.0)
    assert impact is None and least > 0.0
    assert np.hypot(*plant.velocity_world()) < 0.05                      # at rest in front of it
    # stops within margin + the front disc's reach past the bumper + the braking slack (decel factor)
    assert least < 0.1 + 0.7 + 0.12 * speed ** 2 / 12 + 0.5
    assert interventions >= 1


def test_a_command_that_keeps_clear_goes_through_unchanged():
    plant, sup, body = car(7.0)
    beside = obstacle("post", Circle(0.3), [20.0, 2.2])                 # 0.95 m body half-width + 0.95 m gap
    u = np.array([0.5, 0.0])
    for k in range(60):
        v = sup.filter(plant.state, u, [beside], k * DT)
        assert not v.override and np.array_equal(v.command, u)
        plant.step(v.command, DT)
    assert sup.interventions == 0


def test_commands_are_clipped_to_the_actuator_limits_and_a_nonfinite_one_brakes():
    plant, sup, _ = car(5.0)
    v = sup.filter(plant.state, np.array([10.0, 2.0]), [], 0.0)
    assert v.command.tolist() == [3.0, 0.5] and not v.override
    v = sup.filter(plant.state, np.array([np.nan, 0.0]), [], DT)
    assert v.override and v.engaged and v.command[0] == -6.0 and "non-finite" in v.reason


def test_a_mover_closing_in_from_behind_does_not_make_the_car_brake():
    plant, sup, body = car(5.0)
    chaser = obstacle("chaser", Box(4.5, 1.9), [-6.0, 0.0], velocity=(8.0, 0.0))
    u = np.array([0.0, 0.0])
    v = sup.filter(plant.state, u, [chaser], 0.0)
    assert not v.override


def test_a_crossing_pedestrian_the_car_passes_in_front_of_does_not_trigger_a_stop_in_its_way():
    # at 7 m/s the car's rear bumper passes x = 14.4 after 2.45 s; the pedestrian reaches the lane's
    # edge (y = -1.35) after 3.1 s: going on clears, stopping would leave the car in the way
    plant, sup, body = car(7.0)
    ped = obstacle("ped", Circle(0.4), [14.0, -6.0], velocity=(0.0, 1.5))
    least, impact, interventions = drive(plant, sup, body, [ped], [0.0, 0.0], 3.0, moving=True)
    assert impact is None and interventions == 0


def test_when_no_stop_is_possible_it_still_brakes_and_hits_slower():
    def run(supervised):
        plant, sup, body = car(10.0)
        block = obstacle("block", Box(1.0, 3.0), [7.0, 0.0])            # 4.4 m from the bumper, 8.3 m needed
        if not supervised:
            sup.cfg = SupervisorConfig(margin=-1e9, release_margin=-1e9)
        return drive(plant, sup, body, [block], [0.0, 0.0], 3.0)
    _, hit_sup, n = run(True)
    _, hit_bare, _ = run(False)
    assert hit_bare == pytest.approx(10.0, abs=0.5)
    assert hit_sup is not None and hit_sup < 0.75 * hit_bare and n == 1


def test_when_braking_cannot_stop_short_of_a_pedestrian_it_brakes_steering_away_and_hits_slower():
    # a pedestrian steps out from the right 6.2 m ahead of the CoG at 25 km/h: braking alone meets them
    def run(steering_choice):
        plant, sup, body = car(6.944)
        if not steering_choice:
            sup._override = lambda state, u, obstacles, t: sup.emergency(state)
        ped = obstacle("ped", Circle(0.4), [6.2, -1.8], velocity=(0.0, 1.5))
        steer = []
        impact = None
        for k in range(int(3.0 / DT)):
            t = k * DT
            v = sup.filter(plant.state, np.array([0.0, 0.0]), [obstacle("ped", ped.shape, ped.center_at(t),
                                                                        ped.velocity, t)], t)
            assert not v.override or v.command[0] == -6.0                  # it always brakes fully
            steer.append(v.command[1])
            plant.step(v.command, DT)
            gap = body.clearance(ped.shape, ped.center_at(t + DT), 0.0, plant.position(), plant.heading())
            if gap <= 0.0 and impact is None:
                impact = float(np.hypot(*plant.velocity_world()))
        return impact, max(steer), sup.interventions
    held, held_steer, _ = run(False)
    swerved, steer, n = run(True)
    assert held is not None and held_steer == 0.0
    assert n == 1 and steer > 0.2                                      # away from the pedestrian's side
    assert swerved is None or swerved < 0.5 * held


def test_an_intervention_is_released_only_with_the_release_margin():
    plant, sup, _ = car(0.0)
    # the front disc reaches 0.69 m past the bumper (2.14 m ahead of the CoG): 0.05 m left, inside the margin
    wall = obstacle("wall", Box(1.0, 10.0), [2.14 + 0.69 + 0.05 + 0.5, 0.0])
    v = sup.filter(plant.state, np.array([3.0, 0.0]), [wall], 0.0)
    assert v.override and v.engaged
    v = sup.filter(plant.state, np.array([0.0, 0.0]), [wall], DT)        # standing still keeps the same clearance
    assert v.override and not v.engaged and sup.interventions == 1
    far = obstacle("wall", Box(1.0, 10.0), [10.0, 0.0])
    v = sup.filter(plant.state, np.array([0.0, 0.0]), [far], 2 * DT)
    assert not v.override and v.released


def test_a_body_at_rest_reuses_its_prediction_only_while_the_obstacles_stand_where_they_stood():
    """The same state, command and obstacles (new states, later stamps) give the last clearance without
    a new prediction; a wall moved or of another shape is predicted again."""
    plant, sup, _ = car(0.0)
    predictions = []
    poses = sup._poses
    sup._poses = lambda *a, **k: predictions.append(1) or poses(*a, **k)
    u = np.array([0.0, 0.0])

    def clearance(wall, t):
        before = len(predictions)
        return sup.filter(plant.state, u, [wall], t).clearance, len(predictions) > before

    c0, new = clearance(obstacle("wall", Box(1.0, 10.0), [4.0, 0.0]), 0.0)   # the steering estimate starts here
    assert new and clearance(obstacle("wall", Box(1.0, 10.0), [4.0, 0.0]), 0.0)[0] == c0
    assert clearance(obstacle("wall", Box(1.0, 10.0), [4.0, 0.0], stamp=DT), DT) == (c0, False)
    c1, new = clearance(obstacle("wall", Box(1.0, 10.0), [3.5, 0.0]), 2 * DT)
    assert new and c1 == pytest.approx(c0 - 0.5, abs=0.02)
    c2, new = clearance(obstacle("wall", Box(2.0, 10.0), [3.5, 0.0]), 3 * DT)
    assert new and c2 == pytest.approx(c1 - 0.5, abs=0.02)


def test_contact_is_the_exact_body_clearance():
    plant, sup, body = car(0.0)
    on_top = obstacle("on_top", Circle(1.0), [0.0, 0.0])
    gap, who = sup.contact(plant.state, [on_top], 0.0)
    assert who == "on_top" and gap < 0
    aside = obstacle("aside", Circle(0.5), [0.0, 0.95 + 0.5 + 0.02])     # inside the disc cover, 2 cm off the body
    gap, who = sup.contact(plant.state, [aside], 0.0)
    assert gap == pytest.approx(0.02, abs=0.01)
    far = obstacle("far", Circle(0.5), [0.0, 2.0])                      # the cover does not touch it: no contact
    assert sup.contact(plant.state, [far], 0.0)[0] == np.inf


def quad(velocity):
    params = QuadrotorParams.from_toml()
    plant = Quadrotor(params, np.array([0.0, 0.0, 2.0, *velocity, 0.0]))
    names = plant.state_names
    sup = AerialSupervisor(SupervisorConfig(latency_s=0.15, decel_factor=0.8), 0.3, QuadLimits(params.accel_max),
                           DT, names)
    return plant, sup


def test_a_quadrotor_flown_at_a_ball_brakes_to_hover_before_it_then_holds():
    plant, sup = quad([3.0, 0.0, 0.0])
    ball = ObstacleState("ball", Sphere(0.5), np.array([6.0, 0.0, 2.0]), 0.0, np.zeros(3), 0.0)
    least = np.inf
    for k in range(int(6.0 / DT)):
        v = sup.filter(plant.state, np.array([2.0, 0.0, 0.0]), [ball], k * DT)
        plant.step(v.command, DT)
        least = min(least, float(np.linalg.norm(plant.position() - ball.center)) - 0.5 - 0.3)
        if k == int(3.0 / DT):
            held = plant.position().copy()
    assert least > 0.0
    assert np.linalg.norm(plant.velocity_world()) < 0.1
    assert np.linalg.norm(plant.position() - held) < 0.1                 # holds where it stopped
    assert abs(plant.position()[2] - 2.0) < 0.2 and sup.interventions >= 1


def test_a_repeated_tick_at_rest_gives_the_same_verdict_and_a_changed_obstacle_a_new_one():
    plant, sup, _ = car(0.0)
    wall = obstacle("wall", Box(1.0, 10.0), [2.14 + 0.69 + 0.05 + 0.5, 0.0])
    u = np.array([3.0, 0.0])
    first = sup.predicted_clearance(plant.state, u, [wall], 0.0)
    again = sup.predicted_clearance(plant.state, u, [obstacle("wall", wall.shape, wall.center, stamp=1.0)], 1.0)
    assert again == first and first[0] < 0.1
    moved = obstacle("wall", wall.shape, wall.center + np.array([0.3, 0.0]), stamp=2.0)
    assert sup.predicted_clearance(plant.state, u, [moved], 2.0)[0] == pytest.approx(first[0] + 0.3, abs=1e-9)
    walker = obstacle("walker", Circle(0.3), [5.0, 0.0], velocity=(-1.0, 0.0), stamp=3.0)
    later = obstacle("walker", Circle(0.3), [4.0, 0.0], velocity=(-1.0, 0.0), stamp=4.0)
    assert sup.predicted_clearance(plant.state, u, [later], 4.0) != sup.predicted_clearance(plant.state, u, [walker], 3.0)


def test_the_stop_after_a_failsafe_steers_off_what_braking_with_the_steering_held_would_hit():
    # tripped while steering 0.3 rad left; a barrel stands where braking with that steering held
    # ends: the plain stop meets it, the stop that knows it steers off
    def tripped():
        plant, sup, body = car(7.0)
        for k in range(12):                                                   # the steering the car holds
            plant.step(sup.filter(plant.state, np.array([0.0, 0.3]), [], k * DT).command, DT)
        return plant, sup, body

    plant, sup, _ = tripped()
    arc = []
    for _ in range(int(3.0 / DT)):
        plant.step(sup.stop(plant.state), DT)
        arc.append(plant.position())
    stop = next(k for k in range(1, len(arc)) if np.allclose(arc[k], arc[k - 1]))       # at rest here
    ahead = (arc[stop - 1] - arc[stop - 3]) / np.linalg.norm(arc[stop - 1] - arc[stop - 3])
    barrel = obstacle("barrel", Circle(0.5), arc[stop - 1] + 1.0 * ahead)     # under the front bumper

    def run(aware: bool):
        plant, sup, body = tripped()
        least = np.inf
        for k in range(int(3.0 / DT)):
            u = sup.stop(plant.state, [barrel], k * DT) if aware else sup.stop(plant.state)
            assert u[0] == sup.limits.a_min                                   # it always brakes fully
            plant.step(u, DT)
            least = min(least, body.clearance(barrel.shape, barrel.center, 0.0, plant.position(), plant.heading()))
        return least
    held, aware = run(False), run(True)
    assert held <= 0.0 < aware


def test_going_on_counts_a_mover_that_the_turn_brings_behind_the_body():
    """A car turning left in front of a car crossing from the right (the state of a real-time
    iteration NMPC in the suite's junction_crossing_car, 0.75 s before it was hit): braking keeps
    only 1 cm, and going on, hard left at +3 m/s^2, puts the crossing car behind the body's middle
    where it catches it up. Going on must count that mover: the command is overridden."""
    plant, sup, body = car(3.0848)
    plant.reset(np.array([57.6108, 0.3151, 0.1297, 3.0848, 0.62, 0.3614]))
    sup.delta = 0.3806                                   # the steering that the commands sent have reached
    crossing = ObstacleState("crossing_car", Box(4.5, 1.9), np.array([60.0, -6.0]), np.pi / 2,
                             np.array([0.0, 5.0]), 9.85)
    v = sup.filter(plant.state, np.array([3.0, 0.4106]), [crossing], 9.85)
    assert v.override and v.nearest == "crossing_car" and v.clearance < CFG.margin
    assert v.command[0] == -6.0                          # it brakes


def test_a_car_is_not_stopped_in_the_way_of_a_crossing_car():
    """A car cruising at 6 m/s towards a junction that a car crosses from the right at 5 m/s (the
    suite's junction_crossing_car at t = 8.4 s): going on passes ahead of it, and a stop is safe only
    where the body then stays out of the crossing car's way for mover_wait_s. Before, the
    supervisor braked once going on no longer cleared it within 1 s and left the car at rest with
    its nose in the crossing lane, where the crossing car hit it."""
    plant, sup, body = car(6.0)
    plant.reset(np.array([50.4, 0.0, 0.0, 6.0, 0.0, 0.0]))
    crossing = ObstacleState("crossing_car", Box(4.5, 1.9), np.array([60.0, -13.25]), np.pi / 2,
                             np.array([0.0, 5.0]), 0.0)
    least, impact = np.inf, None
    for k in range(int(6.0 / DT)):
        t = k * DT
        now = ObstacleState(crossing.id, crossing.shape, crossing.center_at(t), crossing.yaw, crossing.velocity, t)
        v = sup.filter(plant.state, np.array([0.0, 0.0]), [now], t)
        plant.step(v.command, DT)
        gap = body.clearance(crossing.shape, crossing.center_at(t + DT), crossing.yaw, plant.position(), plant.heading())
        if gap <= 0.0 and impact is None:
            impact = float(np.hypot(*plant.velocity_world()))
        least = min(least, gap)
    assert impact is None and least > 0.0


@pytest.mark.parametrize("y0", [-12.0, -10.0])
def test_a_car_braking_into_a_crossing_cars_way_is_made_to_go_on_out_of_it(y0):
    # A controller that brakes hard at 6 m/s with a car crossing 6 m ahead from the right at 4.7 m/s:
    # the stop ends with the bumper in the crossing car's lane (x 5.05..6.95) before it arrives. The
    # stop was judged on its own (the command "held" brought the car to rest and was not checked
    # standing there), and the crossing car behind the body's middle did not count: the braking went
    # through and the crossing car hit the car at rest. Going on at a_max clears its lane first.
    plant, sup, body = car(6.0)
    crossing = obstacle("crossing", Box(1.9, 4.5), [6.0, y0], velocity=(0.0, 4.7))
    least, impact, interventions = drive(plant, sup, body, [crossing], [-6.0, 0.0], 5.0, moving=True)
    assert impact is None and least > 0.1
    assert interventions >= 1 and plant.position()[0] > 6.95 + 2.0    # past its lane, not stopped in it



def test_a_car_that_passes_and_steers_back_in_well_ahead_is_left_alone():
    """A car at 8 m/s in the next lane (y = 3.5) has passed a car at 6 m/s, its rear bumper 6 m ahead
    of that car's front, and steers back into the lane: the turn keeps clear, and neither the stop
    nor going on sees a reason to step in (the slower car behind the body's middle does not count
    in the stop; ``config/scenarios/safety/cut_in.toml`` is the case where that is a blind spot)."""
    plant, sup, body = car(8.0, y=3.5)
    rear = -float(body.outline[:, 0].min())                     # the reference point's distance to the rear bumper
    slow = obstacle("slow_car", Box(4.5, 1.9), [-rear - 6.0 - 2.25, 0.0], velocity=(6.0, 0.0))
    least, impact, n = drive(plant, sup, body, [slow], [0.0, -0.12], 1.5, moving=True)
    assert impact is None and n == 0 and plant.position()[1] < 2.5    # back towards its lane, untouched
