"""Evaluation metrics of the paper (section "Simulation and Experimental Results"), plus safety figures.

Paper definitions, per trajectory point k = 1..M:
    J_Lat     = || (X - X_r) sin psi_r - (Y - Y_r) cos psi_r ||^2_{q1}
    J_Heading = || psi - psi_r ||^2_{q2}
    J_Con     = || u_tilde ||^2_R,     u_tilde = u - u_r  (u_r = 0 for the vehicle: u_tilde = [a_x, delta_f])
    J_MC      = (1/M) sum_k (J_k,Lat + J_k,Heading + J_k,Con)
    L_p       = sum_{k=1}^{M-1} || (X_{k+1}, Y_{k+1}) - (X_k, Y_k) ||
t_com is the time at which the run completes, t_cal the controller's computation time per
control step (median and 99th percentile here). The reference (X_r, Y_r, psi_r) of every
controller is the nearest point of the same reference path and its tangent, so the figures
compare like with like. In 3-D, the lateral error is the distance to the path and psi is the
course angle of the horizontal velocity.

Added for safety: the minimum clearance between the robot body and each obstacle's physical
boundary, the number of collisions (contact episodes: the clearance to an obstacle going
from >= 0 to < 0), the RMS and peak lateral error and the peak lateral acceleration. Added for
smoothness: the longitudinal jerk, d a_x / dt of the applied acceleration command (first
differences over the control steps), its 99th percentile and maximum in absolute value.
"""

from __future__ import annotations

import numpy as np

from vflpcd.core.angles import wrap_angle


def lateral_error(X, Y, X_r, Y_r, psi_r) -> np.ndarray:
    """(X - X_r) sin psi_r - (Y - Y_r) cos psi_r for arrays of shape (M,)."""
    return (np.asarray(X) - X_r) * np.sin(psi_r) - (np.asarray(Y) - Y_r) * np.cos(psi_r)


def j_lat(e_lat: np.ndarray, q1: float) -> np.ndarray:
    """J_k,Lat, shape (M,)."""
    return q1 * np.asarray(e_lat, float) ** 2


def j_heading(psi: np.ndarray, psi_r: np.ndarray, q2: float) -> np.ndarray:
    """J_k,Heading with the angle difference wrapped to (-pi, pi], shape (M,)."""
    return q2 * wrap_angle(np.asarray(psi, float) - psi_r) ** 2


def j_con(u_tilde: np.ndarray, R: np.ndarray) -> np.ndarray:
    """J_k,Con = u_tilde_k' R u_tilde_k for u_tilde (M, n_u), R (n_u, n_u). Returns (M,)."""
    u = np.asarray(u_tilde, float)
    return np.einsum("ki,ij,kj->k", u, R, u)


def j_mc(jl: np.ndarray, jh: np.ndarray, jc: np.ndarray) -> float:
    """Weighted average motion-control cost J_MC over the M trajectory points (NaN for none)."""
    return _mean(jl + jh + jc)


def _mean(x: np.ndarray) -> float:
    """The mean, NaN (without a warning) for an empty array."""
    x = np.asarray(x, float)
    return float(x.mean()) if x.size else float("nan")


def route_length(positions: np.ndarray) -> float:
    """L_p of positions (M, d)."""
    return float(np.sum(np.linalg.norm(np.diff(np.asarray(positions, float), axis=0), axis=1)))


def calc_time_stats(t_cal: np.ndarray) -> tuple[float, float]:
    """(median, 99th percentile) of per-step computation times, seconds."""
    t = np.asarray(t_cal, float)
    return float(np.median(t)), float(np.percentile(t, 99))


def min_clearance(clearance: np.ndarray) -> np.ndarray:
    """Per-obstacle minimum of clearance (M, n_obs), ignoring NaN (obstacle absent). Returns (n_obs,)."""
    c = np.asarray(clearance, float)
    out = np.full(c.shape[1], np.nan)
    seen = ~np.all(np.isnan(c), axis=0)
    out[seen] = np.nanmin(c[:, seen], axis=0)
    return out


