"""The window frame's heading unwrap: np.unwrap's numbers, with and without jumps."""

import numpy as np
import pytest

from vflpcd.core.dynamics.lifted import PoseLayout, to_window_frame, unwrap_angles

NAMES = ("X", "Y", "psi", "vx", "vy", "omega")


@pytest.mark.parametrize("scale", [0.1, 1.0, 3.0, 10.0])
def test_unwrap_angles_gives_np_unwraps_numbers(scale):
    rng = np.random.default_rng(1)
    for _ in range(200):
        a = rng.normal(size=(3, 21)) * scale
        a[0, 0], a[1, 4] = -0.0, -0.0
        mine, ref = unwrap_angles(a), np.unwrap(a, axis=-1)
        assert np.array_equal(mine, ref) and np.array_equal(np.signbit(mine), np.signbit(ref))
    a = np.array([3.1, -3.1, 3.0])
    assert np.array_equal(unwrap_angles(a), np.unwrap(a)) and unwrap_angles(a) is not a


def test_the_window_heading_is_np_unwraps_from_the_first_and_a_given_layout_changes_nothing():
    w = np.random.default_rng(2).normal(size=(21, 6)) * [5.0, 5.0, 3.0, 1.0, 1.0, 1.0]
    psi = np.unwrap(w[:, 2])
    assert np.array_equal(to_window_frame(w, NAMES)[:, 2], psi - psi[0])
    assert np.array_equal(to_window_frame(w, NAMES, PoseLayout.of(NAMES)), to_window_frame(w, NAMES))


@pytest.mark.parametrize("names", [("X", "Y", "Z", "vx", "vy", "vz"), ("vx", "X", "vy", "Y")])
def test_a_position_window_is_relative_to_its_first_position(names):
    w = np.random.default_rng(3).normal(size=(21, len(names)))
    p = [names.index(n) for n in ("X", "Y", "Z") if n in names]
    expected = w.copy()
    expected[:, p] = w[:, p] - w[:1, p]
    assert np.array_equal(to_window_frame(w, names), expected)
