"""The composite and kinodynamic fields against the paper's definitions."""

import numpy as np
import pytest

from vflpcd.core.guidance.field import ActualTerm, GuidanceField, VirtualTerm
from vflpcd.core.guidance.implicit import (E, CirclePath, GraphPath, GuidanceError, LinePath,
                                          ObstacleImplicit, _inflated_boundary, _offset_radii, _sphere_directions)
from vflpcd.core.guidance.primitives import bump, cup_at, row_centre, s_virtual, superellipse_at, unit
from vflpcd.core.shapes import Box, Box3, Circle, Cylinder, Ellipse, Ellipsoid, Sphere

L1, L2 = 0.05, 0.05


def logistic_derivative(varphi, c):
    cup, _ = bump(varphi, c, L1, L2)
    dz = L1 / (c - varphi) ** 2 + L2 / varphi ** 2
    return cup * (1 - cup) * dz


def test_bumps_blend_to_one_and_switch_at_the_boundaries():
    c = -0.3
    v = np.linspace(-0.6, 0.3, 901)
    cup, cap = bump(v, c, L1, L2)
    assert np.allclose(cup + cap, 1.0)
    assert np.all(cup[v >= 0] == 1.0) and np.all(cap[v <= c] == 1.0)
    inside = (v > c + 0.05) & (v < -0.05)  # (nearer the edges the blend is flat to machine precision)
    assert np.all((cup[inside] > 0) & (cup[inside] < 1))
    assert np.all(np.diff(cup) >= 0)  # monotone in varphi


def test_bump_derivative_matches_finite_differences_and_vanishes_at_the_edges():
    c = -0.3
    v = np.linspace(c + 0.01, -0.01, 57)
    h = 1e-6
    fd = (bump(v + h, c, L1, L2)[0] - bump(v - h, c, L1, L2)[0]) / (2 * h)
    assert fd == pytest.approx(logistic_derivative(v, c), rel=1e-5, abs=1e-9)
    # flat to all orders at both boundaries: the derivative tends to 0 from inside
    assert logistic_derivative(np.array([-1e-3]), c)[0] < 1e-12
    assert logistic_derivative(np.array([c + 1e-3]), c)[0] < 1e-12


def test_s_virtual_follows_eq_S_xi():
    c = -0.4
    v = np.array([-0.5, -0.3, -0.1, 0.2])
    s = s_virtual(v, c, 0.05, np.array([True, True, True, False]))
    assert s[0] == 0.0 and s[3] == 1.0
    assert s[1] == pytest.approx(np.exp(0.05 / (c + 0.3))) and s[2] == pytest.approx(np.exp(0.05 / (c + 0.1)))
    assert 0 < s[1] < s[2] < 1


@pytest.mark.parametrize("implicit", [
    LinePath(np.array([1.0, 2.0]), np.array([0.6, 0.8])),
    CirclePath(np.array([0.5, -1.0]), 3.0),
    GraphPath(np.array([1.0, 1.0]), 0.4, np.array([0.0, 5.0, 10.0, 20.0]), np.array([0.0, 1.0, -1.0, 0.5])),
])
def test_path_gradients_match_finite_differences(implicit):
    rng = np.random.default_rng(1)
    p = rng.uniform(-8, 8, (50, 2))
    _, g = implicit.value_grad(p)
    h = 1e-6
    for j in range(2):
        dp = np.zeros(2)
        dp[j] = h
        fd = (implicit.value_grad(p + dp)[0] - implicit.value_grad(p - dp)[0]) / (2 * h)
        assert fd == pytest.approx(g[:, j], rel=1e-5, abs=1e-6)


SHAPES = [Circle(1.0), Ellipse(2.0, 0.6), Box(4.6, 1.9), Sphere(0.8), Ellipsoid(1.5, 0.8, 1.0),
          Cylinder(0.5, 6.0), Box3(2.0, 1.0, 3.0)]


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: s.kind)
def test_obstacle_boundaries_enclose_the_grown_shape(shape):
    d = shape.dim
    o = ObstacleImplicit.around("o", shape, np.full(d, 2.0), 0.4, np.zeros(d), 0.0,
                                reactive_distance=3.0, repulsive_distance=1.5)
    rng = np.random.default_rng(2)
    pts = rng.uniform(-8, 12, (60000, d))
    sd = shape.signed_distance(pts, np.full(d, 2.0), 0.4)
    phi, g = o.value_grad(pts)
    assert np.all(phi[sd <= 1.5] <= o.c)          # Q encloses the shape grown by the repulsive distance
    assert np.all(phi[sd <= 3.0] <= 0.0)          # R encloses the shape grown by the reactive distance
    assert np.min(sd[phi > 0.0]) > 3.0 - 1e-9 and np.percentile(sd[phi > 0.0], 1) < 3.6  # and is not loose
    h = 1e-6
    for j in range(d):
        dp = np.zeros(d)
        dp[j] = h
        fd = (o.value(pts[:200] + dp) - o.value(pts[:200] - dp)) / (2 * h)
        assert fd == pytest.approx(g[:200, j], rel=1e-5, abs=1e-7)