def collision_count(clearance: np.ndarray) -> int:
    """Number of contact episodes over all obstacles in clearance (M, n_obs)."""
    contact = np.nan_to_num(np.asarray(clearance, float), nan=np.inf) < 0.0
    before = np.vstack([np.zeros((1, contact.shape[1]), bool), contact[:-1]])
    return int(np.sum(contact & ~before))


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(_mean(np.asarray(e, float) ** 2)))


def lateral_acceleration(t: np.ndarray, velocity: np.ndarray, v_min: float = 0.5) -> np.ndarray:
    """Acceleration normal to the velocity, |a - (a . v_hat) v_hat|, shape (M,).

    t: (M,) s; velocity: (M, d) world frame. The acceleration is the second-order finite
    difference of the velocity; where the speed is below v_min (direction undefined) the
    value is NaN.
    """
    v = np.asarray(velocity, float)
    if len(t) < 2:                                   # a run that ended at its first step
        return np.full(len(t), np.nan)
    a = np.gradient(v, np.asarray(t, float), axis=0, edge_order=2 if len(t) > 2 else 1)
    speed = np.linalg.norm(v, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        vhat = v / speed[:, None]
    normal = a - np.einsum("ij,ij->i", a, vhat)[:, None] * vhat
    out = np.linalg.norm(normal, axis=1)
    out[speed < v_min] = np.nan
    return out


def peak_lateral_acceleration(t: np.ndarray, velocity: np.ndarray, v_min: float = 0.5) -> float:
    a = lateral_acceleration(t, velocity, v_min)
    return float(np.nanmax(a)) if np.any(np.isfinite(a)) else float("nan")


def jerk(t: np.ndarray, a_x: np.ndarray) -> np.ndarray:
    """|d a_x / dt| between consecutive control steps (M - 1,): t (M,) s, a_x (M,) m/s^2."""
    t, a_x = np.asarray(t, float), np.asarray(a_x, float)
    dt = np.diff(t)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.abs(np.where(dt > 0.0, np.diff(a_x) / dt, np.nan))


def jerk_stats(t: np.ndarray, a_x: np.ndarray) -> tuple[float, float]:
    """(p99, max) of ``jerk`` in m/s^3; NaN for fewer than two steps."""
    j = jerk(t, a_x)
    j = j[np.isfinite(j)]
    if j.size == 0:
        return float("nan"), float("nan")
    return float(np.percentile(j, 99)), float(np.max(j))


def summarize(*, t, positions, velocity, psi, psi_r, e_lat, u_tilde, t_cal, clearance,
              q1: float, q2: float, R: np.ndarray, t_com: float | None, t_applied=None, a_x=None) -> dict:
    """Every metric of a run as a flat dict of floats (see the module docstring); ``t_applied``,
    ``a_x``: the steps whose command was applied and its longitudinal acceleration (for the jerk)."""
    jl, jh, jc = j_lat(e_lat, q1), j_heading(psi, psi_r, q2), j_con(u_tilde, R)
    jerk_p99, jerk_max = jerk_stats(t_applied, a_x) if a_x is not None else (float("nan"), float("nan"))
    t_med, t_p99 = calc_time_stats(t_cal)
    clear = min_clearance(clearance)
    return {
        "J_Lat": _mean(jl), "J_Heading": _mean(jh), "J_Con": _mean(jc),
        "J_MC": j_mc(jl, jh, jc), "L_p": route_length(positions), "t_com": t_com,
        "t_cal_median": t_med, "t_cal_p99": t_p99,
        "min_clearance": float(np.nanmin(clear)) if np.any(np.isfinite(clear)) else None,
        "min_clearance_per_obstacle": [None if np.isnan(c) else float(c) for c in clear],
        "collisions": collision_count(clearance), "rms_lateral_error": rms(e_lat),
        "peak_lateral_error": float(np.max(np.abs(e_lat))) if len(e_lat) else float("nan"),
        "peak_lateral_acceleration": peak_lateral_acceleration(t, velocity),
        "jerk_p99": jerk_p99, "jerk_max": jerk_max,
    }
