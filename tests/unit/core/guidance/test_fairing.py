"""Fairing: the planned path's curvature bounded around the repulsive regions (fairing.py)."""

import numpy as np
import pytest

from vflpcd.controllers.loops import active_set_loop
from vflpcd.core.guidance.fairing import SPACING, Region, solve_active_set, fair_path, half_planes
from vflpcd.core.guidance.implicit import ObstacleImplicit
from vflpcd.core.guidance.speed import menger_curvature
from vflpcd.core.shapes import Circle


def _obstacle(center, radius=1.0, velocity=(0.0, 0.0)):
    return ObstacleImplicit.around("o", Circle(radius), np.asarray(center, float), 0.0, np.asarray(velocity, float),
                                   0.0, reactive_distance=3.0, repulsive_distance=1.5)


def _values(obstacles):
    """The obstacles' repulsive regions, each evaluated where its centre is when a point is reached."""
    return [Region(lambda pts, t, o=o: o.value_grad(pts - (t[:, None] - o.stamp) * o.velocity, o.stamp), o.c)
            for o in obstacles]


def _detour(obstacle, length=40.0, step=0.1):
    """A path along y = 0 that jumps onto the repulsive boundary's circle where it would enter it:
    clear, but with the boundary's curvature and kinks at both ends."""
    x = np.arange(0.0, length, step)
    y = np.zeros_like(x)
    r = 1.0 + 1.5 + 0.05  # just outside Q: the circle of radius 1 grown by the repulsive distance
    cx = obstacle.center[0]
    inside = np.abs(x - cx) < r
    y[inside] = np.sqrt(r ** 2 - (x[inside] - cx) ** 2) + obstacle.center[1]
    return np.column_stack([x, np.maximum(y, 0.0)])


def test_a_sharp_clear_path_is_faired_within_the_limit_and_stays_clear():
    o = _obstacle([20.0, -0.5])
    xy = _detour(o)
    assert np.all(o.value(xy) > o.c)                     # the input is clear ...
    assert menger_curvature(xy).max() > 0.5              # ... but far too sharp for a car
    kappa_max = 0.14
    out = fair_path(xy, np.arange(len(xy)) * 0.01, kappa_max, _values([o]), heading=np.array([1.0, 0.0]))
    assert menger_curvature(out).max() <= kappa_max
    assert np.all(o.value(out) > o.c)
    np.testing.assert_allclose(out[0], xy[0], atol=1e-6)
    d = out[1] - out[0]
    assert abs(np.arctan2(d[1], d[0])) < 1e-4            # leaves along the robot's heading
    assert np.max(np.linalg.norm(np.diff(out, axis=0), axis=1)) < 1.5 * SPACING


def test_a_drivable_aligned_path_comes_back_unchanged():
    xy = np.column_stack([np.linspace(0, 30, 301), 0.01 * np.linspace(0, 30, 301) ** 1.5])
    out = fair_path(xy, np.zeros(len(xy)), 0.2, _values([]), heading=np.array([1.0, 0.0]))
    assert out is xy


def test_a_start_off_the_robot_heading_is_faired_to_it():
    xy = np.column_stack([np.linspace(0, 30, 301), np.linspace(0, 30, 301)])   # 45 deg, no curvature
    out = fair_path(xy, np.zeros(len(xy)), 0.2, _values([]), heading=np.array([1.0, 0.0]))
    d = out[1] - out[0]
    assert abs(np.arctan2(d[1], d[0])) < 1e-4
    assert menger_curvature(out).max() <= 0.2


def test_the_goal_stays_pinned():
    o = _obstacle([20.0, -0.5])
    xy = _detour(o)
    out = fair_path(xy, np.zeros(len(xy)), 0.14, _values([o]), pin_end=True)
    np.testing.assert_allclose(out[-1], xy[-1], atol=1e-4)


def test_a_moving_obstacle_is_kept_clear_of_at_the_times_the_points_are_reached():
    o = _obstacle([10.0, -0.5], velocity=(1.0, 0.0))   # at x = 20 when the path gets there (t = x / 2)
    t = np.arange(0.0, 40.0, 0.1) / 2.0
    xy = _detour(_obstacle([20.0, -0.5]))
    out = fair_path(xy, t, 0.14, _values([o]))
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])
    s_out = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(out, axis=0), axis=1))])
    t_out = np.interp(s_out / s_out[-1] * s[-1], s, t)
    shifted = out - (t_out[:, None] - o.stamp) * o.velocity
    assert np.all(o.value(shifted) > o.c)


