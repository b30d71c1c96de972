"""Guidance for the quadrotor: the 3-D composite field integrated by eq. (xi_r) and speed-planned.

Each step evaluates the field at the point (a 3-D grid of the whole corridor would hold
millions of cells); the rest follows the planar planner: the side rule (pass on the side -
left, right, above or below - that leaves the path least), the direction fixed at first entry
(flipped if it would circle backwards), the paper's near-zero rule, Gaussian smoothing and speed
planning. Virtual obstacles are a
planar construction and are not used in 3-D; the centripetal limit is met by speed planning.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from vflpcd.core.guidance.field3d import GraphPath3D, GuidanceField3D, Obstacle3D
from vflpcd.core.guidance.grid import BACKWARDS
from vflpcd.core.guidance.integrate_kernel import step_time
from vflpcd.core.guidance.implicit import GuidanceError, ObstacleImplicit, graph_horizon
from vflpcd.core.guidance.planner import MOVER_PASSES, GuidancePlan, PlannerBase
from vflpcd.core.guidance.primitives import cup_at
from vflpcd.core.guidance.speed import step_times
from vflpcd.core.guidance.trajectory import timed_trajectory
from vflpcd.core.obstacles import ObstacleState


@dataclass(frozen=True)
class Prepared3D:
    field: GuidanceField3D
    s0: float
    s_end: float
    x_end: float
    ends_path: bool


class GuidancePlanner3D(PlannerBase):
    """Plans the reference of a quadrotor on a 3-D reference path."""

    dim = 3

    def obstacle(self, o: ObstacleImplicit, t: float = 0.0) -> Obstacle3D:
        """Side e and detour plane by the rule in the module docstring, gamma so that the
        circulation at the passing point runs along the path."""
        center = o.center_at(t)
        proj = self.path.project(center)
        tangent = proj.tangent
        left = np.cross([0.0, 0.0, 1.0], tangent)
        if np.linalg.norm(left) < 1e-6:
            raise GuidanceError(f"obstacle {o.name!r}: the path is vertical there; no detour plane")
        left /= np.linalg.norm(left)
        up = np.cross(tangent, left)
        dirs = np.random.default_rng(0).normal(size=(2000, 3))
        dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
        boundary = center + (dirs * ((1.0 + o.c) / o.norm(dirs @ o.Rz))[:, None])
        best = None
        for e in (left, -left, up, -up):
            reach = float(np.max((boundary - proj.point) @ e))
            if best is None or reach < best[0] - 1e-9:
                best = (reach, e)
        e = best[1]
        m = np.cross(tangent, e)
        u = e @ o.Rz
        p_pass = center + e / o.norm(u[None, :])[0]
        _, g = o.value_grad(p_pass[None, :], t)
        along = float(tangent @ np.cross(g[0], m))
        return Obstacle3D(implicit=o, side=e, normal=m, gamma=float(np.sign(along) or 1.0))

    def prepare(self, s0: float, statics: Sequence[ObstacleState]) -> Prepared3D:
        p = self.params
        s0 = float(np.clip(s0, 0.0, self.path.length))
        s_end = graph_horizon(self.path, s0, p.horizon)
        ends_path = s_end >= self.path.length - 1e-9
        graph = GraphPath3D.from_reference(self.path, s0 - min(5.0, s0), s_end)
        pts = self.path.point_at(np.linspace(s0, s_end, 200))
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        obs = list(self.static_terms(statics, lo, hi, self.obstacle).values())
        if ends_path:
            self.check_clear(self.path.point_at(self.path.length), obs, 0.0, "goal")
        field = GuidanceField3D(path=graph, k_p=p.k_p, k_r=p.k_r, l1=p.l1, l2=p.l2, statics=obs)
        x_end = float(graph.progress(self.path.point_at(s_end)[None, :])[0]) - (p.beta if ends_path else 0.0)
        return Prepared3D(field=field, s0=s0, s_end=s_end, x_end=x_end, ends_path=ends_path)

    def plan(self, prepared: Prepared3D, start: np.ndarray, t0: float, v0: float,
             movers: Sequence[ObstacleState] = ()) -> GuidancePlan:
        p = self.params
        field = prepared.field
        if movers:
            field = replace(field, movers=[self.obstacle(self.implicit(o), t0) for o in movers])
        start = self.check_clear(start, field.statics + field.movers, t0, "start")
        steps = None
        for _ in range(1 + (MOVER_PASSES if movers else 0)):  # moving obstacles at the last pass's times
            raw, reached, inherited, gammas = self._integrate(
                field, start, prepared.x_end, t0, max(v0, 0.5 * self.v_desired),
                int(4 * (prepared.s_end - prepared.s0 + 20.0) / p.beta), steps)
            xyz = self.safe_smooth(raw, field.statics + field.movers, t0, steps, field.path)
            s, kappa, v = self.speed_plan(xyz, self.v_desired, v0, prepared.ends_path and reached)
            steps = step_times(s, v, t0, p.beta)
        return GuidancePlan(trajectory=timed_trajectory(xyz, s, v, t0, self.dt), xy=xyz, s=s, kappa=kappa, v=v,
                            raw=raw, reached=reached, inherited=inherited, field=field, gammas=gammas)

    def _integrate(self, field: GuidanceField3D, start: np.ndarray, x_end: float, t0: float, speed: float,
                   max_steps: int, step_times: np.ndarray | None):
        """Eq. (xi_r) with the field evaluated at each point: (points (K, 3), reached, inherited, gammas)."""
        p = self.params
        obstacles = field.statics + field.movers
        gammas: list[float | None] = [None] * len(obstacles)
        po, pd = field.path.progress_frame()
        if step_times is not None:
            step_times = step_times.tolist()      # plain floats, indexed every step
        x, y, z = (float(v) for v in start)
        pts, prev, inherited = [(x, y, z)], None, 0
        # per obstacle, in plain floats: its centre at its stamp, velocity, stamp, squared reach
        placed = [(ob, *ob.implicit.center.tolist(), *ob.implicit.velocity.tolist(), ob.implicit.stamp,
                   ob.implicit.reach ** 2) for ob in obstacles]
        for k in range(max_steps):
            t = step_time(k, t0, p.beta, speed, step_times)
            P, Vx, Vy, Vz = 1.0, 0.0, 0.0, 0.0
            for n, (ob, cx, cy, cz, vx, vy, vz, stamp, reach2) in enumerate(placed):
                dt = t - stamp
                if (x - cx - vx * dt) ** 2 + (y - cy - vy * dt) ** 2 + (z - cz - vz * dt) ** 2 > reach2:
                    continue
                if gammas[n] is None:
                    phi0, chi0 = field.repulsive_unit_at(ob, ob.gamma, x, y, z, t)
                    if phi0 >= 0.0:
                        continue
                    tangent = field.path.tangent(np.array([x, y, z]))      # first entry: keep unless backwards
                    along = chi0[0] * tangent[0] + chi0[1] * tangent[1] + chi0[2] * tangent[2]
                    gammas[n] = -ob.gamma if along < BACKWARDS else ob.gamma
                phi, chi = field.repulsive_unit_at(ob, gammas[n], x, y, z, t)
                cup = cup_at(phi, ob.implicit.c, field.l1, field.l2)
                P *= cup
                Vx, Vy, Vz = Vx + (1.0 - cup) * chi[0], Vy + (1.0 - cup) * chi[1], Vz + (1.0 - cup) * chi[2]
            ux, uy, uz = field.path_unit_at(x, y, z)
            cx_, cy_, cz_ = P * ux + Vx, P * uy + Vy, P * uz + Vz
            norm = math.sqrt(cx_ * cx_ + cy_ * cy_ + cz_ * cz_)
            if norm < p.epsilon:  # the paper's rule at singular points
                if prev is None:
                    raise GuidanceError(f"the field vanishes at the start {[round(x, 2), round(y, 2), round(z, 2)]} "
                                        "and there is no heading to inherit")
                u, inherited = prev, inherited + 1
            else:
                u = (cx_ / norm, cy_ / norm, cz_ / norm)
                prev = u
            x, y, z = x + p.beta * u[0], y + p.beta * u[1], z + p.beta * u[2]
            pts.append((x, y, z))
            if (x - po[0]) * pd[0] + (y - po[1]) * pd[1] + (z - po[2]) * pd[2] >= x_end:
                return np.asarray(pts), True, inherited, tuple(gammas)
        return np.asarray(pts), False, inherited, tuple(gammas)
