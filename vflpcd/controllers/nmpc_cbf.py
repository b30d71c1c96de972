"""MPC-CBF: nonlinear MPC with discrete-time control barrier functions (the paper's comparison method).

Zeng, Zhang, Sreenath, "Safety-critical model predictive control with discrete-time control
barrier function", ACC 2021, on the dynamic bicycle of the paper. Solved with CasADi + IPOPT.

Problem, solved at every control step t with the measured state x(t):

    min   sum_{k=0}^{N-1} gamma^k ( x~_k' Q x~_k + u~_k' R u~_k ) + gamma^N rho x~_N' Q x~_N
          + w_d sum_{k=0}^{N-1} (delta_k - delta_{k-1})^2 + w_s sum_{k,j} s_{j,k}
    s.t.  x_0 = x(t),  x_{k+1} = F(x_k, u_k)                             (multiple shooting)
          a_min <= a_{x,k} <= a_max,  |delta_k| <= delta_max,  v_{x,k} >= 0
          |delta_k - delta_{k-1}| <= delta_rate_max dt,  delta_{-1} = last command
          h_{ij}(x_{k+1}) >= (1 - gamma_cbf) h_{ij}(x_k) - s_{j,k},  s_{j,k} >= 0      (DCBF)

* x = [X, Y, psi, v_x, v_y, omega], u = [a_x, delta_f]; F is RK4 over dt = the scenario's
  control period (``substeps`` equal RK4 steps) of the paper's eq. vehicle_dynamics with the
  NOMINAL parameter set (``model_params``) whatever the plant is, and v_x replaced by
  max(v_x, v_min) in the 1/v_x tyre-slip terms.
* N = round(T / dt) with T = ``horizon_seconds`` (>= the shared ``[horizon] seconds`` of
  ``config/controllers/vflpc.toml``, which is the default). Q = diag(q_ground), R =
  diag(r_ground) and the discount gamma are the shared ``[cost]`` of that file.
* x~_k = x_k - x_{r,k} with the position error rotated by the CURRENT yaw psi(t) (row 1
  along-track, row 2 cross-track, as the shared cost defines it); psi error against the path
  tangent unwrapped continuously from psi(t).
* u~_k = u_k - u_{r,k}, u_{r,k} = [0, atan(L kappa_k)] (steering feed-forward of the
  reference curvature, wheelbase L).
* Terminal cost: the stage Q times ``terminal_factor`` rho (no DARE: q_ground weighs neither
  v_y nor omega, so a DARE on the linearisation would mostly re-weigh those; a plain factor is
  simpler and was enough here). The steering-rate penalty w_d (``steering_rate_weight``) is
  off (0) in the shipped file; if a tuning turns it on it must be reported with the figures.
* Reference: the current position is projected on the scenario's raw reference path (the
  previous arc length as hint); reference point k lies at s_0 + sum_{i<k} v_{r,i} dt with
  v_r = min(v_d, sqrt(a_lat_max / |kappa|)); heading the tangent; v_{x,r} = v_r, v_{y,r} = 0,
  omega_r = v_r kappa. Past the end of an open path the reference runs straight on along the
  last tangent (the run ends at the goal before it). The MPC tracks this path and avoids
  obstacles only through the DCBF, as in the paper (no planner in front of it).
* Barrier functions: the car is covered by the scenario footprint's discs (radius r_c, centres
  (X, Y) + o_i (cos psi, sin psi)); every obstacle by up to ``obstacle_discs`` discs
  (a circle: itself; a box or an ellipse: discs along its long axis covering its bounding box,
  radius sqrt((l/n)^2 + w^2) for half-extents l >= w, or its bounding circle if that is
  smaller). For car disc i and obstacle disc j with centre c_j(t + k dt) (constant-velocity
  prediction) and radius r_j:  h_ij = ||p_i - c_j||^2 - (r_j + r_c + margin)^2.
  Only obstacles within ``relevance_distance`` (gap between the car's centre and the
  obstacle's bounding circle, now or at the end of the horizon) enter, the nearest
  ``max_obstacles`` of them, so that the NLP's structure is fixed: the unused obstacle-disc
  slots are switched off by an active flag a_j (their constraint reads 1 + s >= 0, never
  active, so that their multipliers are 0 and warm-start cleanly when an obstacle arrives).
* Slack: one s_{j,k} >= 0 per obstacle disc and step (shared by the car discs) with the L1
  weight w_s (exact penalty), so that IPOPT never reports the problem infeasible.

Solver: the NLP is built once (CasADi SX, ``nlpsol("ipopt")``) with the state, the reference,
the previous steering command and the obstacle slots as parameters. Each step is warm-started
with the previous solution shifted by one step (primal; duals too if ``warm_start_duals``).
On an exception or a non-success IPOPT status the command is the previous plan's next control
(shifted once more per further failure; a braking command, a_min with the steering held,
once the plan is used up); ``failures`` counts them and each logs one warning.

Tuning (carsim_avoidance, dt = 50 ms, by hand, on that scenario only): the shared Q, R,
gamma and the shared 1 s horizon are kept, so MPC-CBF is compared on VF-LPC's cost and
horizon. The free choices were set once and then checked by varying them: cbf.gamma = 0.2
(0.1 and 0.4 also pass every obstacle; smaller keeps more clearance and costs more time and
J_MC), margin = 0.3 m (0.1 m also passes, with 0.23 m least clearance); a 2 s horizon lowers
J_MC by about 20 % and t_com by 1.7 s at 2.3 times the computation time (p99 ~ 160 ms), so it
is not the default. v_min = 2 m/s with 2 RK4 sub-steps: the yaw mode of the model is about
-190/v_x 1/s, and with 2 sub-steps of 25 ms RK4 stays stable for v_x >= 2 m/s (the plant
itself leaves the paper's model below 3 m/s); v_min = 1 m/s needs 4 sub-steps, gave the same
run and was 40 % slower. Warm-starting the duals (IPOPT warm_start_init_point, mu_init 1e-4)
halves the iterations; an obstacle keeps its slot while it stays relevant so that its
multipliers stay its own. Measured with the shipped files (2-core container):
J_MC 1.674, L_p 255.2 m, t_com 37.9 s, t_cal median 16 ms / p99 45 ms, no collision, least
clearance 0.44 m (slow car), no solver failure.

Conservatism and known weaknesses:
* Disc covers: a box or an ellipse is replaced by the union of discs covering its bounding
  box (for the 4.6 m x 1.9 m parked car, 3 discs of radius 1.22 m: up to 0.27 m too wide at
  the sides, more at the corners), and the car's rectangle by 3 discs of radius 1.25 m (0.30 m
  wider than the car at the sides); ``margin`` comes on top.
* The DCBF holds at the sampling instants only (the car may cut a corner between them) and
  only for the model: the plant's actuator rate limiter and low-speed blend are not modelled,
  and the obstacle prediction is constant-velocity.
* With the slack, safety is a penalty, not a hard guarantee: a large slack in the solution
  means the model found no way round.
* Local method: IPOPT returns a local optimum, and the DCBF can stop the car in front of an
  obstacle (the deadlock known for MPC-CBF) rather than pick a way round. On dense_static
  (3 m/s through eight close obstacles) it stops for good after 9 to 10 m, without contact, with
  every setting tried (cbf.gamma 0.2 / 0.5, margin 0.1, v_min 1 with 4 sub-steps; a 2 s horizon
  gets to 22 m). The side chosen depends on the warm start.
* No lateral-acceleration or friction limit beyond the reference speed: the linear-tyre model
  lets it swerve at up to ~9.5 m/s^2 on carsim_avoidance, and a_x (weight r = 0.1) switches
  hard between its limits while it swerves.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import casadi as ca
import numpy as np

from vflpcd.core.footprint import Footprint
from vflpcd.config.vehicles import BicycleConfig, BicycleParams
from vflpcd.core.angles import wrap_angle
from vflpcd.core.obstacles import ObstacleState
from vflpcd.core.path import ReferencePath
from vflpcd.core.shapes import Circle
from vflpcd.core.ports import ControllerBase
from vflpcd.base.errors import ConfigError
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table

log = logging.getLogger(__name__)

_FAR = 1.0e3  # offset of the centre of an unused obstacle slot from the car, m


@dataclass(frozen=True)
class NmpcCbfConfig:
    """Settings of ``config/controllers/nmpc_cbf.toml`` plus the shared cost of ``vflpc.toml``."""

    model: BicycleConfig          # the prediction model's parameters and the actuator limits
    q: np.ndarray                 # (6,) state-error weights [X, Y, psi, vx, vy, omega], pose frame
    r: np.ndarray                 # (2,) control-error weights [a_x, delta_f]
    gamma: float                  # cost discount
    horizon_seconds: float
    terminal_factor: float
    steering_rate_weight: float
    v_min: float
    substeps: int
    cbf_gamma: float
    margin: float
    relevance_distance: float
    max_obstacles: int
    obstacle_discs: int
    slack_weight: float
    max_iter: int
    tol: float
    acceptable_tol: float
    warm_start_duals: bool

    @classmethod
    def load(cls, path: str | Path | None = None, shared: str | Path | None = None) -> "NmpcCbfConfig":
        """Read ``path`` (default config/controllers/nmpc_cbf.toml) and the shared cost/horizon of
        ``shared`` (default config/controllers/vflpc.toml)."""
        path = Path(path) if path is not None else config_dir() / "controllers" / "nmpc_cbf.toml"
        shared = Path(shared) if shared is not None else config_dir() / "controllers" / "vflpc.toml"

        sroot = load_table(shared)  # other controllers own this file: read, no check_known
        cost, hor = sroot.table("cost"), sroot.table("horizon")
        q, r = cost.vector("q_ground", 6), cost.vector("r_ground", 2)
        if np.any(q < 0.0):
            raise cost.error("q_ground", "expected 6 numbers >= 0")
        if np.any(r <= 0.0):
            raise cost.error("r_ground", "expected 2 positive numbers")
        gamma = cost.number("gamma", positive=True, max=1.0)
        shared_seconds = hor.number("seconds", positive=True)

        root = load_table(path)
        root.check_known({"model_params", "v_min", "substeps", "horizon_seconds", "terminal_factor",
                          "steering_rate_weight", "cbf", "ipopt"})
        horizon = root.number("horizon_seconds", shared_seconds, positive=True)
        if horizon < shared_seconds - 1e-12:
            raise root.error("horizon_seconds", f"expected at least the shared horizon of {shared} "
                                                f"([horizon] seconds = {shared_seconds:g}), got {horizon:g}")
        params = root.string("model_params", "nominal")
        try:
            model = BicycleConfig.load(params)
        except ConfigError as exc:  # an unknown parameter set is named in this file
            if exc.field.startswith("params."):
                raise root.error("model_params", exc.message) from None
            raise
        cbf = root.table("cbf")
        cbf.check_known({"gamma", "margin", "relevance_distance", "max_obstacles", "obstacle_discs",
                         "slack_weight"})
        ip = root.table("ipopt")
        ip.check_known({"max_iter", "tol", "acceptable_tol", "warm_start_duals"})
        cbf_gamma = cbf.number("gamma", positive=True, max=1.0)
        return cls(
            model=model, q=q, r=r, gamma=gamma, horizon_seconds=horizon,
            terminal_factor=root.number("terminal_factor", min=0.0),
            steering_rate_weight=root.number("steering_rate_weight", 0.0, min=0.0),
            v_min=root.number("v_min", positive=True), substeps=root.integer("substeps", 1, min=1),
            cbf_gamma=cbf_gamma, margin=cbf.number("margin", min=0.0),
            relevance_distance=cbf.number("relevance_distance", positive=True),
            max_obstacles=cbf.integer("max_obstacles", min=1), obstacle_discs=cbf.integer("obstacle_discs", min=1),
            slack_weight=cbf.number("slack_weight", positive=True),
            max_iter=ip.integer("max_iter", min=1), tol=ip.number("tol", positive=True),
            acceptable_tol=ip.number("acceptable_tol", 1e-6, positive=True),
            warm_start_duals=ip.boolean("warm_start_duals", False))


def bicycle_rhs(x, u, p: BicycleParams, v_min: float):
    """Paper eq. vehicle_dynamics as CasADi expressions; 1/v_x terms use max(v_x, v_min)."""
    psi, vx, vy, om = x[2], x[3], x[4], x[5]
    a_x, delta = u[0], u[1]
    vxd = ca.fmax(vx, v_min)
    vy_dot = (2.0 * p.Caf * (delta / p.m - (vy + p.lf * om) / (p.m * vxd))
              + 2.0 * p.Car * (p.lr * om - vy) / (p.m * vxd) - vx * om)
    om_dot = (2.0 / p.Iz) * (p.lf * p.Caf * (delta - (vy + p.lf * om) / vxd) - p.lr * p.Car * (p.lr * om - vy) / vxd)
    return ca.vertcat(vx * ca.cos(psi) - vy * ca.sin(psi), vx * ca.sin(psi) + vy * ca.cos(psi), om,
                      vy * om + a_x, vy_dot, om_dot)


def obstacle_discs(shape, n_max: int) -> tuple[np.ndarray, float, int]:
    """Discs covering a 2-D shape in its body frame: (centres (n, 2), radius, n).

    A circle is itself; any other shape is covered through its bounding box (half-extents
    l >= w along its long axis) by n = n_max discs of radius sqrt((l/n)^2 + w^2) on that axis,
    or by its bounding circle when that is not larger.
    """
    if isinstance(shape, Circle):
        return np.zeros((1, 2)), float(shape.radius), 1
    ext = np.asarray(shape.support_extent(), float)
    axis = int(np.argmax(ext))
    long, short = float(ext[axis]), float(ext[1 - axis])
    r_bound = float(shape.bounding_radius())
    r_n = math.hypot(long / n_max, short)
    if n_max == 1 or r_n >= r_bound:
        return np.zeros((1, 2)), r_bound, 1
    centres = np.zeros((n_max, 2))
    centres[:, axis] = -long + (long / n_max) * (2 * np.arange(n_max) + 1)
    return centres, r_n, n_max


class NmpcCbf(ControllerBase):
    """MPC-CBF baseline. Controller protocol: state [X, Y, psi, vx, vy, omega] -> [a_x, delta_f].

    After each ``step``: ``plan_states`` (N+1, 6) and ``plan_controls`` (N, 2) of the last
    successful solve, ``plan_slack`` (S, N), ``last_obstacles`` the obstacle-disc slots used
    (centres (S, N+1, 2), radii (S,) already inflated by r_c + margin, active (S,)),
    ``last_status`` IPOPT's return status, ``failures`` the fallback count since ``reset``.
    """

    name = "nmpc_cbf"

    def __init__(self, path: ReferencePath, v_desired: float, a_lat_max: float, control_period: float,
                 footprint: Footprint, config: NmpcCbfConfig) -> None:
        if footprint.dim != 2:
            raise ValueError("nmpc_cbf drives the ground vehicle: it needs a 2-D footprint")
        self.path, self.v_desired, self.a_lat_max = path, float(v_desired), float(a_lat_max)
        self.dt = float(control_period)
        self.footprint, self.config = footprint, config
        self.N = max(int(round(config.horizon_seconds / self.dt)), 1)
        self.S = config.max_obstacles * config.obstacle_discs
        lim = config.model.limits
        self.u_min = np.array([lim.a_min, -lim.delta_max])
        self.u_max = np.array([lim.a_max, lim.delta_max])
        self.du_max = lim.delta_rate_max * self.dt
        self._build()
        self.reset()

    # ------------------------------------------------------------------ NLP
    def _build(self) -> None:
        cfg, N, S, dt = self.config, self.N, self.S, self.dt
        p_mod = cfg.model.params
        xs, us = ca.SX.sym("x", 6), ca.SX.sym("u", 2)
        h = dt / cfg.substeps
        xn = xs
        for _ in range(cfg.substeps):
            k1 = bicycle_rhs(xn, us, p_mod, cfg.v_min)
            k2 = bicycle_rhs(xn + 0.5 * h * k1, us, p_mod, cfg.v_min)
            k3 = bicycle_rhs(xn + 0.5 * h * k2, us, p_mod, cfg.v_min)
            k4 = bicycle_rhs(xn + h * k3, us, p_mod, cfg.v_min)
            xn = xn + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
        self._F = ca.Function("F", [xs, us], [xn])

        X = ca.SX.sym("X", 6, N + 1)
        U = ca.SX.sym("U", 2, N)
        Sl = ca.SX.sym("s", S, N)
        P_x0 = ca.SX.sym("x0", 6)
        P_xr = ca.SX.sym("xr", 6, N + 1)
        P_ur = ca.SX.sym("ur", 2, N)
        P_dprev = ca.SX.sym("dprev", 1)
        P_c = ca.SX.sym("c", 2 * S, N + 1)   # obstacle-disc centres: rows 2j, 2j+1 = slot j
        P_r = ca.SX.sym("r", S)              # inflated radii r_j + r_c + margin
        P_a = ca.SX.sym("a", S)              # active flags
        self._p_sizes = [6, 6 * (N + 1), 2 * N, 1, 2 * S * (N + 1), S, S]

        c0, s0 = ca.cos(P_x0[2]), ca.sin(P_x0[2])
        Q, R = np.diag(cfg.q), np.diag(cfg.r)

        def state_cost(k, weight):
            e = X[:, k] - P_xr[:, k]
            e_rot = ca.vertcat(c0 * e[0] + s0 * e[1], -s0 * e[0] + c0 * e[1], e[2:])
            return weight * ca.bilin(Q, e_rot, e_rot)

        J = 0
        for k in range(N):
            du = U[:, k] - P_ur[:, k]
            J += state_cost(k, cfg.gamma ** k) + cfg.gamma ** k * ca.bilin(R, du, du)
        J += state_cost(N, cfg.gamma ** N * cfg.terminal_factor)
        dprev = ca.horzcat(P_dprev, U[1, :-1])
        ddelta = U[1, :] - dprev
        if cfg.steering_rate_weight > 0.0:
            J += cfg.steering_rate_weight * ca.sumsqr(ddelta)
        J += cfg.slack_weight * ca.sum1(ca.sum2(Sl))

        # h_ij(x_k) of every car disc i against obstacle-disc slot j, each built once: H[k][j] = [h_0j, h_1j, ...]
        offsets = np.asarray(self.footprint.offsets, float)
        H = []
        for k in range(N + 1):
            ck, sk = ca.cos(X[2, k]), ca.sin(X[2, k])
            discs = [(X[0, k] + o * ck, X[1, k] + o * sk) for o in offsets]
            row = []
            for j in range(S):
                cx, cy, r2 = P_c[2 * j, k], P_c[2 * j + 1, k], P_r[j] ** 2
                row.append([(px - cx) ** 2 + (py - cy) ** 2 - r2 for px, py in discs])
            H.append(row)

        g, lbg, ubg = [X[:, 0] - P_x0], [0.0] * 6, [0.0] * 6
        for k in range(N):
            g.append(X[:, k + 1] - self._F(X[:, k], U[:, k]))
            lbg += [0.0] * 6
            ubg += [0.0] * 6
        g.append(ddelta.T)
        lbg += [-self.du_max] * N
        ubg += [self.du_max] * N
        one_minus = 1.0 - cfg.cbf_gamma
        for k in range(N):
            for j in range(S):
                for h_now, h_next in zip(H[k][j], H[k + 1][j]):
                    # an unused slot (a_j = 0) reads s + 1 >= 0: never active, so its multiplier stays 0
                    # and the duals warm-start cleanly when an obstacle takes the slot
                    g.append(P_a[j] * (h_next - one_minus * h_now) + (1.0 - P_a[j]) + Sl[j, k])
                    lbg.append(0.0)
                    ubg.append(ca.inf)
        self._n_dyn = 6 * (N + 1)
        w = ca.vertcat(ca.vec(X), ca.vec(U), ca.vec(Sl))
        p = ca.vertcat(P_x0, ca.vec(P_xr), ca.vec(P_ur), P_dprev, ca.vec(P_c), P_r, P_a)
        nlp = {"x": w, "p": p, "f": J, "g": ca.vertcat(*g)}
        self._lbg, self._ubg = np.array(lbg, float), np.array(ubg, float)
        nX, nU = 6 * (N + 1), 2 * N
        self._nX, self._nU = nX, nU
        lbx = np.full(nX + nU + S * N, -np.inf)
        ubx = np.full(nX + nU + S * N, np.inf)
        vx_idx = 6 * np.arange(1, N + 1) + 3
        lbx[vx_idx] = 0.0  # the car does not reverse
        lbx[nX:nX + nU] = np.tile(self.u_min, N)
        ubx[nX:nX + nU] = np.tile(self.u_max, N)
        lbx[nX + nU:] = 0.0
        self._lbx, self._ubx = lbx, ubx
        self._solver = self._make_solver(nlp)

    def _make_solver(self, nlp: dict):
        """The NLP solver: IPOPT to convergence (``[ipopt]`` of the config)."""
        cfg = self.config
        opts = {"print_time": False, "ipopt.print_level": 0, "ipopt.sb": "yes",
                "ipopt.max_iter": cfg.max_iter, "ipopt.tol": cfg.tol, "ipopt.acceptable_tol": cfg.acceptable_tol}
        if cfg.warm_start_duals:
            opts.update({"ipopt.warm_start_init_point": "yes", "ipopt.warm_start_bound_push": 1e-6,
                         "ipopt.warm_start_mult_bound_push": 1e-6, "ipopt.mu_init": 1e-4})
        return ca.nlpsol("nmpc_cbf", "ipopt", nlp, opts)

    def _solve(self, args: dict) -> tuple[bool, str, dict | None]:
        """One call of the solver: (usable, status, solution); usable = IPOPT succeeded with a
        finite solution."""
        sol = self._solver(**args)
        stats = self._solver.stats()
        ok = bool(stats.get("success", False)) and bool(np.all(np.isfinite(np.asarray(sol["x"], float))))
        return ok, str(stats.get("return_status", "?")), sol

    @property
    def warm_duals(self) -> bool:
        """Whether the previous solution's multipliers warm-start the next solve."""
        return self.config.warm_start_duals

    # ------------------------------------------------------------------ protocol
    def reset(self) -> None:
        self._s: float | None = None
        self._w: np.ndarray | None = None       # last successful primal solution
        self._lam_x: np.ndarray | None = None
        self._lam_g: np.ndarray | None = None
        self._since_solve = 0                   # steps since the last successful solve
        self._u_prev = np.zeros(2)              # the plant starts with the wheels straight
        self._slot_of: dict[str, int] = {}      # obstacle id -> its slot (times obstacle_discs)
        self.failures = 0
        self.last_status: str | None = None
        self.plan_states: np.ndarray | None = None
        self.plan_controls: np.ndarray | None = None
        self.plan_slack: np.ndarray | None = None
        self.last_obstacles: dict | None = None

    def step(self, state: np.ndarray, t: float, obstacles: Sequence[ObstacleState] = ()) -> np.ndarray:
        x0 = np.asarray(state, float).reshape(6)
        N = self.N
        proj = self.path.project(x0[:2], self._s)
        self._s = proj.s
        xr, ur = self.reference(proj.s, float(x0[2]))
        centres, radii, active = self._obstacle_slots(x0, t, obstacles)
        self.last_obstacles = {"centres": centres, "radii": radii, "active": active}
        # CasADi's vec() is column-major: the (6, N+1) parameter X_r is xr (N+1, 6) row by row, etc.
        p = np.concatenate([x0, xr.ravel(), ur.ravel(), [self._u_prev[1]],
                            centres.transpose(1, 0, 2).ravel(), radii, active])
        w0 = self._initial_guess(x0, xr, ur)
        args = {"x0": w0, "p": p, "lbx": self._lbx, "ubx": self._ubx, "lbg": self._lbg, "ubg": self._ubg}
        if self.warm_duals and self._lam_g is not None and self._since_solve == 0:
            args["lam_x0"], args["lam_g0"] = self._lam_x, self._lam_g
        try:
            ok, reason, sol = self._solve(args)
            self.last_status = reason
        except Exception as exc:  # noqa: BLE001 - any solver error falls back to the plan
            ok, reason, sol = False, f"{type(exc).__name__}: {exc}", None
            self.last_status = reason
        if ok:
            w = np.asarray(sol["x"], float).ravel()
            self._w = w
            if self.warm_duals:
                self._lam_x = np.asarray(sol["lam_x"], float).ravel()
                self._lam_g = np.asarray(sol["lam_g"], float).ravel()
            self._since_solve = 0
            self.plan_states, self.plan_controls, self.plan_slack = self._unpack(w)
            u = self.plan_controls[0].copy()
        else:
            self.failures += 1
            self._since_solve += 1
            u = self._fallback()
            log.warning("%s: solver failed at t=%.2f s (%s); using %s [%.2f, %.3f]", self.name, t, reason,
                        "the shifted plan" if self._w is not None and self._since_solve < N else "braking",
                        u[0], u[1])
        u = self._limit(u)
        self._u_prev = u
        return u

    # ------------------------------------------------------------------ pieces
    def reference(self, s0: float, psi0: float) -> tuple[np.ndarray, np.ndarray]:
        """Reference states (N+1, 6) and controls (N, 2) from arc length s0; headings unwrapped from psi0."""
        N, dt, path = self.N, self.dt, self.path
        s = np.empty(N + 1)
        s[0] = s0
        v = np.empty(N + 1)
        for k in range(N + 1):
            kap = abs(float(path.curvature_at(s[k])))
            v[k] = min(self.v_desired, math.sqrt(self.a_lat_max / max(kap, 1e-9)))
            if k < N:
                s[k + 1] = s[k] + v[k] * dt
        kappa = np.asarray(path.curvature_at(s), float)
        pts = np.asarray(path.point_at(s), float)
        head = np.asarray(path.heading_at(s), float)
        if not path.closed:  # past the end of an open path the reference runs straight on
            beyond = np.maximum(s - path.length, 0.0)
            kappa = np.where(beyond > 0.0, 0.0, kappa)
            pts = pts + beyond[:, None] * np.asarray(path.tangent_at(path.length), float)[None, :]
        psi = np.empty(N + 1)
        psi[0] = psi0 + wrap_angle(head[0] - psi0)
        psi[1:] = psi[0] + np.cumsum(wrap_angle(np.diff(head)))
        xr = np.column_stack([pts[:, 0], pts[:, 1], psi, v, np.zeros(N + 1), v * kappa])
        ur = np.column_stack([np.zeros(N), np.arctan(self.config.model.params.wheelbase * kappa[:N])])
        return xr, ur

    def _obstacle_slots(self, x0: np.ndarray, t: float, obstacles: Sequence[ObstacleState]):
        """Centres (S, N+1, 2), inflated radii (S,), active flags (S,) of the obstacle-disc slots."""
        cfg, N, S = self.config, self.N, self.S
        nd = cfg.obstacle_discs
        pos = x0[:2]
        centres = np.tile(pos + np.array([_FAR, _FAR]), (S, N + 1, 1))
        radii, active = np.ones(S), np.zeros(S)
        T = N * self.dt
        cand = []
        for o in obstacles:
            c_now = np.asarray(o.center_at(t), float)[:2]
            c_end = np.asarray(o.center_at(t + T), float)[:2]
            rb = float(o.shape.bounding_radius())
            gap = min(np.linalg.norm(c_now - pos), np.linalg.norm(c_end - pos)) - rb
            if gap <= cfg.relevance_distance:
                cand.append((gap, o))
        cand.sort(key=lambda item: item[0])
        if len(cand) > cfg.max_obstacles:
            log.debug("nmpc_cbf: %d relevant obstacles, keeping the nearest %d", len(cand), cfg.max_obstacles)
        kept = [o for _, o in cand[:cfg.max_obstacles]]
        # an obstacle keeps its slot while it stays relevant, so the warm-started duals stay its own
        ids = {o.id for o in kept}
        slot_of = {oid: i for oid, i in self._slot_of.items() if oid in ids}
        free = [i for i in range(cfg.max_obstacles) if i not in slot_of.values()]
        for o in kept:
            if o.id not in slot_of:
                slot_of[o.id] = free.pop(0)
        self._slot_of = slot_of
        tk = t + self.dt * np.arange(N + 1)
        inflate = self.footprint.radius + cfg.margin
        for o in kept:
            i = slot_of[o.id]
            local, r, n = obstacle_discs(o.shape, nd)
            cy, sy = math.cos(o.yaw), math.sin(o.yaw)
            world = local[:, :2] @ np.array([[cy, sy], [-sy, cy]])          # rotated offsets (n, 2)
            traj = np.stack([np.asarray(o.center_at(tt), float)[:2] for tt in tk])  # (N+1, 2)
            for j in range(n):
                slot = i * nd + j
                centres[slot] = traj + world[j]
                radii[slot] = r + inflate
                active[slot] = 1.0
        return centres, radii, active

    def _initial_guess(self, x0: np.ndarray, xr: np.ndarray, ur: np.ndarray) -> np.ndarray:
        N, S = self.N, self.S
        if self._w is not None and self._since_solve < N:
            Xp, Up, Sp = self._unpack(self._w)
            shift = self._since_solve + 1
            X = np.vstack([Xp[shift:], np.repeat(Xp[-1:], shift, axis=0)])
            U = np.vstack([Up[shift:], np.repeat(Up[-1:], shift, axis=0)])
            Sg = np.hstack([Sp[:, shift:], np.zeros((S, shift))])
            X[:, 2] += 2.0 * np.pi * np.round((x0[2] - X[0, 2]) / (2.0 * np.pi))  # follow the yaw wrap
            X[0] = x0
        else:  # roll the model out with the reference controls
            U = ur.copy()
            X = np.empty((N + 1, 6))
            X[0] = x0
            for k in range(N):
                X[k + 1] = np.asarray(self._F(X[k], U[k]), float).ravel()
                X[k + 1, 3] = max(X[k + 1, 3], 0.0)
            if not np.all(np.isfinite(X)):
                X = xr.copy()
                X[0] = x0
            Sg = np.zeros((S, N))
        return np.concatenate([X.ravel(), U.ravel(), Sg.T.ravel()])

    def _unpack(self, w: np.ndarray):
        N, S, nX, nU = self.N, self.S, self._nX, self._nU
        return (w[:nX].reshape(N + 1, 6), w[nX:nX + nU].reshape(N, 2), w[nX + nU:].reshape(N, S).T)

    def _fallback(self) -> np.ndarray:
        if self._w is not None and self._since_solve < self.N:
            return self._unpack(self._w)[1][self._since_solve].copy()
        return np.array([self.u_min[0], self._u_prev[1]])

    def _limit(self, u: np.ndarray) -> np.ndarray:
        u = np.where(np.isfinite(u), u, self._u_prev)
        a = float(np.clip(u[0], self.u_min[0], self.u_max[0]))
        d = float(np.clip(u[1], self._u_prev[1] - self.du_max, self._u_prev[1] + self.du_max))
        return np.array([a, float(np.clip(d, self.u_min[1], self.u_max[1]))])


def make_nmpc_cbf(scenario, config: NmpcCbfConfig | None = None, **_) -> NmpcCbf:
    """The MPC-CBF controller for a ground scenario (config: default file when None)."""
    return NmpcCbf(scenario.path, scenario.v_desired, scenario.a_lat_max, scenario.control_period,
                   scenario.footprint, config if config is not None else NmpcCbfConfig.load())
