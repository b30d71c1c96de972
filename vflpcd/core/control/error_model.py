"""The tick's horizon problem from the robot state, the guidance reference and the lifted model.

All states are taken into the window frame of the current pose (``lifted.to_window_frame``:
the robot at the origin heading along +X for the vehicle, at the origin for the quadrotor) and
lifted together: Upsilon(x) (n_K,) for the robot and Upsilon(x_r,tau) for tau = 0 .. N.

* error state (paper eq. discrete-time-nonlinear-system-dynmaics): x~_tau = Upsilon - Upsilon_r,
  without the constant observable (identically zero in the error), n = n_K - 1;
* reference control u_r,tau: the least-squares solution of the model on the physical rows,
  x_r,tau+1 = [A Upsilon_r,tau + B u_r]_{1..n_x} (the paper's eq. nominal_desired_path read as
  the definition of u_r), clipped into the actuator limits;
* c_tau = A Upsilon_r,tau + B u_r,tau + B_d m(z_r,tau) - Upsilon_r,tau+1: what the reference does not
  satisfy under the (compensated) model;
* A_tau, B_tau: the nominal A and B; with ``gp_jacobians``, eq. JocabianMatrices at
  (Upsilon_r,tau, u_r,tau) when a GP is given. A model whose input matrix is scheduled on a state
  (``lifted``: B + s B_s) is linearised at the reference every step instead: B_tau = B + s_r,tau B_s,
  A_tau = A + B_s u_r,tau e_s', with u_r,tau fitted through B_tau (``ErrorModel._scheduled_linearisation``).

Why the nominal Jacobians by default: the GP's mean is what removes the model's offset (it enters
c_tau, the horizon's affine term), while the gradient of a sparse GP fitted on a few hundred
closed-loop samples is noisy and changes at every refit. With eq. JocabianMatrices the horizon
solver (whose Riccati prior and Newton curvature are the nominal pair's) met a different, jolting
linearisation each tick: on ``vflpcd bench ml`` (racing_track, exact vehicle, noise) the lap-2
RMS lateral error was 0.116 / 0.095 m on seeds 0 / 1, against 0.097 / 0.089 m with the nominal
Jacobians and the GP mean alone (w/o ML: 0.194 / 0.192 m).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np
import scipy.linalg as sl

from vflpcd.core.control.barrier import safety_points
from vflpcd.core.control.barrier_kernel import FORMS
from vflpcd.core.control.problem import HorizonProblem
from vflpcd.core.control.tick_kernel import KIND_NONE, KIND_PLANAR, KIND_POSITION
from vflpcd.core.dynamics.compensation import KoopmanCompensation
from vflpcd.core.dynamics.lifted import LiftedLinearModel, PoseLayout, window_in_place
from vflpcd.core.dynamics.sparse_gp import FITCGP


_KINDS = {"none": KIND_NONE, "position": KIND_POSITION, "planar": KIND_PLANAR}     # PoseLayout.kind


@dataclass(frozen=True)
class TickLoops:
    """The tick's loops, compiled: ``tick_kernel``'s ``window_loop``, ``window_lift_loop`` (the window and
    a deep Koopman lift of it in one call) and ``linearisation_loop``,
    ``gp_kernel.corrected_next_loop`` (the GP's mean in c_tau), ``rate_kernel.increment_loop`` (the
    increment form's fill, ``RateForm.increments``), ``tick_kernel.command_loop`` (the command
    clipped into the limits, ``tick_horizon.clipped_command``), ``barrier_kernel.safety_points_loop`` (a
    threat's safety points in the window, ``ErrorModel.safety_points_in_window``),
    ``horizon_reference.strided_rows`` (the
    horizon's reference rows, ``HorizonReference.at``) and ``horizon_kernel.horizon_command_loop``
    (the problem, its solve and the command in one call, ``tick_horizon.CompiledHorizon``)."""

    window: Callable
    linearisation: Callable
    correction: Callable
    increment: Callable | None = None
    command: Callable | None = None
    reference: Callable | None = None
    horizon: Callable | None = None
    lift: Callable | None = None
    barrier: Callable | None = None


@dataclass(frozen=True)
class Limits:
    """u_min, u_max (n_u,) and the per-step rate limit du_max (n_u,) (inf: none)."""

    u_min: np.ndarray
    u_max: np.ndarray
    du_max: np.ndarray


@dataclass(eq=False)
class TickFrame:
    """What the controller needs back: the window origin (the world state, (n_x,)), the lifted
    robot state U (n_K,) and reference U_r (N + 1, n_K), and the reference in the window frame
    x_r (N + 1, n_x). Read-only by convention (built once a tick, as ``HorizonProblem``)."""

    origin: np.ndarray
    U: np.ndarray
    U_r: np.ndarray
    x_r: np.ndarray


class ErrorModel:
    """Builds ``HorizonProblem``s for a lifted model with the constant observable last.

    Q_x (n_x,) weights of the physical states, q_lift the weight of each encoder observable,
    R (n_u, n_u), gamma, N steps, limits; comp: the GP structure (or None). The terminal P (n, n)
    solves the discounted DARE of the nominal error model, and K_terminal (n_u, n) is its LQR gain
    (the fallback law u~ = -K_terminal x~). ``gp_jacobians``: linearise with the GP's gradient
    (eq. JocabianMatrices) instead of the nominal A, B (module docstring). A model with a scheduled
    input matrix (B + s B_s) has its nominal pair (P, K_terminal, the solvers' priors) at
    s = ``schedule_at`` and its horizon linearised at the reference every tick (``_scheduled_linearisation``;
    ``problem_loop``: ``scheduled_kernel.problem_loop`` compiled, or None for the numpy path).
    ``tick_loops``: the tick's loops compiled (``TickLoops``: the window, the nominal linearisation
    and the GP's correction), or None for the numpy path. ``B_x_pinv`` (n_u, n_x) is the
    pseudo-inverse of B's physical rows (u_r's fit), ``A_N``, ``B_N`` the nominal pair along the
    horizon (read-only views, the same arrays at every tick)."""

    def __init__(self, model: LiftedLinearModel, Q_x: np.ndarray, q_lift: float, R: np.ndarray, gamma: float,
                 N: int, limits: Limits, comp: KoopmanCompensation | None = None, gp_jacobians: bool = False,
                 schedule_at: float | None = None, problem_loop=None, tick_loops=None) -> None:
        if model.scheduled and schedule_at is None:
            raise ValueError(f"a model scheduled on {model.schedule!r} needs the value its nominal pair is taken at")
        A = model.A
        B = model.B + (schedule_at * model.B_s if model.scheduled else 0.0)
        e_last = np.zeros(model.n_K)
        e_last[-1] = 1.0
        if not (np.allclose(A[-1], e_last) and np.allclose(B[-1], 0.0)):
            raise ValueError("the lifted model's last observable must be the constant 1")
        self.model, self.N, self.limits, self.comp = model, int(N), limits, comp
        self.problem_loop = problem_loop
        self.gp_jacobians = bool(gp_jacobians)
        self.n = model.n_K - 1
        self.A, self.B = A[:-1, :-1], B[:-1]
        self.Q = np.diag(np.concatenate([np.asarray(Q_x, float), np.full(self.n - model.n_x, float(q_lift))]))
        self.R, self.gamma = np.asarray(R, float), float(gamma)
        g = np.sqrt(self.gamma)
        self.P = sl.solve_discrete_are(g * self.A, g * self.B, self.Q, self.R)
        self.K_terminal = np.linalg.solve(self.R + self.gamma * self.B.T @ self.P @ self.B,
                                          self.gamma * self.B.T @ self.P @ self.A)
        self.B_x_pinv = np.linalg.pinv(B[: model.n_x])
        self.A_N = np.broadcast_to(self.A, (self.N, self.n, self.n))
        self.B_N = np.broadcast_to(self.B, (self.N, self.n, model.n_u))
        self.layout = PoseLayout.of(model.state_names)
        self.tick_loops = tick_loops
        self._lifts: dict[int, tuple] = {}            # window length -> (its lifter, its float32 buffer)
        self._position = np.array(self.layout.position, dtype=np.int64)
        self._window_pose = (_KINDS[self.layout.kind], self._position, self.layout.heading or 0)   # the loops' layout
        self._no_G, self._no_g = np.zeros((self.N + 1, 0, self.n)), np.zeros((self.N + 1, 0))   # no half-planes (empty)

    def frame(self, state: np.ndarray, reference: np.ndarray) -> TickFrame:
        """Window frame of the world state (n_x,) and world reference (N + 1, n_x), lifted."""
        window, U = self._lifted_window(state, reference)
        return TickFrame(np.asarray(state, float), U[0], U[1:], window[1:])

    def lifted_next(self, origin: np.ndarray, state: np.ndarray) -> np.ndarray:
        """Upsilon (n_K,) of the world state (n_x,) in the window frame of the world state ``origin``:
        a transition's second state, for the GP."""
        return self._lifted_window(origin, state[None, :])[1][1]

    def _lifted_window(self, state: np.ndarray, reference: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The window [state; reference] (T, n_x) in the state's frame and its lift (T, n_K): compiled, by
        ``tick_loops.lift`` in one call where the lift is a deep Koopman encoder (``Lifter.encoder``),
        else ``tick_loops.window`` and the lift; or numpy. One lifter and its float32 buffer per window
        length."""
        T = len(reference) + 1
        window = np.empty((T, self.model.n_x))
        lift = self._lifts.get(T)
        if lift is None:
            lifter = self.model.lifter(T)
            lift = self._lifts[T] = (lifter, np.empty((T, self.model.n_x), np.float32), lifter.encoder())
        if self.tick_loops is not None:                  # the same numbers, compiled
            loops = self.tick_loops
            pose = (state, reference, *self._window_pose, self.model.x_mean, self.model.x_std, window, lift[1])
            if loops.lift is not None and lift[2] is not None:
                U = np.empty((T, self.model.n_K))
                loops.lift(*pose, *lift[2], U)
                return window, U
            loops.window(*pose)
            return window, lift[0].from_normalised(window, lift[1])
        window[0], window[1:] = state, reference
        return window, lift[0](window_in_place(window, self.layout))

    def problem(self, frame: TickFrame, u_prev: np.ndarray, gp: FITCGP | None = None) -> HorizonProblem:
        """The horizon problem of the module docstring."""
        m, N, lim = self.model, self.N, self.limits
        U_r = frame.U_r
        u_r, nxt, A, B = self._scheduled_linearisation(U_r) if m.scheduled else self._linearisation(U_r)
        if gp is not None and self.comp is not None:
            nxt = self.comp.corrected_next(nxt, U_r[:-1], u_r, gp,
                                           None if self.tick_loops is None else self.tick_loops.correction)
        if gp is not None and self.comp is not None and self.gp_jacobians:
            jac = [self.comp.jacobians(U_r[k], u_r[k], gp) for k in range(N)]     # a scheduled model's bilinear term included
            A = np.array([a[:-1, :-1] for a, _ in jac])
            B = np.array([b[:-1] for _, b in jac])
        c = (nxt - U_r[1:])[:, :-1]
        x0 = (frame.U - U_r[0])[:-1]
        return HorizonProblem(A=A, B=B, c=c, x0=x0, Q=self.Q, R=self.R, P=self.P, gamma=self.gamma, u_ref=u_r,
                              u_min=lim.u_min, u_max=lim.u_max, du_max=lim.du_max,
                              u_prev=np.asarray(u_prev, float), G=self._no_G, g=self._no_g)

    def _linearisation(self, U_r: np.ndarray):
        """u_r,tau (N, n_u) through the pseudo-inverse of B's physical rows, clipped into the limits, the
        nominal next lifted states (N, n_K) and the nominal pair (the same arrays every tick: solvers
        may keep what they derive from them)."""
        m, lim = self.model, self.limits
        if self.tick_loops is not None:         # the same numbers, compiled
            u_r, nxt = self.tick_loops.linearisation(U_r, m.A, m.B, self.B_x_pinv, m.n_x, lim.u_min, lim.u_max)
            return u_r, nxt, self.A_N, self.B_N
        pred = U_r[:-1] @ m.A.T                                           # (N, n_K)
        u_r = (U_r[1:, : m.n_x] - pred[:, : m.n_x]) @ self.B_x_pinv.T
        u_r = np.minimum(np.maximum(u_r, lim.u_min), lim.u_max)
        return u_r, pred + u_r @ m.B.T, self.A_N, self.B_N

    def _scheduled_linearisation(self, U_r: np.ndarray):
        """``_linearisation`` for a model whose input matrix depends on a state s (``lifted``: B + s B_s):
        u_r,tau from B_tau = B + s_r,tau B_s, and the linearisation at (Upsilon_r,tau, u_r,tau),
        A_tau = A + B_s u_r,tau e_s', B_tau per step; by ``problem_loop`` when compiled
        (``scheduled_kernel``, the same numbers)."""
        m, lim = self.model, self.limits
        if self.problem_loop is not None:       # the same numbers, compiled
            return self.problem_loop(np.ascontiguousarray(U_r), m.A, m.B, m.B_s, m.schedule_index,
                                     m.n_x, lim.u_min, lim.u_max)
        pred = U_r[:-1] @ m.A.T
        B_tau = m.input_matrix(U_r[:-1])                              # (N, n_K, n_u)
        BxT = B_tau[:, : m.n_x].transpose(0, 2, 1)
        rhs = BxT @ (U_r[1:, : m.n_x] - pred[:, : m.n_x])[..., None]
        u_r = np.linalg.solve(BxT @ BxT.transpose(0, 2, 1), rhs)[..., 0]   # least squares per step
        u_r = np.minimum(np.maximum(u_r, lim.u_min), lim.u_max)
        A_J, B_J = m.jacobians(U_r[:-1], u_r)
        return (u_r, pred + (B_tau @ u_r[..., None])[..., 0], np.ascontiguousarray(A_J[:, :-1, :-1]),
                np.ascontiguousarray(B_J[:, :-1]))

    def safety_points_in_window(self, frame: TickFrame, obstacle, points: np.ndarray, times: np.ndarray,
                                grow: float, x_p: np.ndarray, normal: np.ndarray) -> None:
        """``barrier.safety_points`` of ``obstacle`` at the world positions points (T, d) and times (T,),
        taken into the tick's window frame (``to_window``), written into x_p and normal (T, d): one
        compiled call (``tick_loops.barrier``) for a shape with a closed form, else numpy."""
        form = FORMS.get(obstacle.shape.closed_form)
        loops = self.tick_loops
        if loops is not None and loops.barrier is not None and form is not None:
            # the arrays in the warmed types (a perceived obstacle's are read-only, ``perception``; a
            # column selection is Fortran-ordered): another type would compile inside the tick
            loops.barrier(form, obstacle.shape.support_extent(), np.array(obstacle.center, dtype=float),
                          float(obstacle.yaw), np.array(obstacle.velocity, dtype=float), float(obstacle.stamp),
                          np.ascontiguousarray(points, dtype=float), np.ascontiguousarray(times, dtype=float),
                          float(grow), *self._window_pose, frame.origin, x_p, normal)
            return
        world, n = safety_points(obstacle, points, times, grow)
        x_p[:] = self.to_window(frame, world)
        normal[:] = self.to_window(frame, n, vectors=True)

    def to_window(self, frame: TickFrame, points: np.ndarray, vectors: bool = False) -> np.ndarray:
        """World points (or direction vectors) (..., d) -> the tick's window frame."""
        lay = self.layout
        pts = np.asarray(points, float)
        origin = frame.origin
        if lay.kind == "none":
            return pts
        p = pts if vectors else pts - origin[list(lay.position)]
        if lay.kind == "position":
            return p
        psi0 = origin[lay.heading]
        c, s = np.cos(psi0), np.sin(psi0)
        return np.stack([c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1]], axis=-1)
