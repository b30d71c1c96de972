"""The timed reference: sampling a part of its series gives the same numbers as sampling all; its
curvature is a path's bend, not its point-to-point zig-zag."""

import numpy as np

from vflpcd.core.guidance.speed import CURVATURE_WINDOW, menger_curvature, windowed_curvature
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


def _arc(radius: float, length: float, h: float, zigzag: float = 0.0, sign: float = 1.0) -> np.ndarray:
    """Points every h m along a circle of ``radius`` turning left (sign 1) or right (-1), every
    other point moved ``zigzag`` m outwards."""
    a = np.arange(0.0, length, h) / radius
    r = radius + zigzag * (np.arange(len(a)) % 2)
    return np.column_stack([r * np.sin(a), sign * (radius - r * np.cos(a))])


def test_the_references_curvature_ignores_a_millimetre_zig_zag():
    """A 24 m bend resampled every 0.25 m whose every other point lies 1 mm out: the three-point
    curvature swings from point to point by more than the bend's own curvature, the reference's
    (and its yaw rate) stays within 3 % of 1 / 24 m, signed by the turn."""
    for sign in (1.0, -1.0):
        xy = _arc(24.0, 30.0, 0.25, zigzag=1e-3, sign=sign)
        s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        three = menger_curvature(xy)[2:-2]
        assert np.ptp(three) > 1.0 / 24.0
        traj = timed_trajectory(xy, s, np.full(len(s), 6.0), 0.0, 0.05)
        inner = (traj.s > 1.0) & (traj.s < s[-1] - 1.0)
        assert np.allclose(traj.kappa[inner], sign / 24.0, rtol=0.03)
        assert np.allclose(traj.omega[inner], sign * 6.0 / 24.0, rtol=0.03)


def test_windowed_curvature_of_a_straight_and_of_too_few_points():
    s = np.linspace(0.0, 10.0, 41)
    assert np.all(windowed_curvature(np.full(41, 0.3), s, CURVATURE_WINDOW) == 0.0)
    assert windowed_curvature(np.array([0.1]), np.array([0.0]), CURVATURE_WINDOW).shape == (1,)
