"""GP compensation of the Koopman model error, paper section III-B ("Online Compensation").

Nominal latent model (eq. latent_vehicle_dynamics): Upsilon_{k+1} = A Upsilon_k + B u_k.
GP input z = [Upsilon[z_index], u] (n_z = len(z_index) + n_u), GP output d (n_y,):

    d(z_k) = B_d^+ (Upsilon_{k+1} - A Upsilon_k - B u_k)                      (error_model)
    Upsilon_{k+1} = A Upsilon_k + B u_k + B_d m(z_k)                          (Dynamics_for_planning)
    A_d = A + B_d dm/dUpsilon,   B_d,k = B + B_d dm/du                        (JocabianMatrices)

``OnlineCompensator`` owns an ALD dictionary (the inducing inputs of the next refit), a FIFO
buffer of recent finite samples (the training set of the next refit) and the current
immutable ``FITCGP``. ``observe`` is the cheap per-step call (O(n_y m^2)): every finite
sample is folded into the current GP with ``add_sample`` and offered to the ALD dictionary.
``refit`` is the worker call; it builds a new GP and hands it over by one assignment. Split
for a worker in another process: ``refit_job()`` snapshots what the refit needs (a picklable
``RefitJob``), ``refit_job(job)`` (module function) fits anywhere, ``install(job, model)`` hands
the result over and replays the samples that arrived meanwhile.
"""

from __future__ import annotations

import math
from collections import deque
from typing import NamedTuple

import numpy as np

from vflpcd.core.dynamics.ald import ALDDictionary
from vflpcd.core.dynamics.lifted import PoseLayout, scheduled_jacobians, scheduled_step
from vflpcd.core.dynamics.sparse_gp import DEFAULT_BOUNDS, FITCGP, SEHyper, refit


def channel_rows(state_names, channels) -> tuple[list[int], list[int]]:
    """The rows of the GP's output ``channels`` among ``state_names``, and those of them that enter its
    input z: the pose channels (position, heading) are left out, as a sample's pose is the origin of
    its window frame (``lifted.to_window_frame``), zero in every training input. ValueError names a
    channel that is not a state."""
    names = list(state_names)
    missing = [n for n in channels if n not in names]
    if missing:
        raise ValueError(f"compensation channels {missing} are not states of the model {tuple(names)}")
    layout = PoseLayout.of(names)
    pose = set(layout.position) | ({layout.heading} if layout.heading is not None else set())
    rows = [names.index(n) for n in channels]
    return rows, [r for r in rows if r not in pose]


class TrainingPairs(NamedTuple):
    """GP training pairs: z (N', n_z), d (N', n_y), number of non-finite samples dropped,
    keep (N,) mask of the input samples that were kept."""

    z: np.ndarray
    d: np.ndarray
    dropped: int
    keep: np.ndarray


