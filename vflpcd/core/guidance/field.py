"""The kinodynamic composite field chi_c of one path stretch and its obstacles.

Terms of obstacles that neither move nor depend on the trajectory's history (the static
actual obstacles) are evaluated on the grid once; virtual obstacles (whose effect depends on
whether the trajectory has already been inside the actual reactive region, the paper's second
remark after eq. S_xi) and moving obstacles (whose position depends on the time the trajectory
reaches a point) are evaluated at the point during integration.

Virtual obstacles attract the trajectory to their repulsive boundary Q_vrtl (the paper: "it
will be attracted towards the virtual repulsive boundary"), so their guiding term is
gamma_i E grad varphi_i - k_r (varphi_i - c_i) grad varphi_i, which converges to varphi_i = c_i.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vflpcd.core.guidance.primitives import bump, guiding, s_virtual, unit
from vflpcd.core.guidance.implicit import ObstacleImplicit


@dataclass(frozen=True)
class ActualTerm:
    """An actual obstacle with its direction gamma_i (+1 / -1) and its passing side (+1 left, -1 right);
    ``crosses``: a mover that crosses the route (faster than the planner's ``CROSSING_SPEED``)."""

    implicit: ObstacleImplicit
    gamma: float
    side: float
    crosses: bool = False


@dataclass(frozen=True)
class VirtualTerm:
    """A virtual obstacle (i in I') serving the actual obstacle ``parent``; it acts only while
    the path progress is below ``x_stop`` (where the path enters the parent's reactive region):
    its job is the direction change before R_actl."""

    implicit: ObstacleImplicit
    gamma: float
    parent: ObstacleImplicit
    x_stop: float = np.inf


@dataclass
class GuidanceField:
    """chi_c of eq. (guiding_vector_dynamic_constraint) for a path implicit with direction gamma_0."""

    path: object
    gamma0: float
    k_p: float
    k_r: float
    l1: float
    l2: float
    k_c: float
    statics: list[ActualTerm] = field(default_factory=list)
    movers: list[ActualTerm] = field(default_factory=list)
    virtuals: list[VirtualTerm] = field(default_factory=list)

    # ----------------------------------------------------------------- pieces
    def path_unit(self, pts: np.ndarray) -> np.ndarray:
        """chi_P^ at pts (N, 2)."""
        phi, g = self.path.value_grad(pts)
        return unit(guiding(self.gamma0, self.k_p, phi, g))[0]

    def actual_terms(self, terms: list[ActualTerm], pts: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """(prod cup_Q_i (N,), sum cap_R_i chi_R_i^ (N, 2)) over the given actual obstacles."""
        P = np.ones(len(pts))
        V = np.zeros((len(pts), 2))
        for term in terms:
            o = term.implicit
            phi, g = o.value_grad(pts, t)
            cup, cap = bump(phi, o.c, self.l1, self.l2)
            P *= cup
            V += cap[:, None] * unit(guiding(term.gamma, self.k_r, phi, g))[0]
        return P, V

    def virtual_terms(self, pts: np.ndarray, enabled: np.ndarray | None = None,
                      t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """(prod s_i (N,), sum (1 - s_i) chi_R_i^ (N, 2)) over the virtual obstacles; enabled (n_virtual,) bool.

        The buffer region of a virtual obstacle is in R_vrtl minus every actual reactive region
        (not only its own obstacle's), so that a virtual obstacle never pulls the robot towards
        another obstacle's repulsive boundary.
        """
        free = self.actual_terms(self.statics + self.movers, pts, t)[0] == 1.0
        P = np.ones(len(pts))
        V = np.zeros((len(pts), 2))
        for i, term in enumerate(self.virtuals):
            if enabled is not None and not enabled[i]:
                continue
            o = term.implicit
            phi, g = o.value_grad(pts)
            before = self.path.progress(pts) < term.x_stop
            in_buffer = (phi < 0.0) & (term.parent.value(pts) > 0.0) & free & before  # M_b = ex R_actl ∩ in R_vrtl
            s = s_virtual(phi, o.c, self.k_c, in_buffer)
            P *= s
            V += (1.0 - s)[:, None] * unit(guiding(term.gamma, self.k_r, phi - o.c, g))[0]
        return P, V

    # ----------------------------------------------------------------- whole fields
    def composite(self, pts: np.ndarray, t: float = 0.0) -> np.ndarray:
        """chi of eq. (eq_yaocvf) over the actual obstacles (no virtual ones), (N, 2)."""
        P, V = self.actual_terms(self.statics + self.movers, pts, t)
        return P[:, None] * self.path_unit(pts) + V

    def kinodynamic(self, pts: np.ndarray, t: float = 0.0, enabled: np.ndarray | None = None) -> np.ndarray:
        """chi_c of eq. (guiding_vector_dynamic_constraint), (N, 2)."""
        P, V = self.actual_terms(self.statics + self.movers, pts, t)
        Pv, Vv = self.virtual_terms(pts, enabled, t)
        return (P * Pv)[:, None] * self.path_unit(pts) + V + Vv