@pytest.mark.parametrize("shape", SHAPES, ids=lambda s: s.kind)
def test_inflated_boundary_points_lie_on_the_outer_side_within_the_tolerance(shape):
    pts = _inflated_boundary(shape, 1.5, 200)
    off = shape.signed_distance(pts, np.zeros(shape.dim)) - 1.5
    assert off.min() >= 0.0 and off.max() <= 1e-12
    loose = _inflated_boundary(shape, 1.5, 200, tol=1e-6)
    off = shape.signed_distance(loose, np.zeros(shape.dim)) - 1.5
    assert off.min() >= 0.0 and off.max() <= 1e-6


@pytest.mark.parametrize("shape", [Circle(0.7), Box(4.5, 1.9), Box(0.5, 0.5), Ellipse(2.0, 1.0), Ellipse(0.4, 0.3)],
                         ids=["circle", "box", "square", "ellipse", "small ellipse"])
@pytest.mark.parametrize("distance", [0.1, 1.5, 3.0])
def test_offset_radii_meet_the_offset_curve_to_rounding(shape, distance):
    dirs = _sphere_directions(2, 720)
    radii = _offset_radii(shape, dirs, distance)
    off = shape.signed_distance(dirs * radii[:, None], np.zeros(2)) - distance
    assert np.abs(off).max() <= 1e-13
    pts = _inflated_boundary(shape, distance, 720)          # the search's contract holds, from them
    off = shape.signed_distance(pts, np.zeros(2)) - distance
    assert off.min() >= 0.0 and off.max() <= 1e-12


@pytest.mark.parametrize("error", [1e-6, 0.5])
def test_inflated_boundary_searches_from_offset_radii_that_miss(monkeypatch, error):
    """Radii off by 1e-6 m leave the search a bracket of +-OFFSET_BRACKET round them; by 0.5 m,
    outside it, the wide bracket. The contract holds either way."""
    import vflpcd.core.guidance.implicit as implicit

    exact = implicit._offset_radii
    monkeypatch.setattr(implicit, "_offset_radii", lambda shape, dirs, d: exact(shape, dirs, d) + error)
    shape = Ellipse(2.0, 1.0)
    pts = _inflated_boundary(shape, 1.5, 200)
    off = shape.signed_distance(pts, np.zeros(2)) - 1.5
    assert off.min() >= 0.0 and off.max() <= 1e-12


def test_offset_radii_leave_three_dimensional_shapes_to_the_wide_bracket():
    assert _offset_radii(Sphere(1.0), _sphere_directions(3, 50), 1.0) is None


def test_moving_obstacle_translates_with_time():
    o = ObstacleImplicit.around("m", Circle(1.0), np.array([0.0, 0.0]), 0.0, np.array([1.0, 0.5]), 2.0, 3.0, 1.5)
    assert o.value(np.array([[3.0, 1.5]]), t=5.0)[0] == pytest.approx(-1.0)   # the centre at t = 5
    assert o.value(np.array([[0.0, 0.0]]), t=2.0)[0] == pytest.approx(-1.0)


@pytest.mark.parametrize("p", [2.0, 3.5, 6.0])
def test_the_plain_float_value_gradient_and_bump_are_the_array_ones(p):
    """superellipse_at at an obstacle's row and cup_at (the compiled loops' per-step forms) against
    value_grad and bump, on a rotated, moving superellipse, to rounding."""
    o = ObstacleImplicit("o", np.array([1.0, 2.0]), 0.7, np.array([0.3, -0.2]), 0.5, np.array([2.0, 1.2]), p, None, -0.4)
    rng = np.random.default_rng(3)
    for x, y, t in zip(rng.normal(1.0, 2.0, 300), rng.normal(2.0, 2.0, 300), rng.uniform(0.0, 3.0, 300)):
        v, g = o.value_grad(np.array([[x, y]]), t)
        row = np.array([o.row()])
        at = superellipse_at(x, y, *row_centre(row, 0, t), *row[0, 6:11])
        np.testing.assert_allclose(at, [v[0], g[0, 0], g[0, 1]], rtol=1e-13, atol=1e-13)
        assert abs(cup_at(v[0], o.c, 0.3, 0.2) - bump(v, o.c, 0.3, 0.2)[0][0]) <= 1e-15


