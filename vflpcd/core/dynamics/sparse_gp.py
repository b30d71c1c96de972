"""Sparse GP (FITC) regression of the model error d(z), paper section II-C.

One independent GP per output a in {1..n_y}, each with the squared-exponential kernel

    k^a(z_i, z_j) = sf2_a exp(-1/2 |z_i - z_j|^2 / ell_a^2)

and its own noise variance sn2_a. ``exact_gp_predict`` is eq. (mean_covariance) for
reference; ``FITCGP`` is eq. (FITC) with inducing inputs Z_m (m, n_z), written in the
numerically stable whitened form (L L^T = K_mm, V = L^-1 K_mn):

    Lambda = diag(K_nn - Q_nn) + sn2 I,       A = I + V Lambda^-1 V^T  (= L^-1 Sigma^-1 L^-T)
    alpha  = Sigma K_mn Lambda^-1 y = L^-T A^-1 V Lambda^-1 y,
    mean(z) = k_zm alpha,      var(z) = k_zz - k_zm (K_mm^-1 - Sigma) k_mz.

A ``FITCGP`` is immutable: ``add_sample`` (O(n_y m^2), Sherman-Morrison on A^-1) and
``refit`` (hyper-parameters + posterior, for a worker) both return a new object, so a
controller can swap the model it reads by one reference assignment.

Ill-conditioning policy: ``FITCGP.fit`` raises ``GPConditioningError`` when a Cholesky
factorisation fails, a condition number exceeds ``max_cond`` or anything is non-finite;
``refit`` catches it, logs one ``event=gp_refit_rejected ...`` line and returns the
previous model unchanged (the last good GP is kept).
"""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve, cholesky, solve_triangular
from scipy.optimize import minimize
from scipy.spatial.distance import cdist

log = logging.getLogger(__name__)

LOG_2PI = float(np.log(2.0 * np.pi))

#: Default L-BFGS-B bounds on (log sf2, log ell, log sn2).
DEFAULT_BOUNDS = ((np.log(1e-6), np.log(1e4)), (np.log(1e-3), np.log(1e3)), (np.log(1e-6), np.log(1e2)))


class GPConditioningError(ArithmeticError):
    """A GP posterior could not be built reliably (Cholesky failure, condition number above
    the threshold, or non-finite data/result)."""


@dataclass(frozen=True)
class SEHyper:
    """SE-kernel hyper-parameters, one entry per output: sf2, ell, sn2 each (n_y,)."""

    sf2: np.ndarray
    ell: np.ndarray
    sn2: np.ndarray

    def __post_init__(self) -> None:
        for name in ("sf2", "ell", "sn2"):
            v = np.array(getattr(self, name), dtype=float).reshape(-1)
            v.flags.writeable = False
            object.__setattr__(self, name, v)
        if not (self.sf2.shape == self.ell.shape == self.sn2.shape):
            raise ValueError("sf2, ell and sn2 must have the same length n_y")

    @property
    def n_y(self) -> int:
        return self.sf2.shape[0]

    def __reduce__(self):
        """Unpickled through the constructor, so its arrays are read-only again (``FITCGP.__reduce__``)."""
        return SEHyper, (self.sf2, self.ell, self.sn2)

    @functools.cached_property
    def inv_ell2(self) -> np.ndarray:
        """1 / ell^2 (n_y,)."""
        return 1.0 / self.ell**2

    @functools.cached_property
    def nh_inv_ell2(self) -> np.ndarray:
        """-1 / (2 ell^2) (n_y, 1), the exponent's factor of the SE kernel."""
        return (-0.5 / self.ell**2)[:, None]

    @classmethod
    def from_log(cls, theta: np.ndarray) -> "SEHyper":
        """From theta (n_y, 3) = [log sf2, log ell, log sn2] per output."""
        t = np.asarray(theta, dtype=float).reshape(-1, 3)
        return cls(np.exp(t[:, 0]), np.exp(t[:, 1]), np.exp(t[:, 2]))

    def log(self) -> np.ndarray:
        """theta (n_y, 3) = [log sf2, log ell, log sn2] per output."""
        return np.log(np.column_stack([self.sf2, self.ell, self.sn2]))


