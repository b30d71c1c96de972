"""Least-squares DMDc and EDMDc baselines for the learned dynamics (numpy only).

Both fit a :class:`vflpcd.core.dynamics.lifted.LiftedLinearModel` from one-step pairs
(x_k, u_k, x_{k+1}) taken inside windows of the training logs:

* windows of ``window_s`` seconds (H = round(window_s / dt) steps, H + 1 rows) start every
  ``stride`` rows of each log and never straddle a gap (``Log.window_starts``);
* each window is moved to its first pose's frame (``to_window_frame``), and all its H
  consecutive pairs are used, so the model learns the dynamics in exactly the coordinates
  in which it is rolled out (poses relative to the window start);
* states and controls are normalised per channel with the mean and standard deviation of
  the training pairs (a channel with std < 1e-9 gets std 1), stored in the model.

In normalised coordinates the lifted state is Z_n = [x_n, phi(x), 1]. The least-squares
problem regresses Z_n(k+1) without its constant on [Z_n(k), u_n(k)] over all pairs:

    min_W  sum_k |Z'_k - W^T R_k|^2 / P + ridge |W_without_constant|^2,   R_k = [Z_n(k), u_n(k)]

(P the number of pairs; the constant's coefficient is not penalised), solved through the
normal equations accumulated log by log. The constant's row is fixed (1 -> 1), and
``to_physical`` turns (A_n, B_n) into the physical A, B on U = [x, phi(x), 1].

Dictionaries phi (standardised with their training mean/std):

* ``"dmdc"``: none -- U = [x, 1], x_{k+1} = A x_k + B u_k + c (the affine offset c comes
  from the normalisation and the intercept of the fit);
* ``"vehicle"`` (ground vehicle states [X, Y, yaw|psi, vx, vy, yaw_rate|omega]): the
  world-velocity terms vx cos psi, vx sin psi, vy cos psi, vy sin psi; cos psi, sin psi;
  the Coriolis products vx r, vy r; the slip-like ratios vy / max(vx, v_floor),
  r / max(vx, v_floor) with v_floor = 1 m/s; the squares vx^2, vy^2, r^2 (13 features);
* ``"rff"``: m random Fourier features sqrt(2/m) cos(w_j . x_n + b_j) of the normalised
  state, w_j ~ N(0, I / bandwidth^2), b_j ~ U(0, 2 pi), drawn from numpy's default_rng(seed);
* ``"auto"``: "vehicle" when the state names allow it, otherwise "rff".
"""

from __future__ import annotations

import logging
import time
from typing import Sequence

import numpy as np

from vflpcd.core.dynamics.lifted import LiftedLinearModel, PoseLayout, to_physical, to_window_frame
from vflpcd.training.datasets import Log

log = logging.getLogger("vflpcd.training.dmdc")

V_FLOOR = 1.0           # m/s, lower bound of the speed in the slip-like ratios
_STD_FLOOR = 1e-9
_VX_NAMES = ("vx",)
_VY_NAMES = ("vy",)
_RATE_NAMES = ("yaw_rate", "omega", "r")


def _find(names: Sequence[str], candidates: Sequence[str]) -> int | None:
    return next((list(names).index(c) for c in candidates if c in names), None)


def vehicle_dictionary_applies(state_names: Sequence[str]) -> bool:
    """True if the names hold a planar pose and vx, vy and a yaw rate."""
    return (PoseLayout.of(state_names).kind == "planar" and _find(state_names, _VX_NAMES) is not None
            and _find(state_names, _VY_NAMES) is not None and _find(state_names, _RATE_NAMES) is not None)