class KoopmanCompensation:
    """Model-error compensation around Upsilon_{k+1} = A Upsilon_k + B u_k.

    A (n_K, n_K), B (n_K, n_u), B_d (n_K, n_y) (e.g. [0_3 I_3 0]^T), z_index (n_zx,) indices
    of Upsilon entering the GP input z = [Upsilon[z_index], u]; for a model with a scheduled input
    matrix (``lifted``: B + s B_s) B_s (n_K, n_u) and ``schedule``, the column of s in Upsilon.
    """

    def __init__(self, A: np.ndarray, B: np.ndarray, B_d: np.ndarray, z_index, B_s: np.ndarray | None = None,
                 schedule: int | None = None) -> None:
        if (B_s is None) != (schedule is None):
            raise ValueError("a scheduled input matrix needs both B_s and the schedule column")
        self.A = np.array(A, dtype=float)
        self.B = np.array(B, dtype=float)
        self.B_s = np.zeros_like(self.B) if B_s is None else np.array(B_s, dtype=float)
        self.schedule = schedule
        self.B_d = np.array(B_d, dtype=float)
        self.z_index = np.array(z_index, dtype=np.int64).reshape(-1)
        n_K = self.A.shape[0]
        if (self.A.shape != (n_K, n_K) or self.B.ndim != 2 or self.B.shape[0] != n_K
                or self.B_s.shape != self.B.shape or self.B_d.ndim != 2 or self.B_d.shape[0] != n_K
                or np.any(self.z_index < 0) or np.any(self.z_index >= n_K)):
            raise ValueError("inconsistent shapes of A, B, B_d or z_index")
        self.n_K, self.n_u, self.n_y = n_K, self.B.shape[1], self.B_d.shape[1]
        self.n_z = self.z_index.size + self.n_u
        self.B_d_pinv = np.linalg.pinv(self.B_d)              # (n_y, n_K)

    def gp_input(self, U: np.ndarray, u: np.ndarray) -> np.ndarray:
        """z = [U[..., z_index], u]: U (..., n_K), u (..., n_u) -> (..., n_z)."""
        U, u = np.asarray(U, dtype=float), np.asarray(u, dtype=float)
        return np.concatenate([U[..., self.z_index], u], axis=-1)

    def corrected_next(self, nxt: np.ndarray, U: np.ndarray, u: np.ndarray, gp: FITCGP, loop=None) -> np.ndarray:
        """nxt (N, n_K) + B_d m(z) at z = ``gp_input(U, u)`` (U (N, n_K), u (N, n_u)): the horizon's
        nominal next lifted states corrected by the GP's mean (a new array). ``loop``:
        ``gp_kernel.corrected_next_loop`` compiled (the same numbers to 1e-12), None for numpy."""
        if loop is not None:          # the loop does not check its indices (numpy's shape errors): checked here
            if U.shape != (len(nxt), self.n_K) or u.shape != (len(nxt), self.n_u) or nxt.shape[1:] != (self.n_K,):
                raise ValueError(f"expected nxt and U (N, {self.n_K}), u (N, {self.n_u}); "
                                 f"got {nxt.shape}, {U.shape}, {u.shape}")
            return loop(nxt, U, u, *self.mean_arguments(gp))
        return nxt + gp.means(self.gp_input(U, u)) @ self.B_d.T

    def mean_arguments(self, gp: FITCGP) -> tuple:
        """``gp_kernel.corrected_next_loop``'s arguments after nxt, U and u: the GP's input columns,
        its arrays and B_d. Raises ValueError for a GP of another input or output count (the loop
        does not check its indices)."""
        if gp.Zm.shape[1] != self.n_z or gp.alpha.shape[0] != self.n_y:
            raise ValueError(f"a GP of {gp.Zm.shape[1]} inputs and {gp.alpha.shape[0]} outputs cannot "
                             f"correct this model ({self.n_z} inputs, {self.n_y} outputs)")
        return self.z_index, gp.Zm, gp.hyp.sf2, gp._nh_inv_ell2, gp.alpha, self.B_d

    def nominal(self, U: np.ndarray, u: np.ndarray) -> np.ndarray:
        """A U + (B + s B_s) u for U (..., n_K), u (..., n_u) -> (..., n_K)."""
        return scheduled_step(self.A, self.B, self.B_s, self.schedule, U, u)

    def residual_target(self, U_k: np.ndarray, u_k: np.ndarray, U_next: np.ndarray) -> TrainingPairs:
        """Eq. (error_model) over N samples: U_k (N, n_K), u_k (N, n_u), U_next (N, n_K)
        (a single sample may be 1-D). Samples with any non-finite entry are dropped and
        counted; only finite pairs are returned."""
        U_k, u_k, U_next = (np.atleast_2d(np.asarray(x, dtype=float)) for x in (U_k, u_k, U_next))
        keep = np.all(np.isfinite(np.hstack([U_k, u_k, U_next])), axis=1)
        U_k, u_k, U_next = U_k[keep], u_k[keep], U_next[keep]
        z = self.gp_input(U_k, u_k)
        d = (U_next - self.nominal(U_k, u_k)) @ self.B_d_pinv.T          # (error_model)
        ok = np.all(np.isfinite(d), axis=1)                              # overflow
        keep[np.flatnonzero(keep)[~ok]] = False
        return TrainingPairs(z[ok], d[ok], int((~keep).sum()), keep)

    def residual_sample(self, U_k: np.ndarray, u_k: np.ndarray, U_next: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray] | None:
        """``residual_target`` of one sample U_k (n_K,), u_k (n_u,), U_next (n_K,): (z (n_z,), d (n_y,)),
        None when a number of it, or its residual d (overflow), is not finite."""
        U_k, u_k, U_next = (np.asarray(x, dtype=float) for x in (U_k, u_k, U_next))
        if not all(map(math.isfinite, U_k.tolist() + u_k.tolist() + U_next.tolist())):
            return None
        d = (U_next - self.nominal(U_k, u_k)) @ self.B_d_pinv.T          # (error_model)
        if not all(map(math.isfinite, d.tolist())):
            return None
        return self.gp_input(U_k, u_k), d

    def predict(self, U: np.ndarray, u: np.ndarray, gp: FITCGP | None) -> np.ndarray:
        """Eq. (Dynamics_for_planning): A U + B u + B_d m(z). U (n_K,) or (N, n_K), u (n_u,)
        or (N, n_u) -> same leading shape as U. ``gp=None`` gives the nominal model."""
        nom = self.nominal(U, u)
        if gp is None:
            return nom
        z = self.gp_input(U, u)
        mean = gp.mean(z) if z.ndim == 1 else gp.means(z)
        return nom + mean @ self.B_d.T

    def jacobians(self, U_r: np.ndarray, u_r: np.ndarray, gp: FITCGP | None
                  ) -> tuple[np.ndarray, np.ndarray]:
        """Eq. (JocabianMatrices) at (U_r (n_K,), u_r (n_u,)) -> A_d (n_K, n_K), B_d,k (n_K, n_u),
        with dm/dUpsilon from dm/dz by the chain rule through z_index."""
        A, B = scheduled_jacobians(self.A, self.B, self.B_s, self.schedule, U_r, u_r)     # the nominal step's
        if gp is None:
            return A, B
        _, J = gp.mean_jacobian(self.gp_input(U_r, u_r))                  # (n_y, n_z)
        nx = self.z_index.size
        dm_dU = np.zeros((self.n_y, self.n_K))
        np.add.at(dm_dU, (slice(None), self.z_index), J[:, :nx])
        return A + self.B_d @ dm_dU, B + self.B_d @ J[:, nx:]