def test_obstacle_rejects_bad_coefficients():
    with pytest.raises(GuidanceError, match="c_i < 0"):
        ObstacleImplicit("bad", np.zeros(2), 0.0, np.zeros(2), 0.0, np.ones(2), 2.0, None, 0.1)
    with pytest.raises(GuidanceError, match="'x'.*axes"):
        ObstacleImplicit("x", np.zeros(2), 0.0, np.zeros(2), 0.0, np.array([1.0, np.nan]), 2.0, None, -0.2)
    with pytest.raises(GuidanceError, match="repulsive_distance"):
        ObstacleImplicit.around("y", Circle(1.0), np.zeros(2), 0.0, np.zeros(2), 0.0, 1.0, 2.0)


def make_field():
    path = LinePath(np.array([0.0, 0.0]), np.array([1.0, 0.0]))
    o1 = ObstacleImplicit.around("a", Circle(1.0), np.array([10.0, 0.5]), 0.0, np.zeros(2), 0.0, 3.0, 1.5)
    o2 = ObstacleImplicit.around("b", Box(3.0, 1.0), np.array([25.0, -1.0]), 0.3, np.zeros(2), 0.0, 3.0, 1.5)
    return GuidanceField(path=path, gamma0=-1.0, k_p=1.0, k_r=6.0, l1=L1, l2=L2, k_c=0.05,
                         statics=[ActualTerm(o1, 1.0, -1.0), ActualTerm(o2, -1.0, 1.0)])


def test_field_on_the_path_outside_reactive_regions_is_the_unit_tangent():
    f = make_field()
    x = np.linspace(-5, 40, 451)
    pts = np.column_stack([x, np.zeros_like(x)])
    outside = np.all([t.implicit.value(pts) > 0 for t in f.statics], axis=0)
    chi = f.kinodynamic(pts)
    assert outside.sum() > 100
    assert chi[outside] == pytest.approx(np.tile([1.0, 0.0], (outside.sum(), 1)), abs=1e-12)


def test_field_is_unit_norm_outside_R_and_inside_Q_and_normalisable_between():
    f = make_field()
    rng = np.random.default_rng(3)
    pts = rng.uniform([-5, -10], [40, 10], (20000, 2))
    chi = f.composite(pts)
    vals = np.array([t.implicit.value(pts) for t in f.statics])
    cs = np.array([[t.implicit.c] for t in f.statics])
    outside_all = np.all(vals > 0, axis=0)
    in_some_q = np.any(vals < cs, axis=0)
    n = np.linalg.norm(chi, axis=1)
    assert n[outside_all] == pytest.approx(1.0, abs=1e-12)
    assert n[in_some_q] == pytest.approx(1.0, abs=1e-12)
    u, norm = unit(chi)
    assert np.linalg.norm(u[norm > 1e-3], axis=1) == pytest.approx(1.0)


def test_inside_a_repulsive_region_the_field_is_the_repulsive_field():
    f = make_field()
    t = f.statics[0]
    o = t.implicit
    ang = np.linspace(0, 2 * np.pi, 100, endpoint=False)
    pts = o.center + 1.2 * np.column_stack([np.cos(ang), np.sin(ang)])   # radius 1.2 < repulsive 2.5
    assert np.all(o.value(pts) < o.c)
    phi, g = o.value_grad(pts)
    chi_r = t.gamma * g @ E.T - f.k_r * phi[:, None] * g
    assert f.composite(pts) == pytest.approx(chi_r / np.linalg.norm(chi_r, axis=1, keepdims=True), abs=1e-12)
    # and it pushes outwards (towards the reactive boundary), so Q is never crossed inwards
    assert np.all(np.einsum("ij,ij->i", f.composite(pts), g) > 0)


def test_virtual_obstacle_acts_only_in_its_buffer_region():
    f = make_field()
    parent = f.statics[0].implicit
    v = ObstacleImplicit("virtual:a", np.array([5.0, -4.0]), 0.0, np.zeros(2), 0.0, np.array([6.0, 6.0]), 2.0,
                         None, 4.0 / 6.0 - 1.0)
    f.virtuals = [VirtualTerm(v, 1.0, parent)]
    rng = np.random.default_rng(4)
    pts = rng.uniform([-5, -12], [20, 8], (5000, 2))
    with_v = f.kinodynamic(pts)
    without = f.kinodynamic(pts, enabled=np.array([False]))
    differs = np.any(np.abs(with_v - without) > 1e-12, axis=1)
    in_buffer = (v.value(pts) < 0) & np.all([t.implicit.value(pts) > 0 for t in f.statics], axis=0)
    assert differs.sum() > 100
    assert np.all(in_buffer[differs])  # never outside M_b
