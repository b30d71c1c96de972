"""The pursuer-evader region E_p on hand-worked cases, and the barrier against finite differences."""

import numpy as np
import pytest

from vflpcd.core.control.barrier import HorizonBarrier, safety_points
from vflpcd.core.control.game_region import bup_angle, evader_frame, in_region, threats
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.shapes import Box, Circle


def test_bup_angle():
    assert bup_angle(0.0, 5.0)[()] == pytest.approx(np.pi / 2)
    assert bup_angle(2.5, 5.0)[()] == pytest.approx(np.arccos(-0.5))      # 120 deg
    assert bup_angle(5.0, 5.0)[()] == pytest.approx(np.pi)
    assert bup_angle(9.0, 5.0)[()] == pytest.approx(np.pi)                 # faster pursuer: clipped
    assert bup_angle(1.0, 0.0)[()] == pytest.approx(np.pi)                 # evader at rest


# l = 2, l_safe = 8, s_bar = 120 deg: sin = 0.866, cos = -0.5, tan = -1.732, l / cos = -4.
# H1: X <= -1.732 and Y >= -1.732 X - 4;  H2: X >= 1.732 and Y >= 1.732 X - 4;  H3: |X| < 1.732, Y >= -sqrt(4 - X^2)
@pytest.mark.parametrize("zeta, inside", [
    ((0.0, 5.0), True),        # straight ahead (H3)
    ((0.0, -1.9), True),       # just above the lower terminal semicircle (H3)
    ((0.0, -2.1), False),      # below it
    ((1.0, -1.8), False),      # below the semicircle at X = 1 (-sqrt(3) = -1.732)
    ((1.0, -1.7), True),
    ((3.0, 1.3), True),        # H2: 1.732 * 3 - 4 = 1.196 <= 1.3
    ((3.0, 1.1), False),
    ((-3.0, 1.3), True),       # H1 mirrors H2
    ((-3.0, 1.1), False),
    ((0.0, 10.5), False),      # beyond l + l_safe = 10 (E_p1)
    ((6.0, 7.9), True),        # ||zeta|| = 9.92
    ((6.0, 8.1), False),       # ||zeta|| = 10.08
])
def test_region_hand_worked(zeta, inside):
    assert bool(in_region(np.array([zeta]), 2.0, 8.0, np.radians(120.0))[0]) is inside


def test_static_pursuer_region_is_the_swept_strip():
    s_bar = np.pi / 2                                   # v_p = 0
    assert in_region([[1.9, 5.0]], 2.0, 8.0, s_bar)[0]
    assert not in_region([[2.1, 5.0]], 2.0, 8.0, s_bar)[0]
    assert not in_region([[-2.1, 5.0]], 2.0, 8.0, s_bar)[0]


def test_evader_frame_and_threats():
    zeta = evader_frame(np.array([[0.0, 3.0], [3.0, 0.0]]), np.array([0.0, 2.0]))
    assert np.allclose(zeta, [[0.0, 3.0], [3.0, 0.0]])
    zeta = evader_frame(np.array([[5.0, 0.0, 1.0]]), np.array([1.0, 0.0, 0.0]))    # 3-D: off-axis distance
    assert np.allclose(zeta, [[1.0, 5.0]])
    # robot driving +x at 5 m/s: an obstacle ahead, one behind, one aside; a 1 m/s one 2.5 m off-axis (H2: 4 cos + 2.5 sin <= 2)
    mask = threats(np.zeros(2), np.array([5.0, 0.0]),
                   np.array([[6.0, 0.0], [-6.0, 0.0], [0.0, 9.0], [4.0, 2.5]]),
                   np.array([[0.0, 0.0], [0.0, 0.0], [0.0, 0.0], [0.0, -1.0]]), np.full(4, 2.0), 8.0)
    assert mask.tolist() == [True, False, False, True]


def test_barrier_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    T, n = 6, 7
    barrier = HorizonBarrier(pos_index=np.array([0, 1]), p_ref=rng.normal(size=(T, 2)),
                             x_p=rng.normal(size=(2, T, 2)),
                             normal=(lambda v: v / np.linalg.norm(v, axis=-1, keepdims=True))(rng.normal(size=(2, T, 2))),
                             mu=np.array([3.0, 0.5]), length=0.7)
    x = rng.normal(size=(T, n))
    grad = barrier.gradient(x)
    eps = 1e-6
    for j in range(n):
        e = np.zeros(n)
        e[j] = eps
        fd = (barrier.value(x + e) - barrier.value(x - e)) / (2 * eps)
        assert np.allclose(grad[:, j], fd, rtol=1e-6, atol=1e-8)
    assert np.all(grad[:, 2:] == 0.0)


def test_barrier_is_the_paper_norm_outside_and_pushes_out_inside():
    o = ObstacleState("c", Circle(1.0), np.array([0.0, 0.0]), 0.0, np.zeros(2), 0.0)
    pts = np.array([[4.0, 0.0], [1.5, 0.0]])
    x_p, normal = safety_points(o, pts, np.zeros(2), grow=1.0)          # safety circle radius 2
    assert np.allclose(x_p, [[2.0, 0.0], [2.0, 0.0]], atol=1e-6)
    assert np.allclose(normal, [[1.0, 0.0], [1.0, 0.0]], atol=1e-6)
    b = HorizonBarrier(np.array([0, 1]), pts, x_p[None], normal[None], np.array([1.0]))
    h = b.value(np.zeros((2, 2)))
    assert h[0] == pytest.approx(np.exp(-2.0))                          # mu exp(-||p - x_p||)
    assert h[1] > 1.0                                                    # inside: larger than at the boundary
    assert b.gradient(np.zeros((2, 2)))[1, 0] < 0                        # decreasing outwards


def test_safety_points_follow_a_moving_box():
    o = ObstacleState("car", Box(4.0, 2.0), np.array([0.0, 0.0]), 0.0, np.array([2.0, 0.0]), 0.0)
    x_p, normal = safety_points(o, np.array([[4.0, 5.0], [4.0, 5.0]]), np.array([0.0, 2.0]), grow=0.5)
    assert np.allclose(x_p[1], [4.0, 1.5], atol=1e-6) and np.allclose(normal[1], [0.0, 1.0], atol=1e-6)
    assert np.linalg.norm(x_p[0] - [2.0, 1.0]) == pytest.approx(0.5, abs=1e-6)   # corner region at t = 0


def test_bad_barrier_input_is_rejected():
    with pytest.raises(ValueError):
        HorizonBarrier(np.array([0, 1]), np.zeros((2, 2)), np.zeros((1, 2, 2)), np.zeros((1, 2, 2)), np.array([-1.0]))
    with pytest.raises(ValueError):
        HorizonBarrier(np.array([0, 1]), np.zeros((2, 2)), np.full((1, 2, 2), np.nan), np.zeros((1, 2, 2)), np.array([1.0]))
    for length in (0.0, np.nan):                        # a barrier without obstacles checks its length too
        with pytest.raises(ValueError):
            HorizonBarrier(np.array([0, 1]), np.zeros((2, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2)), np.zeros(0),
                           length)
    assert HorizonBarrier(np.array([0, 1]), np.zeros((2, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2)), np.zeros(0)).count == 0


def test_the_region_takes_scalar_or_per_pursuer_distances_alike():
    zeta = np.random.default_rng(4).uniform(-8.0, 8.0, size=(50, 2))
    for s_bar in (0.5 * np.pi, 0.7 * np.pi, np.pi):
        assert np.array_equal(in_region(zeta, 2.0, 3.0, s_bar), in_region(zeta, np.full(50, 2.0), 3.0, np.full(50, s_bar)))
