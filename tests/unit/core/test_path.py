import importlib.util

import numpy as np
import pytest

from vflpcd.core.guidance.speed import menger_curvature
from vflpcd.core.path import (ReferencePath, feet_arc_lengths, feet_on_polyline, nearest_on_polyline, progress_delta,
                              unit_differences)


def test_arc_curvature_and_length():
    p = ReferencePath.arc([1.0, 2.0], 10.0, 0.0, np.pi)
    assert p.length == pytest.approx(10 * np.pi, rel=1e-4)
    assert p.curvature == pytest.approx(np.full(len(p.s), 0.1), rel=1e-3)
    cw = ReferencePath.arc([0.0, 0.0], 10.0, np.pi, 0.0)
    assert cw.curvature == pytest.approx(np.full(len(cw.s), -0.1), rel=1e-3)


def test_full_circle_is_closed_and_wraps():
    p = ReferencePath.arc([0.0, 0.0], 5.0, 0.0, 2 * np.pi)
    assert p.closed
    assert p.point_at(p.length + 1.0) == pytest.approx(p.point_at(1.0))
    assert progress_delta(p, 0.5, p.length - 0.5) == pytest.approx(1.0)


def test_projection_on_a_line_uses_the_paper_sign():
    p = ReferencePath.line([0.0, 0.0], [10.0, 0.0])
    left = p.project([4.0, 1.5])
    assert left.s == pytest.approx(4.0) and left.lateral == pytest.approx(-1.5)
    right = p.project([4.0, -1.0])
    assert right.lateral == pytest.approx(1.0) and right.heading == pytest.approx(0.0)


def test_projection_window_keeps_progress_on_a_hairpin():
    # out along y = 0, back along y = 3: a point at y = 1.4 is nearest to the outbound leg
    wp = np.array([[0, 0], [20, 0], [23, 1.5], [20, 3], [0, 3]], float)
    p = ReferencePath.from_waypoints(wp)
    near_return = p.project([5.0, 1.6])
    assert near_return.s > 25.0  # globally the return leg is nearer
    windowed = p.project([5.0, 1.6], s_hint=4.0, back=5.0, ahead=5.0)
    assert windowed.s == pytest.approx(5.0, abs=0.2)


def test_waypoint_spline_passes_through_waypoints_and_3d_lateral_is_distance():
    wp = np.array([[0, 0, 2], [12, 2, 2.5], [24, -1, 3], [36, 0, 3]], float)
    p = ReferencePath.from_waypoints(wp, ds=0.05)
    for w in wp:
        assert p.project(w).lateral == pytest.approx(0.0, abs=2e-3)
    off = p.project(wp[1] + [0, 0, 1.0])
    assert off.lateral == pytest.approx(1.0, abs=0.02)


def test_bad_points_raise():
    with pytest.raises(ValueError):
        ReferencePath(np.array([[0.0, 0.0]]))
    with pytest.raises(ValueError):
        ReferencePath(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(ValueError):
        ReferencePath.from_waypoints(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 1.0]]))


@pytest.mark.parametrize("closed", [False, True])
def test_arc_length_of_is_the_projections_arc_length(closed):
    path = ReferencePath.arc([0.0, 0.0], 20.0, 0.0, 2 * np.pi if closed else np.pi)
    rng = np.random.default_rng(0)
    for s_hint in (None, *rng.uniform(0.0, path.length, 20)):
        p = path.point_at(rng.uniform(0.0, path.length)) + rng.normal(size=2)
        assert path.arc_length_of(p, s_hint) == path.project(p, s_hint).s


