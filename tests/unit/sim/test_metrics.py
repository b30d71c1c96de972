"""Every metric against values computed by hand on short synthetic trajectories."""

import numpy as np
import pytest

from sim import metrics as M


@pytest.fixture
def trajectory():
    # four points around a reference along the X axis (X_r = X, Y_r = 0, psi_r = 0)
    X = np.array([0.0, 1.0, 2.0, 3.0])
    Y = np.array([0.0, 1.0, 0.0, -1.0])
    psi = np.array([0.0, 0.5, 0.0, -0.5])
    u = np.array([[1.0, 0.0], [0.0, 1.0], [1.0, 1.0], [0.0, 0.0]])
    return X, Y, psi, u


def test_cost_terms_by_hand(trajectory):
    X, Y, psi, u = trajectory
    e = M.lateral_error(X, Y, X, np.zeros(4), np.zeros(4))
    assert e == pytest.approx([0.0, -1.0, 0.0, 1.0])          # (X-X_r) sin 0 - (Y-0) cos 0 = -Y
    jl = M.j_lat(e, q1=2.0)
    jh = M.j_heading(psi, np.zeros(4), q2=4.0)
    jc = M.j_con(u, np.array([[1.0, 0.0], [0.0, 2.0]]))
    assert jl == pytest.approx([0.0, 2.0, 0.0, 2.0])
    assert jh == pytest.approx([0.0, 1.0, 0.0, 1.0])           # 4 * 0.5^2
    assert jc == pytest.approx([1.0, 2.0, 3.0, 0.0])           # u' diag(1, 2) u
    assert M.j_mc(jl, jh, jc) == pytest.approx((1 + 5 + 3 + 3) / 4)  # = 3.0


def test_lateral_error_sign_and_rotated_reference():
    # reference heading 90 deg (north): a point east of it is on its right -> positive
    assert M.lateral_error(np.array([1.0]), np.array([0.0]), 0.0, 0.0, np.pi / 2) == pytest.approx([1.0])
    assert M.lateral_error(np.array([0.0]), np.array([1.0]), 0.0, 0.0, 0.0) == pytest.approx([-1.0])


def test_heading_cost_wraps_the_angle():
    jh = M.j_heading(np.array([np.pi - 0.1]), np.array([-np.pi + 0.1]), q2=1.0)
    assert jh == pytest.approx([0.04])


def test_route_length(trajectory):
    X, Y, _, _ = trajectory
    assert M.route_length(np.column_stack([X, Y])) == pytest.approx(3 * np.sqrt(2))
    assert M.route_length(np.array([[0, 0, 0], [0, 3, 4.0]])) == pytest.approx(5.0)


def test_calc_time_median_and_p99():
    med, p99 = M.calc_time_stats(np.array([1.0, 2.0, 3.0, 4.0, 100.0]) * 1e-3)
    assert med == pytest.approx(3e-3)
    assert p99 == pytest.approx((4.0 + 0.96 * 96.0) * 1e-3)  # linear interpolation at rank 3.96


def test_clearance_and_collision_episodes():
    c = np.array([[1.0, np.nan], [-0.5, np.nan], [0.2, 2.0], [-0.1, -1.0], [-0.2, -1.0]])
    assert M.min_clearance(c) == pytest.approx([-0.5, -1.0])
    assert M.collision_count(c) == 3   # obstacle 0 twice (k=1, k=3), obstacle 1 once (k=3)
    never = np.full((3, 1), np.nan)
    assert np.isnan(M.min_clearance(never)[0]) and M.collision_count(never) == 0


def test_rms():
    assert M.rms(np.array([0.0, -1.0, 0.0, 1.0])) == pytest.approx(np.sqrt(0.5))


def test_lateral_acceleration_on_a_circle_is_v2_over_r():
    t = np.linspace(0.0, 5.0, 501)
    w, r = 0.4, 5.0                      # speed 2 m/s on a 5 m circle
    v = r * w * np.column_stack([-np.sin(w * t), np.cos(w * t)])
    assert M.peak_lateral_acceleration(t, v) == pytest.approx((r * w) ** 2 / r, rel=1e-4)


def test_lateral_acceleration_of_straight_acceleration_is_zero_and_slow_points_ignored():
    t = np.linspace(0.0, 2.0, 21)
    v = np.column_stack([0.1 + 2.0 * t, np.zeros_like(t)])
    a = M.lateral_acceleration(t, v)
    assert np.isnan(a[0]) and np.isnan(a[1]) and not np.isnan(a[2])   # 0.1, 0.3 < 0.5 m/s <= 0.5
    assert np.nanmax(a) == pytest.approx(0.0, abs=1e-12)


def test_summarize_collects_everything(trajectory):
    X, Y, psi, u = trajectory
    pos = np.column_stack([X, Y])
    out = M.summarize(t=np.arange(4.0), positions=pos, velocity=np.ones((4, 2)), psi=psi, psi_r=np.zeros(4),
                      e_lat=-Y, u_tilde=u, t_cal=np.full(4, 1e-3), clearance=np.array([[1.0], [2.0], [0.5], [3.0]]),
                      q1=2.0, q2=4.0, R=np.diag([1.0, 2.0]), t_com=3.0)
    assert out["J_MC"] == pytest.approx(3.0)
    assert out["J_Lat"] == pytest.approx(1.0) and out["J_Heading"] == pytest.approx(0.5)
    assert out["J_Con"] == pytest.approx(1.5)
    assert out["min_clearance"] == pytest.approx(0.5) and out["collisions"] == 0
    assert out["t_com"] == 3.0 and out["L_p"] == pytest.approx(3 * np.sqrt(2))


def test_jerk_is_the_change_of_the_applied_acceleration_per_second():
    t = np.array([0.0, 0.05, 0.10, 0.15, 0.30])                 # a skipped step counts over its real gap
    a_x = np.array([0.0, 0.0, 1.0, 1.0, -2.0])
    assert M.jerk(t, a_x) == pytest.approx([0.0, 20.0, 0.0, 20.0])
    p99, peak = M.jerk_stats(t, a_x)
    assert peak == 20.0 and p99 == pytest.approx(np.percentile([0.0, 20.0, 0.0, 20.0], 99))
    assert all(np.isnan(M.jerk_stats(t[:1], a_x[:1])))


def test_summary_carries_the_peak_lateral_error_and_the_jerk(trajectory):
    X, Y, psi, u = trajectory
    t = np.arange(4) * 0.1
    e = M.lateral_error(X, Y, X, np.zeros(4), np.zeros(4))
    m = M.summarize(t=t, positions=np.column_stack([X, Y]), velocity=np.column_stack([np.ones(4), np.zeros(4)]),
                    psi=psi, psi_r=np.zeros(4), e_lat=e, u_tilde=u, t_cal=np.full(4, 1e-3),
                    clearance=np.full((4, 1), 5.0), q1=1.0, q2=1.0, R=np.eye(2), t_com=0.3,
                    t_applied=t, a_x=u[:, 0])
    assert m["peak_lateral_error"] == 1.0 and m["jerk_max"] == pytest.approx(10.0)
