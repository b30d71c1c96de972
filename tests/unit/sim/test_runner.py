"""The offline closed loop on small scenarios whose outcome is known in advance."""

import numpy as np
import pytest

from vflpcd.controllers import make_controller
from sim.runner import run_closed_loop
from vflpcd.config.scenarios import load_scenario
from vflpcd.core.ports import ControllerBase

CORRIDOR_OBSTACLES = """
[[obstacles]]
id = "block"
shape = "box"
length = 1.0
width = 1.0
center = [15.0, 0.0]
[[obstacles]]
id = "aside"
shape = "circle"
radius = 0.5
center = [20.0, 4.0]
"""


def corridor(line_scenario):
    return line_scenario("corridor", length=30.0, speed=3.0, a_lat_max=2.0, t_max=30.0, obstacles=CORRIDOR_OBSTACLES)


def test_without_the_supervisor_pure_pursuit_hits_the_block_and_the_outcome_says_collision(line_scenario):
    s = corridor(line_scenario)
    rec = run_closed_loop(s, make_controller("pure_pursuit", s), supervised=False)
    m = rec.metrics
    assert rec.outcome == "collision" and m["outcome"] == "collision"      # it reached the goal, through the block
    assert m["impact_speed"] == pytest.approx(3.0, abs=0.05) and m["interventions"] == 0
    assert m["t_com"] == pytest.approx(29.0 / 3.0, abs=0.06)        # constant 3 m/s to the finish line
    assert m["L_p"] == pytest.approx(29.0, abs=0.2)
    assert m["collisions"] == 1                                       # drives straight through the block
    # the car runs over the centred 1 m block: the shortest push out is sideways, 0.95 + 0.5
    assert m["min_clearance_per_obstacle"][0] == pytest.approx(-1.45, abs=0.01)
    # passing 4 m beside a 0.5 m post with a 1.9 m wide body: 4 - 0.5 - 0.95
    assert m["min_clearance_per_obstacle"][1] == pytest.approx(4.0 - 0.5 - 0.95, abs=0.01)
    assert m["rms_lateral_error"] < 1e-9 and m["J_MC"] < 1e-6
    assert rec.t_cal.shape == rec.t.shape and np.all(rec.t_cal > 0)


def test_behind_the_supervisor_pure_pursuit_stops_before_the_block(line_scenario):
    s = corridor(line_scenario)
    rec = run_closed_loop(s, make_controller("pure_pursuit", s))
    m = rec.metrics
    assert rec.outcome == "stopped" and rec.failsafe.startswith("blocked: held at rest by the safety supervisor")
    assert m["collisions"] == 0 and m["impact_speed"] is None and m["interventions"] >= 1
    gap = m["min_clearance_per_obstacle"][0]
    assert 0.0 < gap < 1.5                                                 # in front of it, not far from it
    assert np.linalg.norm(rec.velocity[-1]) < 0.05
    assert np.all(rec.sent[rec.override > 0, 0] == -6.0)                   # overrides brake fully
    assert 0 < m["t_sup_median"] < 0.01


class RaisingController(ControllerBase):
    name = "raising"

    def reset(self):
        pass

    def step(self, state, t, obstacles=()):
        if t >= 1.0:
            raise RuntimeError("broken")
        return np.zeros(2)


def test_a_controller_that_raises_is_a_failsafe_that_brakes_to_rest(line_scenario):
    rec = run_closed_loop(corridor(line_scenario), RaisingController())
    assert rec.outcome == "failsafe" and rec.failsafe == "controller_error: RuntimeError: broken"
    assert np.linalg.norm(rec.velocity[-1]) < 0.05 and rec.t[-1] < 1.0 + 3.0 / 6.0 + 1.0
    bare = run_closed_loop(corridor(line_scenario), RaisingController(), supervised=False)
    assert bare.outcome == "error" and bare.failsafe == "controller_error: RuntimeError: broken"
    assert bare.t[-1] == pytest.approx(1.0)


class NaNController(ControllerBase):
    name = "nan"

    def reset(self):
        pass

    def step(self, state, t, obstacles=()):
        return np.array([np.nan, 0.0]) if t >= 1.0 else np.zeros(2)


def test_a_non_finite_command_ends_the_run_as_diverged(line_scenario):
    rec = run_closed_loop(corridor(line_scenario), NaNController())
    assert rec.outcome == "diverged"
    assert rec.t[-1] == pytest.approx(1.0)
    assert np.all(np.isfinite(rec.state))


