"""Tests for vflpcd.core.shapes: closed forms, brute-force ellipse/ellipsoid checks, API."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.spatial import cKDTree

from vflpcd.core.shapes import (
    SHAPES_2D,
    SHAPES_3D,
    Box,
    Box3,
    Circle,
    Cylinder,
    Ellipse,
    Ellipsoid,
    Sphere,
    shape_from_table,
)

SQ2, SQ3 = math.sqrt(2.0), math.sqrt(3.0)
ALL_SHAPES = [
    Circle(1.3), Ellipse(2.0, 0.7), Box(4.5, 1.9),
    Sphere(1.1), Ellipsoid(3.0, 2.0, 1.0), Box3(2.0, 1.0, 3.0), Cylinder(0.8, 2.5),
]


def _rot(yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s], [s, c]])


# --------------------------------------------------------------------------- closed forms
def test_circle_closed_form():
    c = np.array([1.0, -1.0])
    pts = c + np.array([[0.0, 0.0], [3.0, 0.0], [0.0, 1.0], [3.0, 4.0], [-1.2, 1.6]])
    np.testing.assert_allclose(Circle(2.0).signed_distance(pts, c, yaw=0.7), [-2.0, 1.0, -1.0, 3.0, 0.0], atol=1e-15)


def test_sphere_closed_form():
    c = np.array([1.0, -2.0, 0.5])
    pts = c + np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 4.0], [1.0, 2.0, 2.0], [0.5, 0.0, 0.0], [0.6, 0.0, 0.8]])
    np.testing.assert_allclose(Sphere(1.0).signed_distance(pts, c, yaw=-1.0), [-1.0, 3.0, 2.0, -0.5, 0.0], atol=1e-15)


def test_box_faces_edges_corners_inside():
    box, c = Box(4.0, 2.0), np.array([1.0, 2.0])  # half extents (2, 1)
    pts = c + np.array([
        [3.0, 0.0],    # 1 m beyond the +x face
        [0.5, -1.5],   # 0.5 m below the -y face
        [3.0, 2.0],    # diagonal off the corner (2, 1): sqrt(2)
        [-5.0, -5.0],  # corner (-2, -1): hypot(3, 4) = 5
        [0.0, 0.0],    # centre: nearest faces are +-y at 1 m
        [1.5, 0.0],    # 0.5 m inside the +x face
        [1.9, 0.95],   # near the corner: 0.05 from both faces
        [2.0, 0.3],    # on the face
    ])
    np.testing.assert_allclose(box.signed_distance(pts, c), [1.0, 0.5, SQ2, 5.0, -1.0, -0.5, -0.05, 0.0], atol=1e-12)


def test_box_yaw_rotation():
    rng = np.random.default_rng(1)
    c = np.array([0.3, -0.4])
    pts = rng.uniform(-4, 4, (500, 2))
    d_rot = Box(4.0, 2.0).signed_distance(pts, c, yaw=np.pi / 2)
    np.testing.assert_allclose(d_rot, Box(2.0, 4.0).signed_distance(pts, c), atol=1e-12)
    # A general yaw: rotating the points with the box leaves the distance unchanged.
    yaw = 0.83
    body = rng.uniform(-4, 4, (500, 2))
    world = body @ _rot(yaw).T + c
    np.testing.assert_allclose(Box(4.0, 2.0).signed_distance(world, c, yaw),
                               Box(4.0, 2.0).signed_distance(body, [0.0, 0.0]), atol=1e-12)
    # Corner of the rotated box, 1 m out along its diagonal.
    corner = _rot(yaw) @ np.array([2.0, 1.0]) + c
    out = corner + _rot(yaw) @ np.array([1.0, 1.0]) / SQ2
    assert Box(4.0, 2.0).signed_distance(out, c, yaw) == pytest.approx(1.0, abs=1e-12)


def test_box3_faces_edges_corners_inside_rotation():
    box, c = Box3(4.0, 2.0, 6.0), np.array([1.0, -1.0, 2.0])  # half extents (2, 1, 3)
    pts = c + np.array([
        [0.0, 0.0, 5.0],   # 2 m above the top face
        [3.0, 2.0, 0.0],   # off the vertical edge (2, 1, .): sqrt(2)
        [3.0, 2.0, 4.0],   # off the corner (2, 1, 3): sqrt(3)
        [0.0, 0.0, 0.0],   # centre: -1 (nearest faces +-y)
        [1.8, 0.0, 0.0],   # 0.2 m inside the +x face
        [0.0, 0.0, -2.9],  # 0.1 m inside the bottom face
    ])
    np.testing.assert_allclose(box.signed_distance(pts, c), [2.0, SQ2, SQ3, -1.0, -0.2, -0.1], atol=1e-12)
    rng = np.random.default_rng(2)
    q = rng.uniform(-5, 5, (500, 3))
    np.testing.assert_allclose(box.signed_distance(q, c, yaw=np.pi / 2),
                               Box3(2.0, 4.0, 6.0).signed_distance(q, c), atol=1e-12)


def test_cylinder_side_cap_rim_inside():
    cyl, c = Cylinder(1.0, 4.0), np.array([0.5, 0.5, 1.0])  # spans z in c_z + [-2, 2]
    pts = c + np.array([
        [3.0, 0.0, 0.0],   # radial side: 2
        [0.0, -1.5, 1.9],  # radial side beside the cap: 0.5
        [0.3, 0.4, 2.5],   # above the cap: 0.5
        [0.0, 0.0, -2.25], # below the bottom cap: 0.25
        [4.0, 0.0, 6.0],   # off the rim (1, 0, 2): hypot(3, 4) = 5
        [0.0, 0.0, 0.0],   # centre: -radius
        [0.0, 0.0, 1.8],   # 0.2 m under the cap
        [0.0, 0.9, 0.0],   # 0.1 m inside the side
        [0.6, 0.8, 2.0],   # on the rim
    ])
    expected = [2.0, 0.5, 0.5, 0.25, 5.0, -1.0, -0.2, -0.1, 0.0]
    np.testing.assert_allclose(cyl.signed_distance(pts, c), expected, atol=1e-12)
    np.testing.assert_allclose(cyl.signed_distance(pts, c, yaw=1.1), expected, atol=1e-12)


# --------------------------------------------------------------------------- ellipse / ellipsoid
def _local_refine(param, x0, p, spans, rounds=16, k=21):
    """Refine a nearest boundary point by repeated local grid search over the parameters.

    param: (N, K, m) -> (N, K, dim) boundary parametrisation; x0 (N, m) start; p (N, dim).
    Returns (N,) distances.  Each round takes the best of a k^m grid spanning +-spans around
    the current point, then shrinks the span to +-2 grid steps.
    """
    x0 = np.asarray(x0, dtype=float)
    spans = np.asarray(spans, dtype=float)
    offs = np.stack(np.meshgrid(*[np.linspace(-1, 1, k)] * x0.shape[1], indexing="ij"), -1).reshape(-1, x0.shape[1])
    for _ in range(rounds):
        cand = x0[:, None, :] + offs[None] * spans  # (N, K, m)
        d = np.linalg.norm(param(cand) - p[:, None, :], axis=-1)
        x0 = cand[np.arange(len(p)), np.argmin(d, axis=1)]
        spans = spans * 4.0 / (k - 1)  # +-2 steps of the last grid
    return np.linalg.norm(param(x0[:, None])[:, 0] - p, axis=-1)


def _random_points(rng, axes, n=200):
    """Points inside and outside: a box 1.6x the axes, plus a shell hugging the surface."""
    axes = np.asarray(axes, dtype=float)
    box = rng.uniform(-1.6, 1.6, (n // 2, len(axes))) * axes
    u = rng.normal(size=(n - n // 2, len(axes)))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    shell = u * axes * rng.uniform(0.9, 1.1, (len(u), 1))
    return np.vstack([box, shell])


@pytest.mark.parametrize("a, b", [(3.0, 1.0), (1.0, 3.0), (1.5, 1.2), (2.0, 0.1)])
def test_ellipse_matches_brute_force(a, b):
    rng = np.random.default_rng(10)
    m = 200_000
    th = np.linspace(0.0, 2 * np.pi, m, endpoint=False)
    param = lambda t: np.stack([a * np.cos(t[..., 0]), b * np.sin(t[..., 0])], -1)  # noqa: E731
    boundary = param(th[:, None])
    c, yaw = np.array([0.7, -1.2]), 0.4
    body = _random_points(rng, (a, b))
    world = body @ _rot(yaw).T + c
    d = Ellipse(a, b).signed_distance(world, c, yaw)
    inside = (body[:, 0] / a) ** 2 + (body[:, 1] / b) ** 2 < 1
    assert inside.sum() > 40 and (~inside).sum() > 40
    assert np.all((d < 0) == inside)

    # Exact nearest neighbour among the dense boundary samples (a k-d tree == brute force).
    dist_s, idx = cKDTree(boundary).query(body)
    scale = max(a, b)
    assert np.all(np.abs(d) <= dist_s + 1e-12 * scale)          # never above an attained distance
    assert np.max(dist_s - np.abs(d)) < 0.5 * 2 * np.pi * scale / m  # half the sample spacing
    refined = _local_refine(param, th[idx][:, None], body, [4 * np.pi / m])
    assert np.max(np.abs(refined - np.abs(d))) < 1e-12 * scale


@pytest.mark.parametrize("a, b", [(3.0, 1.0), (1.0, 3.0)])
def test_ellipse_axes_and_center(a, b):
    e = Ellipse(a, b)
    lo, hi = min(a, b), max(a, b)
    assert e.signed_distance([0.0, 0.0], [0.0, 0.0]) == pytest.approx(-lo, abs=1e-14)
    # Along the axes (body frame) with the minor axis on body x or y.
    minor = np.array([0.0, 1.0]) if b < a else np.array([1.0, 0.0])
    major = minor[::-1]
    for t in [0.0, 0.3, 0.99, 1.5, 5.0]:
        assert e.signed_distance(t * lo * minor, [0, 0]) == pytest.approx(t * lo - lo, abs=1e-13)
    assert e.signed_distance((hi + 2.0) * major, [0, 0]) == pytest.approx(2.0, abs=1e-13)
    assert e.signed_distance(0.9 * hi * major, [0, 0]) == pytest.approx(-0.1 * hi, abs=1e-13)
    # Inside on the major axis below the evolute cusp (hi^2 - lo^2)/hi: the nearest point
    # leaves the axis at x = hi^2 x0 / (hi^2 - lo^2) (closed form).
    x0 = 1.0
    xs = hi**2 * x0 / (hi**2 - lo**2)
    expected = -math.hypot(xs - x0, lo * math.sqrt(1 - (xs / hi) ** 2))
    assert e.signed_distance(x0 * major, [0, 0]) == pytest.approx(expected, abs=1e-13)
    # Continuity across the axis (generic root branch vs axis branch).
    for eps in [1e-12, 1e-9, 1e-6]:
        assert e.signed_distance(x0 * major + eps * minor, [0, 0]) == pytest.approx(expected, abs=2 * eps + 1e-12)
        assert e.signed_distance(eps * major, [0, 0]) == pytest.approx(-lo, abs=2 * eps + 1e-12)
    # The offset center and yaw also apply to axis points.
    c = np.array([5.0, -3.0])
    p = c + _rot(0.5) @ ((hi + 1.0) * major)
    assert e.signed_distance(p, c, yaw=0.5) == pytest.approx(1.0, abs=1e-12)


def _ellipsoid_param(axes):
    a, b, c = axes
    return lambda t: np.stack([a * np.sin(t[..., 0]) * np.cos(t[..., 1]),
                               b * np.sin(t[..., 0]) * np.sin(t[..., 1]),
                               c * np.cos(t[..., 0])], -1)


@pytest.mark.parametrize("axes", [(3.0, 2.0, 1.0), (1.0, 3.0, 2.0), (2.0, 2.0, 1.0), (1.0, 1.0, 2.0), (1.5, 0.5, 0.5)])
def test_ellipsoid_matches_brute_force(axes):
    rng = np.random.default_rng(20)
    nt, nphi = 1000, 2000
    tt, pp = np.meshgrid(np.linspace(0, np.pi, nt), np.linspace(0, 2 * np.pi, nphi, endpoint=False), indexing="ij")
    grid = np.column_stack([tt.ravel(), pp.ravel()])
    param = _ellipsoid_param(axes)
    c, yaw = np.array([1.0, -2.0, 0.5]), -0.6
    body = _random_points(rng, axes)
    world = body.copy()
    world[:, :2] = body[:, :2] @ _rot(yaw).T
    world += c
    d = Ellipsoid(*axes).signed_distance(world, c, yaw)
    inside = np.sum((body / np.asarray(axes)) ** 2, axis=1) < 1
    assert inside.sum() > 40 and (~inside).sum() > 40
    assert np.all((d < 0) == inside)

    dist_s, idx = cKDTree(param(grid)).query(body)
    scale = max(axes)
    assert np.all(np.abs(d) <= dist_s + 1e-12 * scale)
    assert np.max(dist_s - np.abs(d)) < min(1e-3, 0.5 * np.hypot(np.pi / (nt - 1), 2 * np.pi / nphi)) * scale
    # Refine in gnomonic coordinates about the best sample (regular at the poles, unlike theta/phi).
    ax = np.asarray(axes)
    v0 = param(grid[idx]) / ax  # unit directions (N, 3)
    t1 = np.cross(v0, np.eye(3)[np.argmin(np.abs(v0), axis=1)])
    t1 /= np.linalg.norm(t1, axis=1, keepdims=True)
    t2 = np.cross(v0, t1)

    def gnomonic(t):
        v = v0[:, None] + t[..., :1] * t1[:, None] + t[..., 1:] * t2[:, None]
        return ax * v / np.linalg.norm(v, axis=-1, keepdims=True)

    refined = _local_refine(gnomonic, np.zeros((len(body), 2)), body, [4 * np.pi / nphi] * 2)
    assert np.max(np.abs(refined - np.abs(d))) < 1e-12 * scale


@pytest.mark.parametrize("axes", [(3.0, 2.0, 1.0), (1.0, 2.0, 3.0), (2.0, 2.0, 1.0)])
def test_ellipsoid_axes_planes_and_center(axes):
    E, e = Ellipsoid(*axes), np.asarray(axes)
    z3 = np.zeros(3)
    assert E.signed_distance(z3, z3) == pytest.approx(-e.min(), abs=1e-14)
    for i in range(3):
        u = np.eye(3)[i]
        assert E.signed_distance((e[i] + 1.5) * u, z3) == pytest.approx(1.5, abs=1e-13)
        assert E.signed_distance(-e[i] * u, z3) == pytest.approx(0.0, abs=1e-13)
    i_min = int(np.argmin(e))
    assert E.signed_distance(0.4 * e[i_min] * np.eye(3)[i_min], z3) == pytest.approx(-0.6 * e[i_min], abs=1e-13)
    # Points on coordinate planes / axes (closed-form branches) against slightly perturbed
    # copies (generic root branch): the distance is 1-Lipschitz, so they must agree.
    rng = np.random.default_rng(3)
    pts = rng.uniform(-0.9, 0.9, (60, 3)) * e
    for k in range(3):
        pts[20 * k:20 * k + 10, k] = 0.0          # on a coordinate plane
        pts[20 * k + 10:20 * k + 20, [k, (k + 1) % 3]] = 0.0  # on an axis
    d0 = E.signed_distance(pts, z3)
    for eps in [1e-10, 1e-7]:
        d1 = E.signed_distance(pts + eps, z3)
        np.testing.assert_allclose(d1, d0, atol=4 * eps + 1e-12)


def test_equal_axes_reduce_to_circle_and_sphere():
    rng = np.random.default_rng(4)
    p2 = np.vstack([rng.uniform(-4, 4, (300, 2)), [[0.0, 0.0], [1.0, 0.0], [0.0, -3.0]]])
    np.testing.assert_allclose(Ellipse(2.0, 2.0).signed_distance(p2, [0.5, 0.5], 0.3),
                               Circle(2.0).signed_distance(p2, [0.5, 0.5]), atol=1e-12)
    p3 = np.vstack([rng.uniform(-4, 4, (300, 3)), [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -3.0]]])
    np.testing.assert_allclose(Ellipsoid(2.0, 2.0, 2.0).signed_distance(p3, [0.5, 0.5, 0.0], 0.3),
                               Sphere(2.0).signed_distance(p3, [0.5, 0.5, 0.0]), atol=1e-12)


# --------------------------------------------------------------------------- common API
@pytest.mark.parametrize("shape", [s for s in ALL_SHAPES if s.dim == 2], ids=lambda s: s.kind)
def test_outline_on_boundary_and_sign(shape):
    c, yaw = np.array([2.0, -1.0]), 0.9
    out = shape.outline(c, yaw, n=97)
    assert out.shape == (97, 2)
    np.testing.assert_array_equal(out[0], out[-1])
    np.testing.assert_allclose(shape.signed_distance(out, c, yaw), 0.0, atol=1e-12)
    assert np.all(shape.signed_distance(c + 0.5 * (out - c), c, yaw) < 0)  # star-shaped about c
    assert np.all(shape.signed_distance(c + 1.5 * (out - c), c, yaw) > 0)
    assert shape.signed_distance(c, c, yaw) < 0
    with pytest.raises(ValueError):
        shape.outline(c, yaw, n=4)


def test_box_outline_contains_corners():
    out = Box(4.0, 2.0).outline([0.0, 0.0], n=9)
    for corner in [(2, 1), (-2, 1), (-2, -1), (2, -1)]:
        assert np.min(np.linalg.norm(out - corner, axis=1)) < 1e-12


@pytest.mark.parametrize("shape", ALL_SHAPES, ids=lambda s: s.kind)
def test_vectorised_shapes_and_bounds(shape):
    rng = np.random.default_rng(5)
    dim = shape.dim
    c = rng.normal(size=dim)
    pts = c + rng.uniform(-3, 3, (4, 5, dim))
    d = shape.signed_distance(pts, c, yaw=0.25)
    assert d.shape == (4, 5) and d.dtype == np.float64
    loop = [[shape.signed_distance(pts[i, j], c, yaw=0.25) for j in range(5)] for i in range(4)]
    np.testing.assert_allclose(d, loop, atol=1e-14)
    assert shape.signed_distance(pts[0, 0], c, 0.25).shape == ()
    # bounding_radius / support_extent enclose the shape, and are tight (touched somewhere).
    u = rng.normal(size=(2000, dim))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = shape.bounding_radius()
    assert np.all(shape.signed_distance(c + (r + 1e-9) * u, c, 0.25) > 0)
    ext = shape.support_extent()
    assert ext.shape == (dim,)
    for i in range(dim):
        e_i = np.eye(dim)[i] * ext[i]
        assert shape.signed_distance(e_i, np.zeros(dim)) == pytest.approx(0.0, abs=1e-12)
        assert shape.signed_distance(1.001 * e_i, np.zeros(dim)) > 0
    with pytest.raises(ValueError):
        shape.signed_distance(np.zeros((3, dim + 1)), c)
    with pytest.raises(ValueError):
        shape.signed_distance(np.zeros((3, dim)), np.zeros(dim + 1))


def test_bounding_radius_values():
    assert Box(4.0, 3.0).bounding_radius() == pytest.approx(2.5)
    assert Box3(2.0, 4.0, 4.0).bounding_radius() == pytest.approx(3.0)
    assert Cylinder(3.0, 8.0).bounding_radius() == pytest.approx(5.0)
    assert Ellipsoid(1.0, 3.0, 2.0).bounding_radius() == 3.0
    np.testing.assert_allclose(Cylinder(3.0, 8.0).support_extent(), [3.0, 3.0, 4.0])


def test_inflated():
    assert Circle(1.0).inflated(0.5) == Circle(1.5)
    assert Sphere(2.0).inflated(0.25) == Sphere(2.25)
    p = np.array([[3.0, 0.0], [0.2, 0.1]])
    np.testing.assert_allclose(Circle(1.0).inflated(0.5).signed_distance(p, [0, 0]),
                               Circle(1.0).signed_distance(p, [0, 0]) - 0.5)
    with pytest.raises(ValueError, match="Circle.radius"):
        Circle(1.0).inflated(-2.0)


@pytest.mark.parametrize("cls", list(SHAPES_2D.values()) + list(SHAPES_3D.values()), ids=lambda c: c.kind)
@pytest.mark.parametrize("bad", [-1.0, 0.0, float("nan"), float("inf"), "x", None, True])
def test_bad_sizes_raise_naming_the_field(cls, bad):
    names = [f.name for f in dataclasses.fields(cls)]
    for name in names:
        kw = {n: 1.0 for n in names}
        kw[name] = bad
        with pytest.raises(ValueError, match=rf"{cls.__name__}\.{name} must be positive and finite"):
            cls(**kw)


def test_bad_size_message():
    with pytest.raises(ValueError, match=r"^Ellipse\.b must be positive and finite, got -1$"):
        Ellipse(1.0, -1)


def test_shape_from_table_and_registries():
    assert set(SHAPES_2D) == {"circle", "ellipse", "box"}
    assert set(SHAPES_3D) == {"sphere", "ellipsoid", "box3", "cylinder"}
    assert all(cls.dim == 2 for cls in SHAPES_2D.values()) and all(cls.dim == 3 for cls in SHAPES_3D.values())
    assert shape_from_table("circle", {"radius": 1.0}) == Circle(1.0)
    assert shape_from_table("ellipse", {"a": 2, "b": 1}) == Ellipse(2.0, 1.0)
    assert shape_from_table("box", {"length": 4.5, "width": 1.9}) == Box(4.5, 1.9)
    assert shape_from_table("cylinder", {"radius": 0.5, "height": 2.0}) == Cylinder(0.5, 2.0)
    assert shape_from_table("box3", {"length": 1, "width": 2, "height": 3}).kind == "box3"
    assert isinstance(shape_from_table("ellipse", {"a": 2, "b": 1}).a, float)
    with pytest.raises(ValueError, match="unknown shape kind 'triangle'"):
        shape_from_table("triangle", {"radius": 1.0})
    with pytest.raises(ValueError, match=r"missing size key\(s\) \['width'\]"):
        shape_from_table("box", {"length": 4.5})
    with pytest.raises(ValueError, match=r"unexpected size key\(s\) \['c'\]"):
        shape_from_table("ellipse", {"a": 2, "b": 1, "c": 3})
    with pytest.raises(ValueError, match=r"Sphere\.radius"):
        shape_from_table("sphere", {"radius": -2.0})


@pytest.mark.parametrize("shape", [Circle(1.2), Box(4.6, 1.9), Ellipse(2.0, 1.0), Sphere(0.8), Box3(2.0, 1.0, 0.6),
                                   Ellipsoid(1.5, 1.0, 0.5), Cylinder(0.7, 1.4)])
def test_distance_and_normal_is_the_signed_distance_and_its_gradient(shape):
    rng = np.random.default_rng(3)
    d = shape.dim
    pts = rng.uniform(-4.0, 4.0, size=(400, d))
    center, yaw = rng.normal(size=d), 0.7
    sd, n = shape.distance_and_normal(pts, center, yaw)
    np.testing.assert_array_equal(sd, shape.signed_distance(pts, center, yaw))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    h = 1e-6
    fd = np.stack([(shape.signed_distance(pts + h * e, center, yaw) - shape.signed_distance(pts - h * e, center, yaw))
                   / (2 * h) for e in np.eye(d)], axis=1)
    smooth = np.abs(np.linalg.norm(fd, axis=1) - 1.0) < 1e-4       # off the medial axes, where the gradient exists
    assert smooth.mean() > 0.9
    np.testing.assert_allclose(n[smooth], fd[smooth], atol=1e-5)
    # the nearest boundary point lies sd back along the normal
    on = pts - sd[:, None] * n
    np.testing.assert_allclose(shape.signed_distance(on, center, yaw), 0.0, atol=1e-6)


def test_distance_and_normal_keeps_the_leading_shape_and_a_direction_at_the_centre():
    sd, n = Circle(1.0).distance_and_normal(np.zeros((2, 3, 2)), np.zeros(2))
    assert sd.shape == (2, 3) and n.shape == (2, 3, 2)
    np.testing.assert_allclose(n.reshape(-1, 2), [[1.0, 0.0]] * 6)
    sd, n = Box(2.0, 1.0).distance_and_normal(np.array([[0.9, 0.1], [-0.1, -0.45]]), np.zeros(2))
    np.testing.assert_allclose(sd, [-0.1, -0.05])
    np.testing.assert_allclose(n, [[1.0, 0.0], [0.0, -1.0]])


@pytest.mark.parametrize("shape, pts", [
    (Ellipse(2.0, 1.0), [[3.0, 0.0], [-0.5, 0.0], [1.9, 0.0], [0.0, 0.0], [0.0, -2.0]]),
    (Ellipsoid(1.5, 1.0, 0.5), [[2.0, 0.0, 0.0], [0.3, -0.2, 0.0], [1.4, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 1.5, 0.0]]),
])
def test_ellipse_normals_on_the_axes_point_from_the_nearest_boundary_point(shape, pts):
    """The closed-form normal of the ellipse and ellipsoid on their axes and coordinate planes
    (Eberly's special branches): unit, and the nearest boundary point lies sd back along it."""
    pts = np.array(pts)
    sd, n = shape.distance_and_normal(pts, np.zeros(shape.dim))
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-12)
    on = pts - sd[:, None] * n
    np.testing.assert_allclose(shape.signed_distance(on, np.zeros(shape.dim)), 0.0, atol=1e-9)
    np.testing.assert_allclose(np.abs(sd), np.linalg.norm(pts - on, axis=1), atol=1e-12)
