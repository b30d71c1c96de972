"""Speed planning along a planned path (paper section III-A, after eq. S_xi).

The centripetal limit v^2 kappa <= a_max gives v_max(s) = min(v_d, sqrt(a_max / kappa(s)));
the steering's rate limit caps the speed where the curvature changes: a car at speed v on a path
whose curvature changes by d kappa / ds per metre turns its steering at about L v |d kappa / ds|
(small angles), so v <= kappa_rate_max / |d kappa / ds| (``kappa_rate_max`` = delta_rate_max / L,
d kappa / ds over ``RATE_WINDOW`` of the windowed signed curvature; planar paths only);
a forward pass (v_{k+1}^2 <= v_k^2 + 2 a_acc ds) and a backward pass
(v_k^2 <= v_{k+1}^2 + 2 a_dec ds) make the profile reachable under the longitudinal limits,
and only ever lower speeds, so the centripetal limit still holds. A speed cap below the robot's
speed is taken as reached by braking at a_dec from it (``plan_speed``). Times follow from
dt = 2 ds / (v_k + v_{k+1}).
"""

from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d    # at import: a worker's first replan does not load it (0.2-0.5 s)

CURVATURE_WINDOW = 1.0   # m: a path's bend is its heading's change over this much arc length (``windowed_curvature``)
# m: the curvature's rate of change is taken over this much arc length (``curvature_rate``). The
# steering's rate limit matters for a sustained change (a swerve's S: 0.25 1/m over 4 m), not for
# the millimetre zig-zags of a solved path; over 1 or 2 m those slowed a car following a slow car
# in its lane (follow_slow_car J_MC 0.037 -> 0.095).
RATE_WINDOW = 3.0


def menger_curvature(xy: np.ndarray) -> np.ndarray:
    """Unsigned curvature of a polyline (K, d), d = 2 or 3, from the circle through each point
    and its neighbours (end points copy their neighbour). Returns (K,)."""
    a, b, c = xy[:-2], xy[1:-1], xy[2:]
    ab, bc, ca = (np.linalg.norm(b - a, axis=1), np.linalg.norm(c - b, axis=1), np.linalg.norm(a - c, axis=1))
    u, w = b - a, c - a  # |u x w| = twice the triangle's area, in any dimension
    cross = np.sqrt(np.maximum(np.einsum("ij,ij->i", u, u) * np.einsum("ij,ij->i", w, w)
                               - np.einsum("ij,ij->i", u, w) ** 2, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        k = np.where(ab * bc * ca > 0.0, 2.0 * np.abs(cross) / (ab * bc * ca), 0.0)
    if len(k) == 0:
        return np.zeros(len(xy))
    return np.concatenate([k[:1], k, k[-1:]])


def windowed_curvature(heading: np.ndarray, s: np.ndarray, window: float) -> np.ndarray:
    """Signed curvature (K,) of a planar path from its unwrapped heading (K,) at arc lengths s (K,):
    the heading's change over ``window`` m of arc length centred on each point (one-sided, shorter,
    at the ends). The reference's yaw rate v kappa is what the horizon's model inverts for the
    feed-forward steering, step by step: the curvature of three neighbouring points (Menger's)
    of a path resampled every 0.25 m swings by 0.05 1/m from point to point where the path
    zig-zags by a millimetre (a fairing's or tight path's solution, an anchor on a chord), i.e.
    0.3 rad/s at 6 m/s and a steering feed-forward that jumps by more than the steering's rate
    limit every step; over a metre the same path bends as smoothly as it looks."""
    if len(s) < 2:
        return np.zeros_like(s)
    lo = np.clip(s - 0.5 * window, s[0], s[-1])
    hi = np.clip(s + 0.5 * window, s[0], s[-1])
    return (np.interp(hi, s, heading) - np.interp(lo, s, heading)) / np.maximum(hi - lo, 1e-9)


def arc_lengths(xy: np.ndarray) -> np.ndarray:
    """Arc length (K,) at each point of a polyline (K, d), by its chords (0 at the first)."""
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(xy, axis=0), axis=1))])


def path_heading(xy: np.ndarray) -> np.ndarray:
    """Unwrapped yaw (K,) of a polyline (K, d >= 2) in the horizontal plane: its tangents by central
    differences (one-sided at the ends); 0 for a single point."""
    if len(xy) < 2:
        return np.zeros(len(xy))
    d = np.gradient(xy, axis=0)
    return np.unwrap(np.arctan2(d[:, 1], d[:, 0]))


def heading_curvature(xy: np.ndarray, window: float = CURVATURE_WINDOW) -> np.ndarray:
    """``windowed_curvature`` of a planar polyline (K, 2) from its points."""
    if len(xy) < 2:
        return np.zeros(len(xy))
    return windowed_curvature(path_heading(xy), arc_lengths(xy), window)


def curvature_rate(xy: np.ndarray, s: np.ndarray) -> np.ndarray:
    """|d kappa / ds| (K,) of a planar polyline (K, 2) at arc lengths s (K,): the change of its
    windowed signed curvature (``heading_curvature``) over ``RATE_WINDOW``."""
    return np.abs(windowed_curvature(heading_curvature(xy), s, RATE_WINDOW))