def test_pd_tracker_flies_the_uav_path_into_obstacles_without_the_supervisor_and_stops_behind_it():
    s = load_scenario("uav_3d")
    rec = run_closed_loop(s, make_controller("pd_tracker", s), supervised=False)
    assert rec.outcome == "collision"
    assert rec.metrics["rms_lateral_error"] < 0.1
    # it does not avoid anything, so it flies into obstacles on the path: the count must say so
    assert rec.metrics["collisions"] >= 1
    rec = run_closed_loop(s, make_controller("pd_tracker", s))
    assert rec.metrics["collisions"] == 0 and rec.outcome == "stopped" and rec.metrics["interventions"] >= 1


def test_racing_track_lap_with_process_noise_is_seeded():
    s = load_scenario("racing_track")
    from dataclasses import replace
    s = replace(s, params="exact", process_noise=True, t_max=10.0)
    a = run_closed_loop(s, make_controller("pure_pursuit", s), seed=3)
    b = run_closed_loop(s, make_controller("pure_pursuit", s), seed=3)
    c = run_closed_loop(s, make_controller("pure_pursuit", s), seed=4)
    assert np.array_equal(a.state, b.state)
    assert not np.array_equal(a.state, c.state)


def test_footprint_clearance_is_exact_for_a_rectangle():
    from vflpcd.core.footprint import Footprint
    from vflpcd.core.shapes import Box, Circle

    fp = Footprint.rectangle(4.0, 2.0, 1.0)  # body x in [-1, 3], y in [-1, 1]
    assert fp.clearance(Circle(0.5), np.array([5.0, 0.0]), 0.0, np.zeros(2), 0.0) == pytest.approx(1.5, abs=1e-3)
    assert fp.clearance(Circle(0.5), np.array([4.0, 2.0]), 0.0, np.zeros(2), 0.0) == pytest.approx(
        np.hypot(1.0, 1.0) - 0.5, abs=2e-3)                                   # nearest the corner (3, 1)
    assert fp.clearance(Circle(0.5), np.array([0.0, 3.0]), 0.0, np.zeros(2), np.pi / 2) == pytest.approx(-0.5, abs=1e-3)
    assert fp.clearance(Box(0.2, 0.2), np.array([1.0, 0.5]), 0.0, np.zeros(2), 0.0) == pytest.approx(-0.6)  # inside
    assert np.all(np.linalg.norm(fp.outline[:, None, :] - fp.offsets[None, :, None] * [1, 0], axis=2).min(axis=1)
                  <= fp.radius + 1e-12)                                          # the discs cover the body


@pytest.mark.parametrize("stop", [False, True])
def test_vflpc_passes_a_goal_on_a_road_that_goes_on_and_slows_for_one_that_is_a_stop(line_scenario, stop):
    s = line_scenario("goal", length=40.0, speed=5.0, t_max=30.0, stop=stop)
    rec = run_closed_loop(s, make_controller("vflpc", s))
    assert rec.outcome == "completed"
    speed = np.linalg.norm(rec.velocity, axis=1)
    ok = np.all(np.isfinite(rec.applied), axis=1)
    if stop:            # braking for the end of the road: well below the cruise speed at the goal
        assert speed[-1] < 0.7 * s.v_desired and rec.applied[ok, 0].min() < -1.0
    else:               # the same cruise to the goal, nothing braked for
        assert speed[-1] == pytest.approx(s.v_desired, abs=0.1) and rec.applied[ok, 0].min() > -0.3


class FreezeWatcher(ControllerBase):
    """Records how many objects the garbage collector holds frozen at each step."""

    name = "freeze_watcher"

    def __init__(self):
        self.frozen = []

    def reset(self):
        pass

    def step(self, state, t, obstacles=()):
        import gc

        self.frozen.append(gc.get_freeze_count())
        return np.zeros(2)


def test_the_objects_alive_before_a_run_are_kept_out_of_its_collections_and_given_back(line_scenario):
    """A bench's records of earlier runs are frozen while a run ticks (no full collection over them
    inside a timed tick or replan), and the collector is as it was after the run, also when the
    controller raises."""
    import gc

    held = [{"row": i} for i in range(2000)]            # an earlier run's records (tracked objects)
    before = gc.get_freeze_count()
    watcher = FreezeWatcher()
    run_closed_loop(corridor(line_scenario), watcher)
    assert len(watcher.frozen) > 10 and min(watcher.frozen) >= before + len(held)
    assert gc.get_freeze_count() == before
    run_closed_loop(corridor(line_scenario), RaisingController(), supervised=False)
    assert gc.get_freeze_count() == before and gc.isenabled()
