"""Lifted linear (Koopman) models and the window-frame pose convention they share.

Model (paper eq. for the latent dynamics)
-----------------------------------------
A :class:`LiftedLinearModel` maps a state x (n_x,) to the lifted state
Upsilon(x) = [x, rho(x)] (n_K,) -- the first n_x entries are x itself, in SI units -- and
predicts with the linear time-invariant system

    Upsilon_{k+1} = A Upsilon_k + B u_k,       A: (n_K, n_K), B: (n_K, n_u),

reading the predicted state as the first n_x entries. ``rollout`` lifts once and iterates.
The DMDc/EDMDc baselines (``vflpcd.training.dmdc``) and the deep Koopman model share it.

Scheduled input matrix (optional): with a scheduling channel s (a state, e.g. the car's v_x) the
input matrix depends on it,

    Upsilon_{k+1} = A Upsilon_k + (B + s_k B_s) u_k,     s_k = Upsilon_k[schedule], B_s: (n_K, n_u),

a bilinear lift restricted to one state. A model linear in u has one steady input gain at every
state; a car's yaw rate per radian of steering grows with its speed (kinematic at low speed), which
``B + v_x B_s`` represents. Without a schedule B_s is zero and the model is the linear one.

Normalisation lives in the model: per-channel means and standard deviations of the states
(``x_mean``, ``x_std``, (n_x,)) and controls (``u_mean``, ``u_std``, (n_u,)) that it was
fitted with. Models fitted in normalised coordinates x_n = (x - x_mean) / x_std,
u_n = (u - u_mean) / u_std on the lifted state [x_n, rho(x), 1] (the last observable the
constant 1) are turned into the physical A, B above by :func:`to_physical`; the constant
observable carries the affine offsets of the normalisation, so the map stays exactly linear.

Window frame (the pose convention)
----------------------------------
A model never sees absolute world poses. Every prediction window (H + 1 consecutive
states, the first one being the initial state of the rollout) is expressed relative to the
window's first pose:

* ground vehicle (state names contain X, Y and a heading ``yaw`` or ``psi``): with the first
  pose (X_0, Y_0, psi_0), X' = cos psi_0 (X - X_0) + sin psi_0 (Y - Y_0),
  Y' = -sin psi_0 (X - X_0) + cos psi_0 (Y - Y_0), psi' = unwrap(psi) - psi_0, so every window
  starts at X' = Y' = psi' = 0 with the vehicle heading along +X'. Body-frame channels
  (vx, vy, yaw rate, ...) are unchanged. The heading is unwrapped along the window first
  (np.unwrap), so a logged wrap inside a window does not show as a 2 pi jump;
* quadrotor / point mass (names contain X, Y and possibly Z but no heading): the position
  is taken relative to the window's first position; velocities (world frame) are unchanged;
* anything else: no pose, the window frame is the identity.

:func:`to_window_frame` and :func:`from_window_frame` convert; they take the window's
first *world* state as the origin, so ``from_window_frame(to_window_frame(w), w[..., 0, :])``
gives back w (with the heading unwrapped along the window).
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Sequence

import numpy as np

HEADING_NAMES = ("yaw", "psi")
POSITION_NAMES = ("X", "Y", "Z")


@dataclass(frozen=True)
class PoseLayout:
    """Where the pose lives in a state vector.

    kind: "planar" (X, Y, heading), "position" (X, Y[, Z]) or "none"; position: column
    indices of the position channels; heading: column index of the heading, or None."""

    kind: str
    position: tuple[int, ...]
    heading: int | None

    @classmethod
    def of(cls, state_names: Sequence[str]) -> "PoseLayout":
        names = list(state_names)
        pos = tuple(names.index(n) for n in POSITION_NAMES if n in names)
        head = next((names.index(n) for n in HEADING_NAMES if n in names), None)
        if "X" in names and "Y" in names and head is not None:
            return cls("planar", (names.index("X"), names.index("Y")), head)
        if "X" in names and "Y" in names:
            return cls("position", pos, None)
        return cls("none", (), None)


def to_window_frame(states: np.ndarray, state_names: Sequence[str], layout: PoseLayout | None = None) -> np.ndarray:
    """World-frame windows (..., T, n_x) -> the same windows in their first pose's frame (..., T, n_x).

    ``state_names`` (n_x,) name the columns and decide the convention (module docstring);
    ``layout``: their ``PoseLayout`` when at hand (a caller that converts every tick keeps it)."""
    w = np.array(states, dtype=np.float64)  # copy
    lay = PoseLayout.of(state_names) if layout is None else layout
    if w.ndim < 2 or w.shape[-1] != len(state_names):
        raise ValueError(f"expected windows of shape (..., T, {len(state_names)}), got {w.shape}")
    return window_in_place(w, lay)


def window_in_place(w: np.ndarray, lay: PoseLayout) -> np.ndarray:
    """``to_window_frame`` on w (..., T, n_x) float64 itself (overwritten and returned), its layout
    given: for a caller that builds the windows in a new array anyway."""
    if lay.kind == "none":
        return w
    if lay.kind == "position":
        p = _columns(lay.position)
        w[..., p] = w[..., p] - w[..., :1, p]
        return w
    i, j = lay.position
    dx, dy = w[..., i] - w[..., :1, i], w[..., j] - w[..., :1, j]
    psi = unwrap_angles(w[..., lay.heading])
    psi0 = psi[..., :1]
    c, s = np.cos(psi0), np.sin(psi0)
    w[..., i] = c * dx + s * dy
    w[..., j] = -s * dx + c * dy
    w[..., lay.heading] = psi - psi0
    return w


def _columns(index: tuple[int, ...]) -> slice | list[int]:
    """Column indices as a slice where they are consecutive (a view, no fancy indexing), else a list."""
    return slice(index[0], index[-1] + 1) if list(index) == list(range(index[0], index[-1] + 1)) else list(index)


def unwrap_angles(angles: np.ndarray) -> np.ndarray:
    """``np.unwrap(angles, axis=-1)`` (the same numbers, a new array); a sequence without a step of pi
    or more, the usual window, is returned as it is without np.unwrap's corrections (all zero there)."""
    step = angles[..., 1:] - angles[..., :-1]          # np.diff's steps
    if not (np.abs(step) < np.pi).all():
        return np.unwrap(angles, axis=-1)
    out = np.array(angles, dtype=np.float64)
    out[..., 1:] += 0.0         # as np.unwrap adds its (zero) corrections: -0.0 becomes 0.0
    return out