@pytest.mark.parametrize("closed", [False, True])
def test_the_nearest_segment_loop_gives_the_numpy_searchs_arc_length(closed):
    """path_kernel.nearest_arc_length, run as Python and compiled, finds the numpy search's arc length
    on planar paths (the same numbers: within 1e-12 required, equal found), with windows across a
    closed path's seam, beyond an open path's ends and longer than the path."""
    from vflpcd.core.path_kernel import nearest_arc_length

    loops = [nearest_arc_length]
    if importlib.util.find_spec("numba") is not None:
        from vflpcd.controllers.loops import path_loop

        loops.append(path_loop())
    rng = np.random.default_rng(5)
    wp = np.cumsum(rng.uniform(2.0, 6.0, size=(12, 2)) * [1.0, 0.5], axis=0) * [1.0, rng.choice([-1, 1])]
    path = ReferencePath.from_waypoints(wp if not closed else np.vstack([wp, wp[::-1][1:-1] + [0.0, 8.0]]),
                                        closed=closed)
    for _ in range(200):
        s_hint = rng.choice([None, rng.uniform(-20.0, path.length + 20.0), rng.choice([0.0, path.length])])
        back, ahead = rng.choice([(10.0, 30.0), (1.0, 2.0), (0.0, 0.0), (path.length, 5.0)])
        p = path.point_at(rng.uniform(0.0, path.length)) + rng.normal(size=2) * rng.choice([0.01, 1.0, 10.0])
        expected = path.arc_length_of(p, s_hint, back, ahead)
        for loop in loops:
            got = path.arc_length_of(p, s_hint, back, ahead, loop=loop)
            assert abs(got - expected) <= 1e-12 and got == expected
    assert path.arc_length_of(path.points[3], None, loop=nearest_arc_length) == path.project(path.points[3]).s


def test_on_a_3d_path_the_nearest_segment_loop_gives_the_numpy_searchs_arc_length_to_1e_12():
    from vflpcd.core.path_kernel import nearest_arc_length

    loops = [nearest_arc_length]
    if importlib.util.find_spec("numba") is not None:
        from vflpcd.controllers.loops import path_loop

        loops.append(path_loop())
    rng = np.random.default_rng(6)
    path = ReferencePath.from_waypoints(np.cumsum(rng.uniform(1.0, 5.0, size=(15, 3)) * [1.0, 0.6, 0.3], axis=0))
    for _ in range(60):
        s_hint = rng.choice([None, rng.uniform(0.0, path.length)])
        p = path.point_at(rng.uniform(0.0, path.length)) + rng.normal(size=3) * rng.choice([0.01, 1.0, 10.0])
        expected = path.arc_length_of(p, s_hint)
        for loop in loops:
            assert abs(path.arc_length_of(p, s_hint, loop=loop) - expected) <= 1e-12


@pytest.mark.parametrize("d", [2, 3])
def test_the_polyline_loop_finds_the_numpy_searchs_segment_and_distance(d):
    """path_kernel.polyline_nearest, run as Python and compiled, gives nearest_on_polyline's segment
    and distance (the safety guard's plan monitor): planar the same numbers, in 3-D to 1e-12; with
    repeated vertices (zero-length segments) and points beyond the ends."""
    from vflpcd.core.path_kernel import polyline_nearest

    loops = [polyline_nearest]
    if importlib.util.find_spec("numba") is not None:
        from vflpcd.controllers.loops import polyline_loop

        loops.append(polyline_loop())
    rng = np.random.default_rng(8 + d)
    for trial in range(300):
        xy = np.cumsum(rng.normal(0.0, 2.0, size=(int(rng.integers(2, 60)), d)), axis=0)
        if trial % 10 == 0:
            xy[len(xy) // 2] = xy[len(xy) // 2 - 1]
        p = xy[rng.integers(len(xy))] + rng.normal(size=d) * rng.choice([0.01, 1.0, 30.0])
        distance, i = nearest_on_polyline(p, xy)
        for loop in loops:
            got, j = nearest_on_polyline(p, xy, loop)
            assert j == i and abs(got - distance) <= 1e-12
            assert d == 3 or got == distance


@pytest.mark.parametrize("back, ahead", [(10.0, 30.0), (0.0, 5.0), (3.0, 0.0), (60.0, 40.0)])
def test_a_closed_paths_search_window_holds_every_segment_that_overlaps_it(back, ahead):
    """On a closed path the searched segments (by the sorted arc lengths, across the seam too) are
    those whose [s_i, s_i+1] meets [hint - back, hint + ahead] modulo the length (a segment that
    touches an end within 1e-9 m may count), in increasing order, for hints on and off vertices."""
    path = ReferencePath.arc([0.0, 0.0], 20.0, 0.0, 2 * np.pi)
    L, starts, ends = path.length, path.s[:-1], path.s[1:]
    rng = np.random.default_rng(2)
    for hint in (*rng.uniform(-30.0, L + 30.0, 300), *path.s, *(path.s + back), *(path.s - ahead)):
        idx = np.asarray(path._searched(hint, back, ahead))
        assert np.all(np.diff(idx) > 0)
        lo = (hint - back) % L
        rel_start, rel_end = (starts - lo) % L, (ends - lo) % L
        span = back + ahead
        overlaps = (rel_start <= span) | (rel_end <= span) | (rel_end < rel_start)
        near_end = np.minimum.reduce([np.abs(rel_start - span), np.abs(rel_end - span), np.minimum(rel_end, L - rel_end),
                                      np.minimum(rel_start, L - rel_start)]) < 1e-8
        assert set(np.flatnonzero(overlaps)) <= set(idx)
        assert set(idx) <= set(np.flatnonzero(overlaps | near_end))


def test_unit_differences_are_np_gradients_directions():
    def directions(p):
        g = np.gradient(p, axis=0)
        return g / np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)

    pts = np.cumsum(np.random.default_rng(3).normal(size=(21, 3)), axis=0)
    pts[5:7] = pts[4]                                       # a standstill: a zero direction, no NaN
    assert np.array_equal(unit_differences(pts), directions(pts)) and not unit_differences(pts)[5].any()
    assert np.array_equal(unit_differences(pts[:2]), directions(pts[:2]))