def sq_distances(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """|A_i - B_j|^2 (na, nb) for A (na, n_z), B (nb, n_z), by broadcasting: for the few rows of a
    tick's GP mean, sample and ALD test, where ``cdist``'s fixed cost per call dominated."""
    e = np.atleast_2d(A)[:, None, :] - np.atleast_2d(B)[None]
    return np.einsum("nmi,nmi->nm", e, e)


def se_kernel(A: np.ndarray, B: np.ndarray, sf2: float, ell: float) -> np.ndarray:
    """SE kernel matrix k(A_i, B_j) for A (na, n_z), B (nb, n_z) -> (na, nb)."""
    return sf2 * np.exp(-0.5 / ell**2 * cdist(np.atleast_2d(A), np.atleast_2d(B), "sqeuclidean"))


def _check_data(Z: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Z = np.asarray(Z, dtype=float)
    Y = np.asarray(Y, dtype=float)
    if Z.ndim != 2 or Y.ndim != 2 or Z.shape[0] != Y.shape[0]:
        raise ValueError(f"expected Z (n, n_z) and Y (n, n_y), got {Z.shape} and {Y.shape}")
    return Z, Y


def exact_gp_predict(Z: np.ndarray, Y: np.ndarray, Zs: np.ndarray, hyp: SEHyper
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Full GP, eq. (mean_covariance). Z (n, n_z), Y (n, n_y), Zs (N, n_z) ->
    mean (N, n_y), latent variance (N, n_y)."""
    Z, Y = _check_data(Z, Y)
    Zs = np.atleast_2d(np.asarray(Zs, dtype=float))
    mean = np.empty((Zs.shape[0], hyp.n_y))
    var = np.empty_like(mean)
    for a in range(hyp.n_y):
        K = se_kernel(Z, Z, hyp.sf2[a], hyp.ell[a]) + hyp.sn2[a] * np.eye(Z.shape[0])
        c = (cholesky(K, lower=True), True)
        Ks = se_kernel(Zs, Z, hyp.sf2[a], hyp.ell[a])
        mean[:, a] = Ks @ cho_solve(c, Y[:, a])
        var[:, a] = hyp.sf2[a] - np.einsum("ij,ji->i", Ks, cho_solve(c, Ks.T))
    return mean, var


def _chol(M: np.ndarray, what: str) -> np.ndarray:
    try:
        return cholesky(M, lower=True)
    except np.linalg.LinAlgError as err:
        raise GPConditioningError(f"cholesky_failed:{what}") from err


# --------------------------------------------------------------------------- FITC LML


def fitc_lml_single(Zm: np.ndarray, Z: np.ndarray, y: np.ndarray, theta: np.ndarray,
                    jitter: float = 1e-8, *, D2mm: np.ndarray | None = None,
                    D2nm: np.ndarray | None = None) -> tuple[float, np.ndarray]:
    """FITC log marginal likelihood of one output and its analytic gradient.

    log p(y) = -1/2 y^T C^-1 y - 1/2 log|C| - n/2 log 2 pi with C = Q_nn + Lambda (eq. FITC).
    Zm (m, n_z), Z (n, n_z), y (n,), theta (3,) = [log sf2, log ell, log sn2]
    -> (lml, d lml / d theta (3,)). dL/dtheta = 1/2 tr(M dC/dtheta), M = beta beta^T - C^-1,
    evaluated in O(n m^2) without forming n x n matrices.
    """
    sf2, ell, sn2 = np.exp(np.asarray(theta, dtype=float))
    ell2 = ell * ell
    m, n = Zm.shape[0], Z.shape[0]
    D2mm = cdist(Zm, Zm, "sqeuclidean") if D2mm is None else D2mm
    D2nm = cdist(Z, Zm, "sqeuclidean") if D2nm is None else D2nm
    Rmm = np.exp(-0.5 / ell2 * D2mm)
    Knm = sf2 * np.exp(-0.5 / ell2 * D2nm)                      # (n, m)
    Kmm = sf2 * (Rmm + jitter * np.eye(m))
    L = _chol(Kmm, "Kmm")
    V = solve_triangular(L, Knm.T, lower=True)                  # (m, n)
    lam = np.maximum(sf2 - np.einsum("ij,ij->j", V, V), 0.0) + sn2
    Vl = V / lam                                                # V Lambda^-1
    La = _chol(np.eye(m) + Vl @ V.T, "A")
    r = y / lam
    t = cho_solve((La, True), V @ r)
    beta = r - (V.T @ t) / lam                                  # C^-1 y
    # log|C| = log|Lambda| + log|A|
    lml = -0.5 * (y @ beta) - 0.5 * (np.log(lam).sum() + 2.0 * np.log(np.diag(La)).sum()) \
        - 0.5 * n * LOG_2PI

    # d = diag(M) = beta^2 - diag(C^-1), C^-1 = Lambda^-1 - Vl^T A^-1 Vl.
    G = solve_triangular(La, Vl, lower=True)
    d = beta**2 - (1.0 / lam - np.einsum("ij,ij->j", G, G))
    P = solve_triangular(L, V, lower=True, trans="T")           # K_mm^-1 K_mn (m, n)
    Cinv_Pt = P.T / lam[:, None] - Vl.T @ cho_solve((La, True), Vl @ P.T)
    H = np.outer(beta, P @ beta) - Cinv_Pt - d[:, None] * P.T   # (M - diag d) P^T, (n, m)
    PH = P @ H                                                  # (m, m)

    def tr_dC(dKnm: np.ndarray, dKmm: np.ndarray, dKnn: float, dsn2: float) -> float:
        # tr(M dC), dC = dQ + diag(dK_nn - dQ) + dsn2 I
        return (2.0 * np.sum(dKnm * H) - np.sum(dKmm * PH)
                + dKnn * d.sum() + dsn2 * d.sum())

    g_sf2 = tr_dC(Knm, Kmm, sf2, 0.0)
    g_ell = tr_dC(Knm * D2nm / ell2, sf2 * Rmm * D2mm / ell2, 0.0, 0.0)
    g_sn2 = sn2 * d.sum()
    return float(lml), 0.5 * np.array([g_sf2, g_ell, g_sn2])


def log_marginal_likelihood(Zm: np.ndarray, Z: np.ndarray, Y: np.ndarray, hyp: SEHyper,
                            jitter: float = 1e-8) -> float:
    """Sum over outputs of the FITC log marginal likelihood. Zm (m, n_z), Z (n, n_z), Y (n, n_y)."""
    Z, Y = _check_data(Z, Y)
    theta = hyp.log()
    return float(sum(fitc_lml_single(Zm, Z, Y[:, a], theta[a], jitter)[0] for a in range(hyp.n_y)))


def fit_hyperparameters(Zm: np.ndarray, Z: np.ndarray, Y: np.ndarray, hyp0: SEHyper,
                        bounds=DEFAULT_BOUNDS, jitter: float = 1e-8, maxiter: int = 100) -> SEHyper:
    """Maximise the FITC LML per output with L-BFGS-B (analytic gradients), inducing inputs
    fixed. Zm (m, n_z), Z (n, n_z), Y (n, n_y); returns the fitted ``SEHyper``."""
    Z, Y = _check_data(Z, Y)
    Zm = np.asarray(Zm, dtype=float)
    D2mm, D2nm = cdist(Zm, Zm, "sqeuclidean"), cdist(Z, Zm, "sqeuclidean")
    theta0 = np.clip(hyp0.log(), [b[0] for b in bounds], [b[1] for b in bounds])
    out = np.empty_like(theta0)

    for a in range(Y.shape[1]):
        def neg(th: np.ndarray, a: int = a) -> tuple[float, np.ndarray]:
            try:
                f, g = fitc_lml_single(Zm, Z, Y[:, a], th, jitter, D2mm=D2mm, D2nm=D2nm)
            except GPConditioningError:
                return 1e25, np.zeros(3)
            if not (np.isfinite(f) and np.all(np.isfinite(g))):
                return 1e25, np.zeros(3)
            return -f, -g

        res = minimize(neg, theta0[a], jac=True, method="L-BFGS-B", bounds=bounds,
                       options={"maxiter": maxiter})
        out[a] = res.x
    return SEHyper.from_log(out)


# --------------------------------------------------------------------------- FITC model


@dataclass(frozen=True, eq=False)
class FITCGP:
    """Immutable FITC posterior (eq. FITC) for n_y independent outputs.

    Zm (m, n_z) inducing inputs; hyp per-output hyper-parameters; n number of training
    samples folded in. Internal per-output arrays: Linv (n_y, m, m) = L^-1, Ainv (n_y, m, m)
    = A^-1, c (n_y, m) = V Lambda^-1 y, alpha (n_y, m); ``W`` (n_y, m, m) = K_mm^-1 - Sigma
    = L^-T (I - A^-1) L^-1, for the variance only, is computed when first asked for (a sample
    folded in every tick would otherwise update it for nothing: the controller uses the mean).
    Build with ``FITCGP.fit``; update with ``add_sample`` (returns a new object).
    """

    Zm: np.ndarray
    hyp: SEHyper
    jitter: float
    max_cond: float
    n: int
    Linv: np.ndarray
    Ainv: np.ndarray
    c: np.ndarray
    alpha: np.ndarray

    def __post_init__(self) -> None:
        for name in ("Zm", "Linv", "Ainv", "c", "alpha"):
            getattr(self, name).flags.writeable = False
        # Prediction constants: -1/(2 ell^2) and 1/ell^2 per output (the hyper-parameters'), alpha scaled by sf2.
        object.__setattr__(self, "_inv_ell2", self.hyp.inv_ell2)
        object.__setattr__(self, "_nh_inv_ell2", self.hyp.nh_inv_ell2)

    def __reduce__(self):
        """Unpickled (a refit comes back from a worker process) through the constructor, so its
        arrays are read-only again, the type the compiled update was warmed for (``loops``)."""
        return FITCGP, (self.Zm, self.hyp, self.jitter, self.max_cond, self.n, self.Linv, self.Ainv, self.c,
                        self.alpha)

    @functools.cached_property
    def _alpha_sf(self) -> np.ndarray:
        """alpha scaled by sf2 (n_y, m), for the single-point mean and its Jacobian."""
        return self.hyp.sf2[:, None] * self.alpha

    @property
    def m(self) -> int:
        return self.Zm.shape[0]

    @property
    def n_z(self) -> int:
        return self.Zm.shape[1]

    @property
    def n_y(self) -> int:
        return self.hyp.n_y

    # ---------------------------------------------------------------- construction
    @classmethod
    def fit(cls, Zm: np.ndarray, Z: np.ndarray, Y: np.ndarray, hyp: SEHyper,
            jitter: float = 1e-8, max_cond: float = 1e12) -> "FITCGP":
        """FITC posterior from inducing inputs Zm (m, n_z) and training data Z (n, n_z),
        Y (n, n_y) (n may be 0). Raises ``GPConditioningError`` if the data or a result is
        non-finite, a Cholesky fails, or cond(K_mm) or cond(A) exceeds ``max_cond``."""
        Zm = np.array(Zm, dtype=float)
        Z, Y = _check_data(Z, Y)
        if Zm.ndim != 2 or Zm.shape[0] < 1 or Zm.shape[1] != Z.shape[1] or Y.shape[1] != hyp.n_y:
            raise ValueError(f"shape mismatch: Zm {Zm.shape}, Z {Z.shape}, Y {Y.shape}, n_y {hyp.n_y}")
        if not (np.all(np.isfinite(Zm)) and np.all(np.isfinite(Z)) and np.all(np.isfinite(Y))):
            raise GPConditioningError("non_finite_data")
        if not all(np.all(np.isfinite(v)) and np.all(v > 0) for v in (hyp.sf2, hyp.ell, hyp.sn2)):
            raise GPConditioningError("bad_hyperparameters")
        m, n_y = Zm.shape[0], hyp.n_y
        I = np.eye(m)
        Linv, Ainv = np.empty((n_y, m, m)), np.empty((n_y, m, m))
        c, alpha = np.empty((n_y, m)), np.empty((n_y, m))
        D2mm, D2nm = cdist(Zm, Zm, "sqeuclidean"), cdist(Z, Zm, "sqeuclidean")
        for a in range(n_y):
            sf2, ell2, sn2 = hyp.sf2[a], hyp.ell[a] ** 2, hyp.sn2[a]
            Kmm = sf2 * (np.exp(-0.5 / ell2 * D2mm) + jitter * I)
            _check_cond(Kmm, max_cond, "Kmm")
            L = _chol(Kmm, "Kmm")
            Linv[a] = solve_triangular(L, I, lower=True)
            V = Linv[a] @ (sf2 * np.exp(-0.5 / ell2 * D2nm)).T           # (m, n)
            lam = np.maximum(sf2 - np.einsum("ij,ij->j", V, V), 0.0) + sn2
            A = I + (V / lam) @ V.T
            _check_cond(A, max_cond, "A")
            Ainv[a] = cho_solve((_chol(A, "A"), True), I)
            c[a] = V @ (Y[:, a] / lam)
        for a in range(n_y):
            alpha[a] = Linv[a].T @ (Ainv[a] @ c[a])
        gp = cls(Zm, hyp, float(jitter), float(max_cond), int(Z.shape[0]), Linv, Ainv, c, alpha)
        if not all(np.all(np.isfinite(v)) for v in (Linv, Ainv, alpha, gp.W)):
            raise GPConditioningError("non_finite_posterior")
        return gp

    def add_sample(self, z: np.ndarray, y: np.ndarray, loop=None) -> "FITCGP":
        """Fold one sample z (n_z,), y (n_y,) into the posterior in O(n_y m^2) and return the
        new model (inducing inputs and hyper-parameters unchanged).

        With v = L^-1 k_m(z), lambda = k(z,z) - v.v + sn2: A <- A + v v^T / lambda
        (Sherman-Morrison on A^-1), c <- c + v y / lambda. Raises ValueError on non-finite input.
        ``loop``: ``gp_kernel.add_sample_loop`` compiled (the same numbers), None for numpy.
        """
        z = np.asarray(z, dtype=float).reshape(-1)
        y = np.asarray(y, dtype=float).reshape(-1)
        if z.shape != (self.n_z,) or y.shape != (self.n_y,):
            raise ValueError(f"expected z ({self.n_z},), y ({self.n_y},); got {z.shape}, {y.shape}")
        if not all(map(math.isfinite, z.tolist() + y.tolist())):
            raise ValueError("non-finite sample")
        if loop is not None:
            Ainv, c, alpha = loop(self.Zm, self.hyp.sf2, self._nh_inv_ell2, self.hyp.sn2, self.Linv, self.Ainv,
                                  self.c, z, y)
            return FITCGP(self.Zm, self.hyp, self.jitter, self.max_cond, self.n + 1, self.Linv, Ainv, c, alpha)
        K = self.hyp.sf2[:, None] * np.exp(self._nh_inv_ell2 * sq_distances(self.Zm, z)[:, 0])   # (n_y, m)
        v = np.matmul(self.Linv, K[:, :, None])[:, :, 0]                  # (n_y, m)
        u = np.matmul(self.Ainv, v[:, :, None])                           # A^-1 v (n_y, m, 1)
        vv, vu = (v[:, None, :] @ np.concatenate([v[:, :, None], u], axis=2))[:, 0].T
        lam = np.maximum(self.hyp.sf2 - vv, 0.0) + self.hyp.sn2
        Ainv = self.Ainv - u * (u / (lam + vu)[:, None, None]).transpose(0, 2, 1)
        c = self.c + v * (y / lam)[:, None]
        alpha = np.matmul(self.Linv.transpose(0, 2, 1), np.matmul(Ainv, c[:, :, None]))[:, :, 0]
        return FITCGP(self.Zm, self.hyp, self.jitter, self.max_cond, self.n + 1,
                      self.Linv, Ainv, c, alpha)

    @functools.cached_property
    def W(self) -> np.ndarray:
        """K_mm^-1 - Sigma (n_y, m, m) = L^-T (I - A^-1) L^-1, the variance's matrix (read only)."""
        I = np.eye(self.m)
        W = np.array([self.Linv[a].T @ (I - self.Ainv[a]) @ self.Linv[a] for a in range(self.n_y)])
        W.flags.writeable = False
        return W

    # ---------------------------------------------------------------- prediction
    def _kernel_rows(self, Zs: np.ndarray) -> np.ndarray:
        D2 = sq_distances(np.asarray(Zs, dtype=float), self.Zm)                         # (N, m)
        return self.hyp.sf2[:, None, None] * np.exp(self._nh_inv_ell2[:, :, None] * D2)  # (n_y, N, m)

    def means(self, Zs: np.ndarray) -> np.ndarray:
        """Mean (eq. FITC) at Zs (N, n_z) -> (N, n_y); O(N m) per output."""
        return np.einsum("anm,am->na", self._kernel_rows(Zs), self.alpha)

    def predict(self, Zs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and latent variance (eq. FITC) at Zs (N, n_z) -> (N, n_y), (N, n_y).
        Cost O(N m) per output for the mean, O(N m^2) for the variance."""
        K = self._kernel_rows(Zs)
        mean = np.einsum("anm,am->na", K, self.alpha)
        var = self.hyp.sf2[None, :] - np.einsum("anm,amk,ank->na", K, self.W, K, optimize=True)
        return mean, np.maximum(var, 0.0)

    def mean(self, z: np.ndarray) -> np.ndarray:
        """Mean at one point z (n_z,) -> (n_y,)."""
        d2 = np.einsum("ij,ij->i", self.Zm - z, self.Zm - z)
        return np.einsum("ai,ai->a", np.exp(self._nh_inv_ell2 * d2), self._alpha_sf)

    def mean_jacobian(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean (n_y,) and its Jacobian d m / d z (n_y, n_z) at one point z (n_z,).

        Paper's dd/dz formula: dm_a/dz = sum_j alpha_aj k_a(z, z_j) (z_j - z) / ell_a^2."""
        diff = self.Zm - z                                                # (m, n_z): z_j - z
        Ka = np.exp(self._nh_inv_ell2 * np.einsum("ij,ij->i", diff, diff)) * self._alpha_sf
        return Ka.sum(axis=1), (Ka @ diff) * self._inv_ell2[:, None]


def _check_cond(M: np.ndarray, max_cond: float, what: str) -> None:
    if not np.all(np.isfinite(M)):
        raise GPConditioningError(f"non_finite:{what}")
    cond = np.linalg.cond(M)
    if not np.isfinite(cond) or cond > max_cond:
        raise GPConditioningError(f"cond_{what}={cond:.3g}")


def refit(prev: FITCGP | None, Zm: np.ndarray, Z: np.ndarray, Y: np.ndarray,
          hyp0: SEHyper | None = None, *, optimise: bool = True, bounds=DEFAULT_BOUNDS,
          jitter: float = 1e-8, max_cond: float = 1e12, maxiter: int = 100) -> FITCGP | None:
    """Full refit for a worker: hyper-parameters (if ``optimise``) then the FITC posterior.

    Zm (m, n_z), Z (n, n_z), Y (n, n_y). Starts from ``hyp0`` or else ``prev.hyp``. Returns a
    NEW ``FITCGP``; if the fit is ill-conditioned or non-finite it logs one line
    ``event=gp_refit_rejected reason=... n=... m=... kept=previous|none`` (WARNING) and
    returns ``prev`` unchanged.
    """
    if hyp0 is None:
        if prev is None:
            raise ValueError("refit needs hyp0 when there is no previous model")
        hyp0 = prev.hyp
    try:
        Z, Y = _check_data(Z, Y)
        if not (np.all(np.isfinite(Zm)) and np.all(np.isfinite(Z)) and np.all(np.isfinite(Y))):
            raise GPConditioningError("non_finite_data")
        hyp = fit_hyperparameters(Zm, Z, Y, hyp0, bounds, jitter, maxiter) if optimise else hyp0
        return FITCGP.fit(Zm, Z, Y, hyp, jitter, max_cond)
    except GPConditioningError as err:
        log.warning("event=gp_refit_rejected reason=%s n=%d m=%d kept=%s", err, len(Z),
                    np.shape(Zm)[0], "previous" if prev is not None else "none")
        return prev