class DictionaryModel(LiftedLinearModel):
    """A lifted linear model with a fixed dictionary (module docstring); rho(x) = [phi_std(x), 1].

    dictionary: "dmdc", "vehicle" or "rff"; rff_W (n_x, m) and rff_b (m,) for "rff";
    phi_mean, phi_std (n_phi,) the feature standardisation."""

    def __init__(self, A, B, *, dictionary: str, phi_mean: np.ndarray, phi_std: np.ndarray,
                 rff_W: np.ndarray | None = None, rff_b: np.ndarray | None = None, **kwargs) -> None:
        super().__init__(A, B, **kwargs)
        self.dictionary = dictionary
        self.phi_mean = np.asarray(phi_mean, dtype=np.float64)
        self.phi_std = np.asarray(phi_std, dtype=np.float64)
        self.rff_W = None if rff_W is None else np.asarray(rff_W, dtype=np.float64)
        self.rff_b = None if rff_b is None else np.asarray(rff_b, dtype=np.float64)
        if self.n_K != self.n_x + self.phi_mean.shape[0] + 1:
            raise ValueError(f"n_K = {self.n_K} does not match n_x + {self.phi_mean.shape[0]} features + 1")

    def features(self, x: np.ndarray) -> np.ndarray:
        """Raw dictionary phi(x): x (..., n_x) window frame -> (..., n_phi)."""
        return dictionary_features(self.dictionary, x, self.state_names, self.x_mean, self.x_std,
                                   self.rff_W, self.rff_b)

    def rho(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        phi = (self.features(x) - self.phi_mean) / self.phi_std
        return np.concatenate([phi, np.ones(x.shape[:-1] + (1,))], axis=-1)


def dictionary_features(kind: str, x: np.ndarray, state_names: Sequence[str], x_mean: np.ndarray,
                        x_std: np.ndarray, rff_W: np.ndarray | None = None,
                        rff_b: np.ndarray | None = None) -> np.ndarray:
    """phi(x) of the named dictionary: x (..., n_x) -> (..., n_phi) (n_phi = 0 for "dmdc")."""
    x = np.asarray(x, dtype=np.float64)
    if kind == "dmdc":
        return np.zeros(x.shape[:-1] + (0,))
    if kind == "vehicle":
        lay = PoseLayout.of(state_names)
        psi = x[..., lay.heading]
        vx = x[..., _find(state_names, _VX_NAMES)]
        vy = x[..., _find(state_names, _VY_NAMES)]
        r = x[..., _find(state_names, _RATE_NAMES)]
        c, s = np.cos(psi), np.sin(psi)
        vfl = np.maximum(vx, V_FLOOR)
        return np.stack([vx * c, vx * s, vy * c, vy * s, c, s, vx * r, vy * r,
                         vy / vfl, r / vfl, vx * vx, vy * vy, r * r], axis=-1)
    if kind == "rff":
        xn = (x - x_mean) / x_std
        m = rff_b.shape[0]
        return np.sqrt(2.0 / m) * np.cos(xn @ rff_W + rff_b)
    raise ValueError(f"unknown dictionary {kind!r} (have: dmdc, vehicle, rff)")


def window_pairs(logs: Sequence[Log], window_steps: int, stride: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-step pairs inside window-frame windows: (X (P, n_x), U (P, n_u), X_next (P, n_x))."""
    Xs, Us, Ys = [], [], []
    for lg in logs:
        starts = lg.window_starts(window_steps + 1, stride)
        if starts.size == 0:
            continue
        rows = starts[:, None] + np.arange(window_steps + 1)[None, :]
        w = to_window_frame(lg.states[rows], lg.state_names)  # (M, H + 1, n_x)
        u = lg.controls[rows[:, :-1]]                          # (M, H, n_u)
        Xs.append(w[:, :-1].reshape(-1, lg.states.shape[1]))
        Ys.append(w[:, 1:].reshape(-1, lg.states.shape[1]))
        Us.append(u.reshape(-1, lg.controls.shape[1]))
    if not Xs:
        raise ValueError(f"no window of {window_steps + 1} rows in the training logs")
    return np.concatenate(Xs), np.concatenate(Us), np.concatenate(Ys)


def check_logs(logs: Sequence[Log], what: str = "training") -> tuple[tuple[str, ...], tuple[str, ...], float]:
    """(state names, control names, dt) shared by all logs; ValueError if none or they differ."""
    if not logs:
        raise ValueError(f"no {what} logs")
    first = logs[0]
    for lg in logs[1:]:
        if (lg.state_names, lg.control_names) != (first.state_names, first.control_names) \
                or abs(lg.dt - first.dt) > 1e-9:
            raise ValueError(f"log {lg.name} differs from {first.name} in channel names or dt")
    return first.state_names, first.control_names, first.dt


def robust_std(a: np.ndarray) -> np.ndarray:
    """Per-column std of a (N, n); columns with (almost) none get 1 so that normalising is safe."""
    s = a.std(axis=0)
    return np.where(s < _STD_FLOOR, 1.0, s)


def fit_lifted(logs: Sequence[Log], *, dictionary: str = "dmdc", window_s: float = 2.0, stride: int = 5,
               ridge: float = 0.0, n_features: int = 64, bandwidth: float = 2.0, seed: int = 0,
               chunk: int = 200_000) -> DictionaryModel:
    """Fit a dictionary model by (ridge) least squares over window-frame one-step pairs.

    logs: training logs with equal channel names and dt; window_s: window length, s; stride:
    rows between window starts; ridge: Tikhonov weight on the normalised regressors; the rff
    options (n_features, bandwidth in normalised state units, seed) only for "rff"."""
    state_names, control_names, dt = check_logs(logs)
    if dictionary == "auto":
        dictionary = "vehicle" if vehicle_dictionary_applies(state_names) else "rff"
    if dictionary == "vehicle" and not vehicle_dictionary_applies(state_names):
        raise ValueError(f"the vehicle dictionary needs X, Y, yaw|psi, vx, vy, yaw_rate|omega; got {state_names}")
    if ridge < 0.0:
        raise ValueError(f"ridge must be >= 0, got {ridge}")
    t0 = time.perf_counter()
    H = int(round(window_s / dt))
    if H < 1:
        raise ValueError(f"window_s = {window_s} s is shorter than one step of {dt} s")
    X, U, Y = window_pairs(logs, H, stride)
    P, n_x = X.shape
    x_mean, x_std = X.mean(axis=0), robust_std(X)
    u_mean, u_std = U.mean(axis=0), robust_std(U)
    rff_W = rff_b = None
    if dictionary == "rff":
        rng = np.random.default_rng(seed)
        rff_W = rng.normal(0.0, 1.0 / bandwidth, size=(n_x, n_features))
        rff_b = rng.uniform(0.0, 2.0 * np.pi, size=n_features)

    def phi(x):
        return dictionary_features(dictionary, x, state_names, x_mean, x_std, rff_W, rff_b)

    n_phi = phi(X[:1]).shape[1]
    phi_sum, phi_sq = np.zeros(n_phi), np.zeros(n_phi)
    for a in range(0, P, chunk):
        f = phi(X[a:a + chunk])
        phi_sum += f.sum(axis=0)
        phi_sq += (f * f).sum(axis=0)
    phi_mean = phi_sum / P
    phi_std = np.sqrt(np.maximum(phi_sq / P - phi_mean ** 2, 0.0))
    phi_std = np.where(phi_std < _STD_FLOOR, 1.0, phi_std)

    n_K = n_x + n_phi + 1
    n_u = U.shape[1]

    def lifted_n(x):
        ones = np.ones((x.shape[0], 1))
        return np.concatenate([(x - x_mean) / x_std, (phi(x) - phi_mean) / phi_std, ones], axis=1)

    G = np.zeros((n_K + n_u, n_K + n_u))
    C = np.zeros((n_K + n_u, n_K - 1))
    for a in range(0, P, chunk):
        R = np.concatenate([lifted_n(X[a:a + chunk]), (U[a:a + chunk] - u_mean) / u_std], axis=1)
        T = lifted_n(Y[a:a + chunk])[:, :-1]
        G += R.T @ R
        C += R.T @ T
    G /= P
    C /= P
    reg = np.full(n_K + n_u, ridge)
    reg[n_K - 1] = 0.0  # the constant (intercept) is not penalised
    try:
        W = np.linalg.solve(G + np.diag(reg), C)
    except np.linalg.LinAlgError:
        W = np.linalg.lstsq(G + np.diag(reg), C, rcond=None)[0]
    A_n = np.zeros((n_K, n_K))
    B_n = np.zeros((n_K, n_u))
    A_n[:-1] = W[:n_K].T
    A_n[-1, -1] = 1.0
    B_n[:-1] = W[n_K:].T
    A, B = to_physical(A_n, B_n, x_mean, x_std, u_mean, u_std)
    model = DictionaryModel(A, B, dictionary=dictionary, phi_mean=phi_mean, phi_std=phi_std, rff_W=rff_W,
                            rff_b=rff_b, state_names=state_names, control_names=control_names, dt=dt,
                            x_mean=x_mean, x_std=x_std, u_mean=u_mean, u_std=u_std)
    resid = Y[:chunk] - (model.lift(X[:chunk]) @ A.T + U[:chunk] @ B.T)[:, :n_x]
    log.info("fitted %s model on %d pairs from %d logs: n_K=%d, ridge=%g, one-step RMS %.3g, %.2f s",
             dictionary, P, len(logs), n_K, ridge, float(np.sqrt(np.mean(resid ** 2))), time.perf_counter() - t0)
    return model


def fit_dmdc(logs: Sequence[Log], *, window_s: float = 2.0, stride: int = 5, ridge: float = 0.0) -> DictionaryModel:
    """DMDc: x_{k+1} = A x_k + B u_k (+ the affine offset of the normalisation) by least squares,
    U = [x, 1], n_K = n_x + 1. See :func:`fit_lifted`."""
    return fit_lifted(logs, dictionary="dmdc", window_s=window_s, stride=stride, ridge=ridge)


def fit_edmdc(logs: Sequence[Log], *, dictionary: str = "auto", window_s: float = 2.0, stride: int = 5,
              ridge: float = 1e-6, n_features: int = 64, bandwidth: float = 2.0, seed: int = 0) -> DictionaryModel:
    """EDMDc with a fixed dictionary ("auto", "vehicle" or "rff"; module docstring) and ridge
    regularisation. See :func:`fit_lifted`."""
    if dictionary == "dmdc":
        raise ValueError("EDMDc needs a nonlinear dictionary (auto, vehicle or rff)")
    return fit_lifted(logs, dictionary=dictionary, window_s=window_s, stride=stride, ridge=ridge,
                      n_features=n_features, bandwidth=bandwidth, seed=seed)