def test_anchors_lie_on_the_path_and_bend_as_it_does():
    """Points 1.5 m outside a 24 m arc: their feet on the 0.5 m chords bend only at the chords'
    vertices (their three-point curvature swings by a half of the bend's), the anchors lie on the
    path (within 1 mm) and bend by the arc's curvature at every point (within 5 %)."""
    path = ReferencePath.arc([0.0, 24.0], 24.0, -np.pi / 2, 0.5, ds=0.1)
    a = np.linspace(-np.pi / 2 + 0.1, 0.3, 120)
    pts = np.column_stack([25.5 * np.cos(a), 24.0 + 25.5 * np.sin(a)])
    chords = path.point_at(np.arange(0.0, path.length, 0.5))
    k_feet = menger_curvature(feet_on_polyline(pts, chords))
    assert np.ptp(k_feet) > 0.5 / 24.0
    anchors = path.anchors(pts, 0.0, path.length)
    assert np.all(np.abs(np.hypot(anchors[:, 0], anchors[:, 1] - 24.0) - 24.0) < 1e-3)
    assert np.allclose(menger_curvature(anchors)[1:-1], 1.0 / 24.0, rtol=0.05)
    s = feet_arc_lengths(pts, chords, np.arange(0.0, path.length, 0.5))
    assert np.allclose(path.point_at(s), anchors)


def test_a_run_on_continues_the_end_tangent_and_keeps_the_path_before_it():
    bend = ReferencePath.arc([0.0, 0.0], 10.0, 0.0, np.pi / 2)
    longer = bend.run_on(5.0)
    assert not longer.closed and longer.length == pytest.approx(bend.length + 5.0, abs=1e-9)
    np.testing.assert_array_equal(longer.points[: len(bend.points)], bend.points)
    np.testing.assert_allclose(longer.s[: len(bend.s)], bend.s, atol=1e-12)
    end, tangent = bend.points[-1], bend.tangents[-1]
    beyond = longer.points[len(bend.points):]
    rel = beyond - end
    np.testing.assert_allclose(rel[:, 0] * tangent[1] - rel[:, 1] * tangent[0], 0.0, atol=1e-12)   # on the end tangent
    assert longer.point_at(longer.length) == pytest.approx(end + 5.0 * tangent, abs=1e-9)
    assert longer.curvature_at(bend.length + 2.5) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("length", [0.0, -1.0, float("nan")])
def test_a_run_on_is_a_positive_length_from_an_open_path(length):
    with pytest.raises(ValueError, match="positive length"):
        ReferencePath.line([0.0, 0.0], [3.0, 0.0]).run_on(length)
    with pytest.raises(ValueError, match="closed path"):
        ReferencePath.arc([0.0, 0.0], 5.0, 0.0, 2 * np.pi).run_on(1.0)