def plan_speed(xy: np.ndarray, v_desired: float, a_lat_max: float, a_accel: float, a_decel: float,
               v_start: float, v_end: float | None = None,
               kappa_cap: float = np.inf, kappa_rate_max: float = np.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Speed profile for the path xy (K, d): returns (s (K,), kappa (K,), v (K,)).

    kappa is the largest Menger curvature of each point and its two neighbours (a
    conservative estimate); v_start is the robot's speed: the profile starts at it (no faster than
    the centripetal limit there), and a cap v_desired below it ((K,): a slower stretch to yield
    or follow) is reached by braking from it at a_decel, not by a step: a plan must join the
    speed the robot has, or its reference falls behind the robot at once and the tracking brakes
    hard to catch it. v_end: the speed required at the last point (None: free; a stop shorter
    than braking at a_decel allows starts the braking at once).
    ``kappa_cap``: the curvature the centripetal limit takes at most (a path that its fairing
    will bring within it). ``kappa_rate_max`` (1/(m s)): the steering's rate limit as a rate of
    curvature (module docstring; a planar path's speed is capped by it like v_desired, reached by
    braking from v_start).
    """
    s = arc_lengths(xy)
    if np.isfinite(kappa_rate_max) and xy.shape[1] == 2 and len(xy) > 2:
        rate = curvature_rate(xy, s)
        with np.errstate(divide="ignore"):
            v_desired = np.minimum(v_desired, np.where(rate > 0.0, kappa_rate_max / rate, np.inf))
    k = menger_curvature(xy)
    kappa = np.maximum(k, np.maximum(np.roll(k, 1), np.roll(k, -1)))
    kappa[0], kappa[-1] = max(k[0], k[min(1, len(k) - 1)]), max(k[-1], k[max(len(k) - 2, 0)])
    with np.errstate(divide="ignore"):
        w_bend = a_lat_max / np.clip(kappa, 1e-12, kappa_cap)     # the centripetal limit on v^2
    w0 = max(v_start, 0.0) ** 2
    w_cap = np.maximum(np.square(v_desired), w0 - 2.0 * a_decel * s)   # the cap as reached by braking from v_start
    w = np.minimum(w_cap, w_bend)
    w[0] = min(w0, w_bend[0])      # the passes on v^2 (module docstring), each in closed form:
    up = 2.0 * a_accel * s         # forward: w_k = min(w_k, min_{j<k} w_j + 2 a_acc (s_k - s_j))
    w[1:] = np.minimum(w[1:], np.minimum.accumulate(w[:-1] - up[:-1]) + up[1:])
    if v_end is not None:
        w[-1] = min(w[-1], v_end * v_end)
    down = 2.0 * a_decel * s       # backward: w_k = min(w_k, min_{j>k} w_j + 2 a_dec (s_j - s_k))
    w[:-1] = np.minimum(w[:-1], np.minimum.accumulate((w[1:] + down[1:])[::-1])[::-1] - down[:-1])
    return s, kappa, np.sqrt(w)


def arrival_times(s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Time at each path point (K,) for speeds v (K,) along arc lengths s (K,), starting at 0."""
    vm = v[:-1] + v[1:]
    with np.errstate(divide="ignore"):
        dt = np.where(vm > 0.0, 2.0 * np.diff(s) / vm, np.inf)
    return np.concatenate([[0.0], np.cumsum(dt)])


def step_times(s: np.ndarray, v: np.ndarray, t0: float, beta: float) -> np.ndarray:
    """When the speed-planned path (arc lengths s (K,), speeds v (K,)) reaches arc length k beta,
    k = 0, 1, ..: the step times of the next integration of eq. (xi_r) (the path's own sampling
    may differ from the integration's, e.g. after fairing). Only reached points count."""
    t = arrival_times(s, v)
    ok = np.isfinite(t)
    if not np.any(ok):
        return np.array([t0])
    s_ok = s[ok]
    return t0 + np.interp(np.arange(0.0, s_ok[-1] + 1e-9, beta), s_ok, t[ok])


def smooth_path(raw: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian smoothing of a polyline (K, d) with std sigma (samples) that keeps its first point:
    the offset smoothing makes there fades out over 3 sigma samples along the quintic smoothstep
    1 - (10 x^3 - 15 x^4 + 6 x^5), whose first and second derivatives vanish at both ends, so the
    fade adds no kink and no curvature step where it ends (a linear fade did: a one-sample
    curvature dip that the timed reference turned into a yaw-rate spike)."""
    xy = gaussian_filter1d(raw, sigma=max(sigma, 1e-6), axis=0, mode="nearest")
    x = np.clip(np.arange(len(xy)) / max(3.0 * sigma, 1.0), 0.0, 1.0)
    fade = 1.0 - x ** 3 * (10.0 - 15.0 * x + 6.0 * x ** 2)
    return xy + fade[:, None] * (raw[0] - xy[0])
