"""Real-time-iteration NMPC: the MPC-CBF problem of ``nmpc_cbf`` with one Gauss-Newton SQP step per tick.

The model, horizon, cost, DCBF constraints, reference, obstacle slots, warm start and fallback are
those of :class:`vflpcd.controllers.nmpc_cbf.NmpcCbf` (config/controllers/nmpc_cbf.toml); what
differs is the solver (config/controllers/nmpc_rti.toml), the real-time iteration of acados:
from w = the previous solution shifted by one step (``NmpcCbf._initial_guess``), one QP in the
step dw per tick, then w <- w + dw.

The QP (Gauss-Newton: the cost is quadratic in w, so its Hessian is exact and the curvature of
the dynamics and of the DCBF rows is left out, which keeps the QP convex), written as the optimal
control QP that HPIPM (the structure-exploiting interior-point QP solver of acados) solves, stage
by stage:

    stage state   x~_k = [dX_k (6), z_k]      z_k = d delta_{k-1}: the previous steering step,
    stage control u~_k = [dU_k (2), ds_k (S)]  so that the steering-rate row is a stage row
    dynamics      dX_{k+1} = A_k dX_k + B_k dU_k - F_k,   z_{k+1} = d delta_k
                  A_k, B_k = dF/dX, dF/dU at (X_k, U_k);  F_k = X_{k+1} - F(X_k, U_k) (the gap)
    rate rows     |delta_k + d delta_k - delta_{k-1} - z_k| <= delta_rate_max dt   (z_0 = 0)
    DCBF rows     h(X_{k+1}) - (1 - gamma) h(X_k) + s_k >= 0 linearised, with dX_{k+1} replaced by
                  the dynamics row: a row of stage k in (dX_k, dU_k, ds_k)
    boxes         dX_0 = x(t) - X_0, v_x >= 0, the actuator bounds, s >= 0

Its matrices come from one CasADi function of (w, p) (the Jacobians of the NLP's own constraint
rows, sliced by stage), compiled to C with the system compiler when one is present (``compile``:
"auto", "always" or "never"; ``vflpcd.controllers.compiled`` caches the library); ``compiled``
says whether it was. A step is usable when HPIPM solved the QP and the result is finite; otherwise
the controller falls back as MPC-CBF does (the shifted plan, then braking).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import casadi as ca
import numpy as np

from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table
from vflpcd.controllers.compiled import compiled
from vflpcd.controllers.nmpc_cbf import NmpcCbf, NmpcCbfConfig

log = logging.getLogger(__name__)

BIG = 1e8  # HPIPM's stand-in for an infinite bound


@dataclass(frozen=True)
class RtiConfig:
    """Settings of config/controllers/nmpc_rti.toml."""

    compile: str
    optimisation: str
    iter_max: int
    tol: float
    source: str = "config/controllers/nmpc_rti.toml"

    @classmethod
    def load(cls, path: str | Path | None = None) -> "RtiConfig":
        path = Path(path) if path is not None else config_dir() / "controllers" / "nmpc_rti.toml"
        root = load_table(path)
        root.check_known({"compile", "optimisation", "hpipm"})
        qp = root.table("hpipm")
        qp.check_known({"iter_max", "tol"})
        return cls(compile=root.string("compile", "auto", choices=("auto", "always", "never")),
                   optimisation=root.string("optimisation", "-O1", choices=("-O0", "-O1", "-O2", "-O3")),
                   iter_max=qp.integer("iter_max", min=1), tol=qp.number("tol", positive=True), source=str(path))


class NmpcRti(NmpcCbf):
    """MPC-CBF solved by real-time iterations (module docstring)."""

    name = "nmpc_rti"

    def __init__(self, *args, rti: RtiConfig, **kwargs) -> None:
        self.rti = rti
        self.compiled = False
        super().__init__(*args, **kwargs)

    # ------------------------------------------------------------------ the stage-wise QP
    def _make_solver(self, nlp: dict):
        """(QP-data function of (w, p), HPIPM conic): the module docstring's QP."""
        N, S = self.N, self.S
        nd = len(self.footprint.offsets)
        nX, nU = self._nX, self._nU
        w, p, f, g = nlp["x"], nlp["p"], nlp["f"], nlp["g"]
        if self.config.steering_rate_weight > 0.0:
            raise ValueError("nmpc_rti: steering_rate_weight > 0 couples two stages' controls in the cost; "
                             "the stage-wise QP supports the hard rate limit only")
        J, H, grad = ca.jacobian(g, w), ca.hessian(f, w)[0], ca.gradient(f, w)
        X = lambda k: list(range(6 * k, 6 * k + 6))                         # noqa: E731
        U = lambda k: list(range(nX + 2 * k, nX + 2 * k + 2))               # noqa: E731
        Sl = lambda k: list(range(nX + nU + S * k, nX + nU + S * (k + 1)))  # noqa: E731
        dyn = lambda k: list(range(6 + 6 * k, 12 + 6 * k))                  # noqa: E731
        rate0 = 6 * (N + 1)
        cbf = lambda k: list(range(rate0 + N + k * S * nd, rate0 + N + (k + 1) * S * nd))  # noqa: E731
        nx, nu, ng = 7, 2 + S, 1 + S * nd
        n_v = (N + 1) * nx + N * nu
        xo = lambda k: k * (nx + nu)                                         # noqa: E731  stage k's x~ offset
        rows = N * (nx + ng)
        Hq, gq = ca.SX(n_v, n_v), ca.SX.zeros(n_v)
        Aq = ca.SX(rows, n_v)
        lba, uba = ca.SX.zeros(rows), ca.SX.zeros(rows)
        lbv, ubv = ca.SX.zeros(n_v), ca.SX.zeros(n_v)
        lbx, ubx, lbg, ubg = self._lbx, self._ubx, self._lbg, self._ubg
        for k in range(N + 1):
            o = xo(k)
            Hq[o:o + 6, o:o + 6] = H[X(k), X(k)]
            gq[o:o + 6] = grad[X(k)]
            if k == 0:
                lbv[o:o + 6] = ubv[o:o + 6] = -g[0:6]                        # dX_0 = x(t) - X_0
                lbv[o + 6] = ubv[o + 6] = 0.0                                # z_0 = 0: delta_{-1} is given
            else:
                lbv[o:o + 6] = np.maximum(lbx[X(k)], -BIG) - w[X(k)]
                ubv[o:o + 6] = np.minimum(ubx[X(k)], BIG) - w[X(k)]
                lbv[o + 6], ubv[o + 6] = -BIG, BIG
            if k == N:
                break
            ou = o + nx
            idx_u = U(k) + Sl(k)
            Hq[ou:ou + nu, ou:ou + nu] = H[idx_u, idx_u]
            Hq[o:o + 6, ou:ou + nu] = H[X(k), idx_u]                         # S_k, both triangles
            Hq[ou:ou + nu, o:o + 6] = H[idx_u, X(k)]
            gq[ou:ou + nu] = grad[idx_u]
            lbv[ou:ou + nu] = np.maximum(lbx[idx_u], -BIG) - w[idx_u]
            ubv[ou:ou + nu] = np.minimum(ubx[idx_u], BIG) - w[idx_u]
            A_k, B_k, F_k = -J[dyn(k), X(k)], -J[dyn(k), U(k)], g[dyn(k)]
            r = k * (nx + ng)
            o1 = xo(k + 1)
            Aq[r:r + 6, o:o + 6] = A_k                                       # dynamics: A dX + B dU - dX_{k+1} = F_k
            Aq[r:r + 6, ou:ou + 2] = B_k
            Aq[r:r + 6, o1:o1 + 6] = -ca.SX.eye(6)
            lba[r:r + 6] = uba[r:r + 6] = F_k
            Aq[r + 6, ou + 1] = 1.0                                          # z_{k+1} = d delta_k
            Aq[r + 6, o1 + 6] = -1.0
            rr = r + nx                                                      # the rate row
            Aq[rr, ou + 1] = 1.0
            if k > 0:
                Aq[rr, o + 6] = -1.0
            g_rate = g[rate0 + k]
            lba[rr], uba[rr] = lbg[rate0 + k] - g_rate, ubg[rate0 + k] - g_rate
            rc, c_rows = rr + 1, cbf(k)                                      # the DCBF rows, dX_{k+1} substituted
            J1 = J[c_rows, X(k + 1)]
            Aq[rc:rc + S * nd, o:o + 6] = J[c_rows, X(k)] + J1 @ A_k
            Aq[rc:rc + S * nd, ou:ou + 2] = J1 @ B_k
            Aq[rc:rc + S * nd, ou + 2:ou + nu] = J[c_rows, Sl(k)]
            shift = -g[c_rows] + J1 @ F_k
            lba[rc:rc + S * nd] = np.maximum(lbg[c_rows], -BIG) + shift
            uba[rc:rc + S * nd] = np.minimum(ubg[c_rows], BIG) + shift
        # where each entry of the NLP's w sits in the QP's stage-ordered v: dw = v[self._w_in_v]
        w_in_v = np.empty(nX + nU + S * N, dtype=np.int64)
        for k in range(N + 1):
            w_in_v[X(k)] = xo(k) + np.arange(6)
            if k < N:
                w_in_v[U(k) + Sl(k)] = xo(k) + nx + np.arange(nu)
        self._w_in_v = w_in_v
        fn = ca.Function("nmpc_rti_qp", [w, p], [Hq, gq, Aq, lba, uba, lbv, ubv])
        conic = ca.conic("nmpc_rti_hpipm", "hpipm", {"h": Hq.sparsity(), "a": Aq.sparsity()},
                         {"N": N, "nx": [nx] * (N + 1), "nu": [nu] * N + [0], "ng": [ng] * N + [0],
                          "error_on_fail": False,
                          "hpipm": {"mode": "speed", "iter_max": self.rti.iter_max, "res_g_max": self.rti.tol,
                                    "res_b_max": self.rti.tol, "res_d_max": self.rti.tol, "res_m_max": self.rti.tol}})
        if self.rti.compile != "never":
            fast = compiled(fn, (self.rti.optimisation,))
            if fast is None and self.rti.compile == "always":
                raise ConfigError(self.rti.source, "compile", '"always", but the QP data could not be compiled '
                                  "(no C compiler, or it failed: see the log)")
            if fast is not None:
                fn, self.compiled = fast, True
        return fn, conic

    def _solve(self, args: dict) -> tuple[bool, str, dict | None]:
        """One real-time iteration from args["x0"] (module docstring)."""
        fn, conic = self._solver
        w0 = np.asarray(args["x0"], float)
        Hq, gq, Aq, lba, uba, lbv, ubv = fn(w0, args["p"])
        sol = conic(h=Hq, g=gq, a=Aq, lba=lba, uba=uba, lbx=lbv, ubx=ubv)
        stats = conic.stats()
        status = str(stats.get("return_status", "?"))
        v = np.asarray(sol["x"], float).ravel()
        if not (bool(stats.get("success", False)) and np.all(np.isfinite(v))):
            return False, f"HPIPM {status}", None
        return True, f"rti ({status}, {stats.get('iter_count', '?')} HPIPM iterations)", {"x": w0 + v[self._w_in_v]}

    @property
    def warm_duals(self) -> bool:
        return False          # an interior-point QP starts from its own central point


def make_nmpc_rti(scenario, config: NmpcCbfConfig | None = None, rti: RtiConfig | None = None, **_) -> NmpcRti:
    """The real-time-iteration NMPC for a ground scenario (default config files when None)."""
    return NmpcRti(scenario.path, scenario.v_desired, scenario.a_lat_max, scenario.control_period,
                   scenario.footprint, config if config is not None else NmpcCbfConfig.load(),
                   rti=rti if rti is not None else RtiConfig.load())
