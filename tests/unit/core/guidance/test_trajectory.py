"""The timed reference: sampling a part of its series gives the same numbers as sampling all."""

import numpy as np

from vflpcd.core.guidance.trajectory import SERIES, timed_trajectory


def test_sampling_some_series_gives_those_of_sampling_all():
    s = np.linspace(0.0, 30.0, 301)
    xy = np.column_stack([s, 2.0 * np.sin(s / 5.0)])
    traj = timed_trajectory(xy, s, np.full(len(s), 5.0), 2.0, 0.05)
    t = 2.0 + np.linspace(-1.0, traj.duration + 1.0, 50)          # before, inside and after the plan
    every = traj.sample(t)
    assert tuple(every) == SERIES
    for names in (("psi", "v", "omega", "pos"), ("v", "pos"), ("accel",)):
        part = traj.sample(t, names)
        assert tuple(part) == names and all(np.array_equal(part[n], every[n]) for n in names)
    assert every["v"][-1] == 0.0 and every["psi"][-1] == traj.psi[-1]
