"""Static obstacles' local grids are computed once and found again at the next replans."""

import numpy as np

from vflpcd.config.scenarios import default_guidance
from vflpcd.core.guidance.planner import GuidancePlanner
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Box, Circle


def _static(oid, shape, x, y, stamp):
    return ObstacleState(id=oid, shape=shape, center=np.array([x, y]), yaw=0.2, velocity=np.zeros(2), stamp=stamp)


def test_a_restamped_static_obstacle_finds_its_grid_and_a_moved_one_does_not():
    planner = GuidancePlanner(ReferencePath.line([0.0, 0.0], [60.0, 0.0]), default_guidance(), 6.0, 3.0, 1.0, 0.05)
    first = planner.prepare(0.0, [_static("car", Box(4.5, 1.9), 25.0, 2.5, 0.0), _static("cone", Circle(0.3), 40.0, -2.0, 0.0)])
    again = planner.prepare(0.0, [_static("car", Box(4.5, 1.9), 25.0, 2.5, 7.5), _static("cone", Circle(0.3), 40.0, -2.0, 7.5)])
    moved = planner.prepare(0.0, [_static("car", Box(4.5, 1.9), 25.0, 2.6, 7.5), _static("cone", Circle(0.3), 40.0, -2.0, 9.0)])
    assert all(a is b for a, b in zip(first.grid.obstacles, again.grid.obstacles))      # perception restamps statics
    assert moved.grid.obstacles[0] is not first.grid.obstacles[0] and moved.grid.obstacles[1] is first.grid.obstacles[1]
    assert not np.array_equal(moved.grid.obstacles[0].origin, first.grid.obstacles[0].origin)
    assert not first.grid.obstacles[0].data.flags.writeable                            # shared: read only


def test_the_grid_cache_keeps_within_its_byte_budget(monkeypatch):
    """Obstacles beyond the budget push the least recently used grids out; the newest stays."""
    import vflpcd.core.guidance.grid as grid

    planner = GuidancePlanner(ReferencePath.line([0.0, 0.0], [60.0, 0.0]), default_guidance(), 6.0, 3.0, 1.0, 0.05)
    one = planner.prepare(0.0, [_static("cone0", Circle(0.3), 10.0, -3.0, 0.0)]).grid.obstacles[0].data.nbytes
    monkeypatch.setattr(grid, "LOCAL_GRID_BYTES", 3 * one)
    monkeypatch.setattr(grid, "_local_grids", type(grid._local_grids)())
    for i in range(8):
        planner.prepare(0.0, [_static(f"cone{i}", Circle(0.3), 5.0 + 5.0 * i, -3.0, 0.0)])
        assert sum(g.data.nbytes for g in grid._local_grids.values()) <= 3 * one
    assert len(grid._local_grids) == 3
    last = planner.prepare(0.0, [_static("cone7", Circle(0.3), 40.0, -3.0, 1.0)]).grid.obstacles[0]
    assert last is list(grid._local_grids.values())[-1]
