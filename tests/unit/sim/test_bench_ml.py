"""The model-uncertainty bench's own measures: where lap 2 starts, and a second of chatter."""

from types import SimpleNamespace

import numpy as np

from sim.bench.ml import chatter_seconds, lap_two


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