def test_a_path_the_first_fairing_length_leaves_in_a_region_comes_back_without_the_stiffer_ones(monkeypatch):
    import vflpcd.core.guidance.fairing as fairing

    solves = []

    def counted(*args, **kwargs):
        solves.append(1)
        return solve_active_set(*args, **kwargs)

    monkeypatch.setattr(fairing, "solve_active_set", counted)
    everywhere = Region(lambda pts, t: (np.full(len(pts), -1.0), np.tile([0.0, 1.0], (len(pts), 1))), -0.5)
    xy = _detour(_obstacle([20.0, -0.5]))            # too sharp: fairing is needed
    out = fair_path(xy, np.zeros(len(xy)), 0.14, [everywhere], pin_end=True)
    assert len(solves) == fairing.OUTER_ROUNDS         # one length, FAIR_MIN, not up to FAIR_MAX
    np.testing.assert_array_equal(out, fairing.resample(xy, np.zeros(len(xy)), SPACING)[0])


@pytest.mark.parametrize("angle", [40.0, 70.0, -90.0])
def test_a_faired_path_stays_within_a_turning_radius_of_the_path_it_fairs(angle):
    """A robot heading well off a long straight plan: the stiff lengths that would meet the limit
    only by running out along the heading (a lever tens of metres long: 625 m off the road in
    one replan of bench variants) are not taken; the path comes back within 1 / kappa_max of its
    own points."""
    from vflpcd.core.guidance.fairing import resample

    xy = np.column_stack([np.linspace(0.0, 60.0, 601), np.zeros(601)])
    t = np.linspace(0.0, 10.0, 601)
    a = np.radians(angle)
    kappa_max = 0.14
    out = fair_path(xy, t, kappa_max, _values([]), heading=np.array([np.cos(a), np.sin(a)]))
    r = resample(xy, t, SPACING)[0]
    assert out.shape == r.shape
    assert np.max(np.linalg.norm(out - r, axis=1)) <= 1.0 / kappa_max
    np.testing.assert_allclose(out[0], xy[0], atol=1e-8)


LOOPS = pytest.mark.parametrize("loop", [None, active_set_loop()], ids=["numpy", "compiled"])


@LOOPS
def test_the_convex_step_is_the_exact_minimiser(loop):
    """Against OSQP on the same QP: the half-planes enforced to 1e-5 m, the cost within 1e-6, on the
    numpy path and the compiled loop."""
    osqp = pytest.importorskip("osqp")
    import scipy.sparse as sp

    o = _obstacle([5.0, -0.3])
    r = np.column_stack([np.linspace(0, 10, 41), np.zeros(41)])
    n, b = half_planes(r, np.zeros(41), _values([o]))
    assert np.isfinite(b).sum() > 5
    eps = (SPACING / 4.0) ** 4
    x, _ = solve_active_set(r, eps, n, b, pin_end=True, loop=loop)
    K = len(r)
    D = np.diff(np.eye(K), 2, axis=0)
    H = np.kron(D.T @ D + eps * np.eye(K), np.eye(2))
    rows, lo, hi = [], [], []
    for k in range(K):
        for j in range(2):
            if k in (0, 1, K - 1):
                e = np.zeros(2 * K)
                e[2 * k + j] = 1.0
                rows.append(e); lo.append(r[k, j]); hi.append(r[k, j])
        if k not in (0, 1, K - 1) and np.isfinite(b[k]):
            e = np.zeros(2 * K)
            e[2 * k:2 * k + 2] = n[k]
            rows.append(e); lo.append(b[k]); hi.append(np.inf)
    m = osqp.OSQP()
    m.setup(P=sp.csc_matrix(2 * H), q=-2 * eps * r.ravel(), A=sp.csc_matrix(np.array(rows)), l=np.array(lo),
            u=np.array(hi), verbose=False, eps_abs=1e-9, eps_rel=1e-9, max_iter=100000, polishing=True)
    res = m.solve(raise_error=True)
    assert res.info.status == "solved"
    ref = res.x.reshape(K, 2)
    J = lambda z: eps * np.sum((z - r) ** 2) + np.sum(np.diff(z, 2, axis=0) ** 2)
    gap = np.where(np.isfinite(b), np.einsum("ij,ij->i", n, x) - b, 0.0)
    assert gap[2:-1].min() > -1e-5
    assert abs(J(x) - J(ref)) <= 1e-6 * max(J(ref), 1e-9) + 1e-9


def test_a_warm_active_set_gives_the_same_minimiser():
    """Started from a previous solve's active set (a superset here), the active set still ends at
    the same minimiser (the problem is strictly convex): the warm start only saves rounds."""
    o = _obstacle([5.0, -0.3])
    r = np.column_stack([np.linspace(0, 10, 41), np.zeros(41)])
    n, b = half_planes(r, np.zeros(41), _values([o]))
    eps = (SPACING / 4.0) ** 4
    cold, active = solve_active_set(r, eps, n, b, pin_end=True)
    warm, _ = solve_active_set(r, eps, n, b, pin_end=True, active0=active | np.isfinite(b))
    assert np.max(np.abs(warm - cold)) < 1e-6


