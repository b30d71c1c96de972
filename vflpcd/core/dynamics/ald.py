"""Approximate linear dependence (ALD) dictionary (Engel et al., 2004), paper section III-B.

A candidate z is tested against the dictionary D (size m) with the SE kernel k:

    delta(z) = k(z, z) - k_D(z)^T K_DD^-1 k_D(z)

and admitted when delta > nu. K_DD^-1 is kept explicitly and updated in O(m^2) per admission
or removal (block / Schur-complement inverse formulas).

When the dictionary is full (m == m_max) a novel candidate REPLACES the most redundant
element, i.e. the one with the smallest leave-one-out ALD value 1 / [K_DD^-1]_ii, provided
the candidate's delta exceeds that value; otherwise it is rejected. The dictionary thus
never exceeds m_max and keeps spreading over the visited input space. Non-finite candidates
are rejected and counted.
"""

from __future__ import annotations

import math

import numpy as np

from vflpcd.core.dynamics.sparse_gp import sq_distances


class ALDDictionary:
    """ALD dictionary of inputs z (n_z,) with threshold ``nu``, size cap ``m_max`` and an SE
    kernel (sf2, ell). ``points`` (m, n_z), ``tags`` (m,) user labels (e.g. sample indices).

    Counters: ``n_admitted``, ``n_replaced``, ``n_rejected_dependent`` (delta <= nu),
    ``n_rejected_full`` (full and not more novel than the most redundant element),
    ``n_rejected_nonfinite``. ``delta_loop``: ``gp_kernel.ald_delta_loop`` compiled, for ``delta``
    (None: numpy).
    """

    def __init__(self, n_z: int, nu: float, m_max: int, sf2: float = 1.0, ell: float = 1.0,
                 delta_loop=None) -> None:
        if nu <= 0 or m_max < 1 or sf2 <= 0 or ell <= 0:
            raise ValueError("need nu > 0, m_max >= 1, sf2 > 0, ell > 0")
        self.n_z, self.nu, self.m_max, self.sf2, self.ell = n_z, float(nu), int(m_max), float(sf2), float(ell)
        self._nh = -0.5 / self.ell ** 2         # the SE kernel's exponent factor
        self._delta_loop = delta_loop           # gp_kernel.ald_delta_loop compiled (the same numbers), None: numpy
        self._D = np.empty((0, n_z))
        self._tags = np.empty(0, dtype=np.int64)
        self._P = np.empty((0, 0))            # K_DD^-1 (m, m)
        self._next_tag = 0
        self.n_admitted = self.n_replaced = 0
        self.n_rejected_dependent = self.n_rejected_full = self.n_rejected_nonfinite = 0

    @property
    def m(self) -> int:
        return self._D.shape[0]

    @property
    def points(self) -> np.ndarray:
        """Dictionary inputs (m, n_z), a copy."""
        return self._D.copy()

    @property
    def tags(self) -> np.ndarray:
        """Tags (m,) of the dictionary elements, a copy."""
        return self._tags.copy()

    def _k(self, z: np.ndarray) -> np.ndarray:
        return self.sf2 * np.exp(self._nh * sq_distances(self._D, z)[:, 0])

    def delta(self, z: np.ndarray) -> float:
        """ALD value of z (n_z,) against the current dictionary (k(z,z) when empty)."""
        z = np.asarray(z, dtype=float).reshape(-1)
        if z.shape != (self.n_z,):
            raise ValueError(f"expected z of {self.n_z} numbers, got {z.size}")
        if self._delta_loop is not None:      # the loop does not check its indices: the shape is checked above
            return float(self._delta_loop(self._D, z, self._P, self.sf2, self._nh))
        k = self._k(z)
        return float(self.sf2 - k @ (self._P @ k))

    def _append(self, z: np.ndarray, tag: int) -> None:
        k = self._k(z)
        a = self._P @ k
        d = self.sf2 - k @ a
        m = self.m
        P = np.empty((m + 1, m + 1))
        P[:m, :m] = self._P + np.outer(a, a) / d
        P[:m, m] = P[m, :m] = -a / d
        P[m, m] = 1.0 / d
        self._P = P
        self._D = np.vstack([self._D, z])
        self._tags = np.append(self._tags, tag)

    def _remove(self, i: int) -> None:
        last = self.m - 1
        for arr in (self._D, self._tags):
            arr[[i, last]] = arr[[last, i]]
        P = self._P
        P[[i, last], :] = P[[last, i], :]
        P[:, [i, last]] = P[:, [last, i]]
        self._P = P[:last, :last] - np.outer(P[:last, last], P[last, :last]) / P[last, last]
        self._D, self._tags = self._D[:last].copy(), self._tags[:last].copy()

    def consider(self, z: np.ndarray, tag: int | None = None) -> bool:
        """Test z (n_z,) and admit it (possibly replacing an element) if novel; O(m^2).
        Returns True when z entered the dictionary."""
        z = np.asarray(z, dtype=float).reshape(-1)
        if tag is None:
            tag = self._next_tag
        self._next_tag = max(self._next_tag, int(tag)) + 1
        if z.shape != (self.n_z,) or not all(map(math.isfinite, z.tolist())):
            self.n_rejected_nonfinite += 1
            return False
        d = self.delta(z)
        if not d > self.nu:
            self.n_rejected_dependent += 1
            return False
        if self.m >= self.m_max:
            loo = 1.0 / np.diag(self._P)     # leave-one-out ALD value of each element
            j = int(np.argmin(loo))
            if not d > loo[j]:
                self.n_rejected_full += 1
                return False
            self._remove(j)
            self.n_replaced += 1
        self._append(z, int(tag))
        self.n_admitted += 1
        return True


def sparsify(Z: np.ndarray, Y: np.ndarray | None, nu: float, m_max: int,
             sf2: float = 1.0, ell: float = 1.0) -> np.ndarray:
    """Run ALD over a batch Z (n, n_z) in order; rows whose z or y (Y (n, n_y), optional)
    is non-finite are skipped. Returns the kept row indices (sorted, int)."""
    Z = np.asarray(Z, dtype=float)
    ok = np.all(np.isfinite(Z), axis=1)
    if Y is not None:
        ok &= np.all(np.isfinite(np.asarray(Y, dtype=float).reshape(Z.shape[0], -1)), axis=1)
    ald = ALDDictionary(Z.shape[1], nu, m_max, sf2, ell)
    for i in range(Z.shape[0]):
        if ok[i]:
            ald.consider(Z[i], tag=i)
        else:
            ald.n_rejected_nonfinite += 1
    return np.sort(ald.tags)
