"""The model-uncertainty bench's own measures: where lap 2 starts, a second of chatter, and the
offset in left and right curves."""

from types import SimpleNamespace

import numpy as np
import pytest

from sim.bench.ml import chatter_seconds, curve_offsets, lap2_better, lap_two
from vflpcd.core.path import ReferencePath


def test_lap_two_starts_where_the_distance_driven_reaches_the_track_length():
    x = np.linspace(0.0, 30.0, 31)                   # 1 m per step along a line
    record = SimpleNamespace(position=np.column_stack([x, np.zeros_like(x)]))
    assert lap_two(record, 12.0).tolist() == list(range(12, 31))


def test_chatter_counts_the_seconds_in_which_both_limits_are_touched():
    t = np.arange(0.0, 4.0, 0.25)
    a = np.zeros_like(t)
    a[[1, 2]] = [-6.0, 3.0]                          # second 0: both limits
    a[[5]] = 3.0                                     # second 1: one limit only
    a[[12, 15]] = [3.0, -6.0]                        # second 3: both
    assert chatter_seconds(t, a, -6.0, 3.0) == 2


def test_curve_offsets_average_the_lateral_error_in_left_and_in_right_curves():
    # a straight, a left quarter circle of radius 20 m, a straight: the body 0.1 m off on the
    # straights, 0.3 m inside the left curve
    pts = [[x, 0.0] for x in np.arange(0.0, 20.0, 0.5)]
    pts += [[20.0 + 20.0 * np.sin(a), 20.0 - 20.0 * np.cos(a)] for a in np.linspace(0.0, np.pi / 2, 60)]
    pts += [[40.0, y] for y in np.arange(20.5, 40.0, 0.5)]
    path = ReferencePath.from_waypoints(np.array(pts))
    s = np.linspace(1.0, path.length - 1.0, 300)
    position = path.point_at(s)
    curved = np.abs(path.curvature_at(s)) > 0.02
    lateral = np.where(curved, 0.3, 0.1)
    record = SimpleNamespace(position=position, lateral=lateral)
    left, right = curve_offsets(SimpleNamespace(path=path), record, np.arange(len(s)))
    assert left == pytest.approx(0.3)
    assert np.isnan(right)


def test_a_run_that_never_drove_a_lap_two_is_never_the_better_one():
    """A run stopped before lap 2 has no lap-2 RMS (None): it is not better than a run that drove
    one, and a run that drove one is better than it (the bench used to crash comparing None)."""
    assert lap2_better(0.2, 0.1) and not lap2_better(0.1, 0.2)
    assert not lap2_better(0.2, None) and lap2_better(None, 0.3)
    assert not lap2_better(None, None)