class RefitJob(NamedTuple):
    """What one refit needs: the sample sequence number at the snapshot, the inducing inputs
    Zm (m, n_z), the training set Z (n, n_z), Y (n, n_y), the previous model, the starting
    hyper-parameters and the refit options."""

    seq0: int
    Zm: np.ndarray
    Z: np.ndarray
    Y: np.ndarray
    prev: FITCGP | None
    hyp0: SEHyper
    options: dict


def refit_job(job: RefitJob) -> FITCGP | None:
    """Run a refit snapshot (worker side, any process): the new model, or ``job.prev`` when the
    fit is rejected."""
    return refit(job.prev, job.Zm, job.Z, job.Y, job.hyp0, **job.options)


class OnlineCompensator:
    """ALD dictionary + FIFO training buffer + current immutable FITC GP.

    comp: the compensation structure; hyp0: initial hyper-parameters (n_y outputs);
    nu, m_max: ALD threshold and dictionary cap (= number of inducing points); n_max: training
    buffer length; ald_ell: ALD kernel length scale (default min(hyp0.ell); ALD uses sf2 = 1,
    so nu is relative). Refit options (optimise, bounds, jitter, max_cond) go to ``refit``;
    ``add_loop``: ``gp_kernel.add_sample_loop`` compiled, for the per-sample update, ``ald_loop``:
    ``gp_kernel.ald_delta_loop`` compiled, for the dictionary's test (None: numpy).
    Every call comes from the owner's thread; a refit runs elsewhere (a worker) on the snapshot
    that ``refit_job`` takes, and ``install`` replays into its model the samples observed meanwhile.
    """

    def __init__(self, comp: KoopmanCompensation, hyp0: SEHyper, *, nu: float = 1e-2,
                 m_max: int = 64, n_max: int = 300, ald_ell: float | None = None,
                 optimise: bool = True, bounds=DEFAULT_BOUNDS, jitter: float = 1e-8,
                 max_cond: float = 1e12, add_loop=None, ald_loop=None) -> None:
        if hyp0.n_y != comp.n_y:
            raise ValueError(f"hyp0 has {hyp0.n_y} outputs, B_d has {comp.n_y}")
        self.comp, self.hyp0 = comp, hyp0
        ell = float(np.min(hyp0.ell)) if ald_ell is None else float(ald_ell)
        self.dictionary = ALDDictionary(comp.n_z, nu, m_max, 1.0, ell, delta_loop=ald_loop)
        self._buffer: deque[tuple[int, np.ndarray, np.ndarray]] = deque(maxlen=n_max)
        self._seq = 0
        self._model: FITCGP | None = None
        self._refit_kw = dict(optimise=optimise, bounds=bounds, jitter=jitter, max_cond=max_cond)
        self.dropped = 0          # non-finite samples never fed to the GP
        self._add_loop = add_loop  # gp_kernel.add_sample_loop compiled (FITCGP.add_sample's loop), None: numpy

    @property
    def model(self) -> FITCGP | None:
        """The current immutable GP, or None before the first successful refit."""
        return self._model

    @property
    def n_buffered(self) -> int:
        return len(self._buffer)

    def observe(self, U_k: np.ndarray, u_k: np.ndarray, U_next: np.ndarray) -> bool:
        """One transition U_k (n_K,), u_k (n_u,), U_next (n_K,). Returns False (and counts it
        in ``dropped``) when non-finite; otherwise buffers it, offers z to the ALD dictionary
        and folds it into the current GP (O(n_y m^2))."""
        pair = self.comp.residual_sample(U_k, u_k, U_next)
        if pair is None:
            self.dropped += 1
            return False
        z, d = pair
        self._seq += 1
        self._buffer.append((self._seq, z, d))
        self.dictionary.consider(z, tag=self._seq)
        if self._model is not None:
            self._model = self._model.add_sample(z, d, self._add_loop)
        return True

    def refit(self) -> FITCGP | None:
        """Refit now, on this thread: hyper-parameters + FITC posterior on the buffer with the dictionary as
        inducing inputs. On an ill-conditioned result the previous model is kept (logged by
        ``sparse_gp.refit``). Returns the model now current."""
        job = self.refit_job()
        if job is None:
            return self._model
        return self.install(job, refit_job(job))

    def refit_job(self) -> RefitJob | None:
        """A snapshot for ``refit_job`` (None while the buffer or the dictionary is empty)."""
        if not self._buffer or self.dictionary.m == 0:
            return None
        prev = self._model
        return RefitJob(self._seq, self.dictionary.points, np.array([s[1] for s in self._buffer]),
                        np.array([s[2] for s in self._buffer]), prev,
                        prev.hyp if prev is not None else self.hyp0, dict(self._refit_kw))

    def install(self, job: RefitJob, new: FITCGP | None) -> FITCGP | None:
        """Hand a refit's model over, with the samples observed since its snapshot folded in.
        Returns the model now current."""
        if new is not job.prev and new is not None:
            for seq, z, d in self._buffer:           # samples that arrived meanwhile
                if seq > job.seq0:
                    new = new.add_sample(z, d, self._add_loop)
            self._model = new
        return self._model