@pytest.mark.parametrize("K, d", [(6, 2), (7, 2), (240, 2), (9, 3), (50, 3)])
def test_the_banded_hessian_is_the_kronecker_product_of_the_bending_energy(K, d):
    """_hessian_bands, built from the closed-form diagonals of D2'D2, against the dense
    kron(D2'D2 + eps I, I_d) taken into LAPACK's lower band layout."""
    from vflpcd.core.guidance.fairing import _hessian_bands

    eps = 3e-4
    D2 = np.zeros((K - 2, K))
    rows = np.arange(K - 2)
    D2[rows, rows], D2[rows, rows + 1], D2[rows, rows + 2] = 1.0, -2.0, 1.0
    M = np.kron(D2.T @ D2 + eps * np.eye(K), np.eye(d))
    u = 2 * d + 1
    expected = np.zeros((u + 1, K * d))
    for off in range(u + 1):
        expected[off, :K * d - off] = np.diagonal(M, -off)
    np.testing.assert_array_equal(_hessian_bands(K, d, eps), expected)


@pytest.mark.parametrize("seed", range(6))
def test_the_compiled_loop_and_the_numpy_path_give_the_same_minimiser(seed):
    """Random obstacles beside a noisy path, with and without a shape and pinned end: the compiled
    active set (its own banded Cholesky) and the numpy one (LAPACK) end at the same active set, the
    same cost to 1e-9 (relative) and the same points to 1e-3 m (the pins' springs and a small eps
    make the systems ill-conditioned: the two factorisations' rounding moves the points by up to
    1e-4 m along the path's nearly free bending modes, at no cost)."""
    rng = np.random.default_rng(seed)
    obstacles = [_obstacle([rng.uniform(3, 17), rng.uniform(-1.2, 1.2)]) for _ in range(3)]
    r = np.column_stack([np.linspace(0, 20, 81), rng.normal(0, 0.2, 81)])
    r[:2, 1] = 0.0
    n, b = half_planes(r, np.zeros(81), _values(obstacles))
    shape = np.column_stack([r[:, 0], np.zeros(81)]) if seed % 2 else None
    eps = (SPACING / (2.0 + 4 * seed)) ** 4
    x_np, a_np = solve_active_set(r, eps, n, b, seed % 3 == 0, shape=shape)
    x_c, a_c = solve_active_set(r, eps, n, b, seed % 3 == 0, shape=shape, loop=active_set_loop())
    np.testing.assert_array_equal(a_np, a_c)
    g = np.zeros_like(r) if shape is None else shape
    J = lambda z: eps * np.sum((z - r) ** 2) + np.sum(np.diff(z - g, 2, axis=0) ** 2)
    assert abs(J(x_c) - J(x_np)) <= 1e-9 * J(x_np)
    np.testing.assert_allclose(x_c, x_np, atol=1e-3)


def test_the_active_set_converges_in_few_rounds_where_a_primal_one_cycled_or_crawled():
    """A stiff path (l = 64 m) through a row of obstacles on both sides: an active set that jumped
    to each round's minimiser released and re-added the same half-planes until its round cap, and
    a primal one that stepped only as far as the half-planes let it moved one contact point a
    round; the dual active set converges in a few rounds per half-plane that ends active."""
    import vflpcd.core.guidance.fairing as fairing

    rng = np.random.default_rng(13)
    obstacles = [_obstacle([x, rng.choice([-1.0, 1.0]) * rng.uniform(1.5, 2.5)], radius=0.5) for x in range(4, 60, 5)]
    r = np.column_stack([np.linspace(0, 64, 257), rng.normal(0, 0.4, 257)])
    r[:2, 1] = 0.0
    n, b = half_planes(r, np.zeros(257), _values(obstacles))
    rounds = []
    loop = active_set_loop()

    def counted(*args):
        rounds.append(loop(*args))
        return rounds[-1]

    _, active = solve_active_set(r, (SPACING / 64.0) ** 4, n, b, False, loop=counted)
    assert 0 < rounds[0] <= 3 * max(active.sum(), 1) < fairing.ACTIVE_ROUNDS, (rounds, active.sum())