def from_window_frame(window_states: np.ndarray, state_names: Sequence[str], origin: np.ndarray) -> np.ndarray:
    """Inverse of :func:`to_window_frame`: window-frame states (..., T, n_x) and the window's first
    world state ``origin`` (..., n_x) -> world-frame states (..., T, n_x) (heading unwrapped)."""
    w = np.array(window_states, dtype=np.float64)
    o = np.asarray(origin, dtype=np.float64)[..., None, :]
    lay = PoseLayout.of(state_names)
    if lay.kind == "none":
        return w
    p = list(lay.position)
    if lay.kind == "position":
        w[..., p] = w[..., p] + o[..., p]
        return w
    psi0 = o[..., lay.heading]
    c, s = np.cos(psi0), np.sin(psi0)
    x, y = w[..., p[0]].copy(), w[..., p[1]].copy()
    w[..., p[0]] = o[..., p[0]] + c * x - s * y
    w[..., p[1]] = o[..., p[1]] + s * x + c * y
    w[..., lay.heading] = w[..., lay.heading] + psi0
    return w


def to_physical(A_n: np.ndarray, B_n: np.ndarray, x_mean: np.ndarray, x_std: np.ndarray,
                u_mean: np.ndarray, u_std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Physical (A, B) of a linear model fitted on Z_n = [x_n, phi, 1] with normalised controls
    (``to_physical_scheduled`` without a scheduled input matrix)."""
    A, B, _ = to_physical_scheduled(A_n, B_n, np.zeros_like(np.asarray(B_n, dtype=np.float64)), 0,
                                    x_mean, x_std, u_mean, u_std)
    return A, B


def to_physical_scheduled(A_n: np.ndarray, B_n: np.ndarray, B_s_n: np.ndarray, schedule: int,
                          x_mean: np.ndarray, x_std: np.ndarray, u_mean: np.ndarray, u_std: np.ndarray
                          ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Physical (A, B, B_s) from a model fitted on Z_n = [x_n, phi, 1] (n_K,) with normalised
    controls, Z_n' = A_n Z_n + (B_n + s_n B_s_n) u_n with s_n = Z_n[schedule] (a state channel).

    A_n: (n_K, n_K), B_n, B_s_n: (n_K, n_u); the last lifted entry must be the constant 1 (its row
    of A_n is e_last, of B_n and B_s_n zero). With U = [x, phi, 1] = P Z_n, P = [[diag(x_std), 0,
    x_mean], [0, I, 0], [0, 0, 1]], u_n = D (u - u_mean), D = diag(1/u_std), and s_n = (s - m_s) / sd_s
    (m_s, sd_s the schedule channel's x_mean and x_std):
    A = P (A_n - B_n D u_mean e_last^T - B_s_n D u_mean e_schedule^T) P^-1,
    B = P (B_n - m_s / sd_s B_s_n) D,  B_s = P B_s_n D / sd_s,  so that U' = A U + (B + s B_s) u."""
    A_n = np.asarray(A_n, dtype=np.float64)
    B_n = np.asarray(B_n, dtype=np.float64)
    B_s_n = np.asarray(B_s_n, dtype=np.float64)
    n_K, n_x = A_n.shape[0], len(x_mean)
    x_std = np.asarray(x_std, dtype=np.float64)
    x_mean = np.asarray(x_mean, dtype=np.float64)
    u_mean = np.asarray(u_mean, dtype=np.float64)
    inv_us = 1.0 / np.asarray(u_std, dtype=np.float64)
    B_u, B_su = B_n * inv_us[None, :], B_s_n * inv_us[None, :]
    m_s, sd_s = x_mean[schedule], x_std[schedule]
    A_eff = A_n.copy()
    A_eff[:, -1] -= B_u @ u_mean
    A_eff[:, schedule] -= B_su @ u_mean
    P = np.eye(n_K)
    P[:n_x, :n_x] = np.diag(x_std)
    P[:n_x, -1] = x_mean
    P_inv = np.eye(n_K)
    P_inv[:n_x, :n_x] = np.diag(1.0 / x_std)
    P_inv[:n_x, -1] = -x_mean / x_std
    return P @ A_eff @ P_inv, P @ (B_u - (m_s / sd_s) * B_su), P @ B_su / sd_s


class LiftedLinearModel(ABC):
    """Upsilon(x) = [x, rho(x)], Upsilon_{k+1} = A Upsilon_k + (B + s_k B_s) u_k (module docstring).

    Subclasses implement :meth:`rho`. States given to ``lift``/``rollout`` are in the window
    frame. Attributes: A (n_K, n_K),
    B (n_K, n_u), state_names (n_x,), control_names (n_u,), dt (s), x_mean/x_std (n_x,),
    u_mean/u_std (n_u,); ``schedule`` the name of the state channel s that scales B_s (n_K, n_u)
    (None: a linear model, B_s zero) and ``schedule_index`` its column.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, *, state_names: Sequence[str],
                 control_names: Sequence[str], dt: float, x_mean: np.ndarray, x_std: np.ndarray,
                 u_mean: np.ndarray, u_std: np.ndarray, B_s: np.ndarray | None = None,
                 schedule: str | None = None) -> None:
        self.A = np.array(A, dtype=np.float64)
        self.B = np.array(B, dtype=np.float64)
        if (B_s is None) != (schedule is None):
            raise ValueError("a scheduled input matrix needs both B_s and the schedule channel's name")
        self.B_s = np.zeros_like(self.B) if B_s is None else np.array(B_s, dtype=np.float64)
        self.schedule = schedule
        self.state_names = tuple(state_names)
        if schedule is not None and schedule not in self.state_names:
            raise ValueError(f"the schedule channel {schedule!r} is not a state ({', '.join(self.state_names)})")
        self.schedule_index = self.state_names.index(schedule) if schedule is not None else None
        self.control_names = tuple(control_names)
        self.dt = float(dt)
        n_x, n_u = len(self.state_names), len(self.control_names)
        n_K = self.A.shape[0]
        if self.A.shape != (n_K, n_K) or n_K < n_x:
            raise ValueError(f"A must be square with at least {n_x} rows, got {self.A.shape}")
        if self.B.shape != (n_K, n_u) or self.B_s.shape != (n_K, n_u):
            raise ValueError(f"B and B_s must have shape ({n_K}, {n_u}), got {self.B.shape} and {self.B_s.shape}")
        self.x_mean, self.x_std = self._stat(x_mean, n_x, "x_mean"), self._stat(x_std, n_x, "x_std", True)
        self.u_mean, self.u_std = self._stat(u_mean, n_u, "u_mean"), self._stat(u_std, n_u, "u_std", True)
        if not (self.dt > 0.0):
            raise ValueError(f"dt must be positive, got {dt}")

    @staticmethod
    def _stat(v, n: int, what: str, positive: bool = False) -> np.ndarray:
        v = np.array(v, dtype=np.float64).reshape(-1)
        if v.shape != (n,) or not np.all(np.isfinite(v)) or (positive and np.any(v <= 0.0)):
            raise ValueError(f"{what} must be {n} finite{' positive' if positive else ''} numbers, got {v}")
        return v

    # ------------------------------------------------------------------ sizes
    @property
    def n_x(self) -> int:
        return len(self.state_names)

    @property
    def n_u(self) -> int:
        return len(self.control_names)

    @property
    def n_K(self) -> int:
        return int(self.A.shape[0])

    # ------------------------------------------------------------------ lifting
    def normalise_state(self, x: np.ndarray) -> np.ndarray:
        """(x - x_mean) / x_std, (..., n_x)."""
        return (np.asarray(x, dtype=np.float64) - self.x_mean) / self.x_std

    @abstractmethod
    def rho(self, x: np.ndarray) -> np.ndarray:
        """Observables beyond the state: x (..., n_x) window frame -> (..., n_K - n_x)."""

    def lift(self, x: np.ndarray) -> np.ndarray:
        """Upsilon(x) = [x, rho(x)]: x (..., n_x) -> (..., n_K)."""
        x = np.asarray(x, dtype=np.float64)
        if x.shape[-1] != self.n_x:
            raise ValueError(f"expected states (..., {self.n_x}), got {x.shape}")
        out = np.empty(x.shape[:-1] + (self.n_K,))
        out[..., : self.n_x] = x
        out[..., self.n_x:] = self.rho(x)
        return out

    def lifter(self, rows: int) -> "Lifter":
        """A ``Lifter`` of ``rows`` states (rows, n_x) at a time, for a caller that lifts that many
        at every tick (a model may keep its intermediate arrays); ``lift`` itself here."""
        return Lifter(self)

    # ------------------------------------------------------------------ prediction
    def rollout(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """Open-loop prediction: x0 (n_x,), controls (H, n_u) -> states (H + 1, n_x), row 0 = x0."""
        x0 = np.asarray(x0, dtype=np.float64)
        controls = np.asarray(controls, dtype=np.float64)
        if x0.shape != (self.n_x,) or controls.ndim != 2 or controls.shape[1] != self.n_u:
            raise ValueError(f"expected x0 ({self.n_x},) and controls (H, {self.n_u}), "
                             f"got {x0.shape} and {controls.shape}")
        return self.rollout_batch(x0[None], controls[None])[0]

    def rollout_batch(self, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
        """Batched :meth:`rollout`: x0 (M, n_x), controls (M, H, n_u) -> states (M, H + 1, n_x)."""
        x0 = np.asarray(x0, dtype=np.float64)
        controls = np.asarray(controls, dtype=np.float64)
        M, H = controls.shape[0], controls.shape[1]
        U = self.lift(x0)
        out = np.empty((M, H + 1, self.n_x))
        out[:, 0] = x0
        for k in range(H):
            U = self.step(U, controls[:, k])
            out[:, k + 1] = U[:, : self.n_x]
        return out

    @property
    def scheduled(self) -> bool:
        """Whether the input matrix depends on a state (B_s, module docstring)."""
        return self.schedule_index is not None

    def step(self, U: np.ndarray, u: np.ndarray) -> np.ndarray:
        """One prediction step: U (..., n_K), u (..., n_u) -> A U + (B + s B_s) u (..., n_K)."""
        return scheduled_step(self.A, self.B, self.B_s, self.schedule_index, U, u)

    def input_matrix(self, U: np.ndarray) -> np.ndarray:
        """B + s B_s at the lifted states U (..., n_K) -> (..., n_K, n_u)."""
        return scheduled_input_matrix(self.B, self.B_s, self.schedule_index, U)

    def jacobians(self, U: np.ndarray, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The step's Jacobians at (U (..., n_K), u (..., n_u)): A + (B_s u) e_s' (..., n_K, n_K) and
        B + s B_s (..., n_K, n_u)."""
        return scheduled_jacobians(self.A, self.B, self.B_s, self.schedule_index, U, u)


class Lifter:
    """``LiftedLinearModel.lift`` of a fixed number of states at a time (``LiftedLinearModel.lifter``):
    called on states x (rows, n_x), or through ``from_normalised`` with their normalised copy
    (x - x_mean) / x_std in float32 at hand (a model whose lift does not start from it ignores it);
    each returns a new (rows, n_K) array. ``encoder``: what a compiled lift needs, where there is one."""

    def __init__(self, model: "LiftedLinearModel") -> None:
        self._lift = model.lift

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return self._lift(x)

    def from_normalised(self, x: np.ndarray, normalised: np.ndarray) -> np.ndarray:
        return self._lift(x)

    def encoder(self) -> tuple | None:
        """The arguments of ``encoder_kernel.encoder_loop`` after h (weights, biases, dims, work) for a
        compiled lift of these rows, or None: a lift that is not a deep Koopman encoder."""
        return None


def scheduled_step(A: np.ndarray, B: np.ndarray, B_s: np.ndarray, schedule: int | None, U: np.ndarray,
                   u: np.ndarray) -> np.ndarray:
    """A U + (B + s B_s) u, s = U[..., schedule] (the plain A U + B u when ``schedule`` is None)."""
    U, u = np.asarray(U, dtype=np.float64), np.asarray(u, dtype=np.float64)
    nxt = U @ A.T + u @ B.T
    if schedule is not None:
        nxt = nxt + U[..., schedule, None] * (u @ B_s.T)
    return nxt


def scheduled_input_matrix(B: np.ndarray, B_s: np.ndarray, schedule: int | None, U: np.ndarray) -> np.ndarray:
    """B + s B_s at the lifted states U (..., n_K) -> (..., n_K, n_u)."""
    U = np.asarray(U, dtype=np.float64)
    if schedule is None:
        return np.broadcast_to(B, U.shape[:-1] + B.shape)
    return B + U[..., schedule, None, None] * B_s


def scheduled_jacobians(A: np.ndarray, B: np.ndarray, B_s: np.ndarray, schedule: int | None, U: np.ndarray,
                        u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """d/dU and d/du of ``scheduled_step`` at (U (..., n_K), u (..., n_u)): A + (B_s u) e_s' and B + s B_s."""
    u = np.asarray(u, dtype=np.float64)
    A_J = np.array(np.broadcast_to(A, u.shape[:-1] + A.shape))
    if schedule is not None:
        A_J[..., :, schedule] += u @ B_s.T
    return A_J, np.array(scheduled_input_matrix(B, B_s, schedule, U))