@LOOPS
@pytest.mark.parametrize("cap", [2, 3, 4])
def test_an_active_set_stopped_at_its_round_cap_returns_a_path_that_keeps_every_half_plane(cap, loop, monkeypatch):
    """Stopped by the round cap, the solve returns a point that violates no half-plane: the dual
    active set's iterates cut into the half-planes until it converges, so the cap makes every
    violated half-plane active until a minimiser violates none (two obstacles beside a noisy path;
    the iterate at each of these caps cuts in)."""
    import vflpcd.core.guidance.fairing as fairing

    rng = np.random.default_rng(59)
    obstacles = [_obstacle([rng.uniform(3, 7), rng.uniform(-1.0, 1.0)]) for _ in range(2)]
    r = np.column_stack([np.linspace(0, 10, 41), rng.normal(0, 0.3, 41)])
    r[:2, 1] = 0.0
    n, b = half_planes(r, np.zeros(41), _values(obstacles))
    monkeypatch.setattr(fairing, "ACTIVE_ROUNDS", cap)
    x, _ = fairing.solve_active_set(r, (SPACING / 4.0) ** 4, n, b, pin_end=True, loop=loop)
    gap = np.where(np.isfinite(b), np.einsum("ij,ij->i", n, x) - b, 0.0)
    assert gap[2:-1].min() > -fairing.VIOLATION


def _ring_arc(radius=15.0, arc=40.0, step=0.1):
    """A left bend: an arc of a ring (centre (0, radius)) from the origin heading +x."""
    a = np.arange(0.0, arc, step) / radius
    return np.column_stack([radius * np.sin(a), radius * (1.0 - np.cos(a))])


def test_a_free_end_in_a_bend_stays_in_the_bend(monkeypatch):
    """A plan on a 15 m ring that starts off the robot's heading is faired; its free end stays on the
    ring (a bending-energy minimiser's free end is straight: without the lead-out it left the ring)."""
    import vflpcd.core.guidance.fairing as fairing

    xy = _ring_arc()
    heading = np.array([np.cos(0.3), -np.sin(0.3)])          # 0.3 rad right of the ring's tangent
    off_ring, shipped = {}, fairing.LEAD_OUT
    for lead in (shipped, 0.0):
        monkeypatch.setattr(fairing, "LEAD_OUT", lead)
        out = fair_path(xy, np.zeros(len(xy)), 0.139, _values([]), heading=heading)
        off_ring[lead] = abs(np.linalg.norm(out[-1] - [0.0, 15.0]) - 15.0)
        assert menger_curvature(out).max() <= 0.139
        np.testing.assert_allclose(out[0], xy[0], atol=1e-6)
    assert off_ring[shipped] < 0.4 and off_ring[0.0] > 2.0       # 0.28 m and 3.25 m


def test_the_lead_out_continues_the_end_on_its_circle_at_most_at_the_limit():
    from vflpcd.core.guidance.fairing import lead_out

    xy = _ring_arc(step=SPACING)
    t = np.arange(len(xy)) * 0.05
    ext, te = lead_out(xy, t, 8.0, 0.139)
    tail = ext[len(xy):]
    assert len(tail) == int(np.ceil(8.0 / SPACING))
    np.testing.assert_allclose(np.linalg.norm(tail - [0.0, 15.0], axis=1), 15.0, atol=0.02)
    np.testing.assert_allclose(np.diff(te[len(xy) - 1:]), 0.05)
    tight, _ = lead_out(_ring_arc(radius=3.0, arc=12.0, step=SPACING), t[:48], 8.0, 0.139)   # 1/3 1/m: capped
    assert menger_curvature(tight[48:]).max() <= 0.139 + 1e-9
    flat = np.column_stack([np.arange(10.0), np.zeros(10), np.zeros(10)])
    assert lead_out(flat, np.arange(10.0), 8.0, 0.139)[0] is flat        # a 3-D path is left as it is


@pytest.mark.parametrize("beside", [2.52, 2.6, 2.7])
def test_a_plan_started_beside_a_region_leaves_it_within_the_limit(beside):
    # A robot passing an obstacle with its start inside the band the half-planes keep clear (between
    # Q's boundary and the level they touch), its heading 1 deg towards it: the field's path turns
    # away after 0.3 m. Held to the half-planes from the third point on, the faired path turned there
    # at 0.64 1/m (a replan refused as undrivable); the lead-in lets its first metres turn away at
    # the limit, and no point enters Q.
    o = _obstacle([1.0, beside])
    assert o.c < o.value(np.zeros((1, 2)))[0] < 0.6 * o.c
    s = np.arange(0.0, 40.0, 0.1)
    turn = np.where(s < 0.3, 0.0, np.where(s < 6.0, -0.1, 0.0))
    xy = 0.1 * np.column_stack([np.cumsum(np.cos(turn)), np.cumsum(np.sin(turn))])
    xy -= xy[0]
    assert np.all(o.value(xy) > o.c)
    heading = np.array([np.cos(0.02), np.sin(0.02)])
    out = fair_path(xy, np.zeros(len(xy)), 0.14, _values([o]), heading=heading)
    assert menger_curvature(out).max() <= 0.14
    assert np.all(o.value(out) > o.c)
    d = out[1] - out[0]
    assert d @ heading == pytest.approx(np.linalg.norm(d), abs=1e-6)
