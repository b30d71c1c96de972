"""Guidance for the quadrotor: the 3-D composite field integrated by eq. (xi_r) and speed-planned.

Each step evaluates the field at the point (a 3-D grid of the whole corridor would hold
millions of cells); the rest follows the planar planner: the side rule (pass on the side -
left, right, above or below - that leaves the path least), the direction fixed at first entry
(flipped if it would circle backwards), the paper's near-zero rule, Gaussian smoothing and speed
planning. Virtual obstacles are a
planar construction and are not used in 3-D; the centripetal limit is met by speed planning.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Sequence

import numpy as np

from vflpcd.core.guidance.field3d import GraphPath3D, GuidanceField3D, Obstacle3D
from vflpcd.core.guidance.grid import BACKWARDS
from vflpcd.core.guidance.integrate3d_kernel import REACHED, VANISHED, steps3d_loop
from vflpcd.core.guidance.implicit import GuidanceError, ObstacleImplicit, graph_horizon
from vflpcd.core.guidance.planner import MOVER_PASSES, GuidancePlan, PlannerBase
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
        """Eq. (xi_r) with the field evaluated at each point (``integrate3d_kernel.steps3d_loop``,
        compiled where the planner's loops are): (points (K, 3), reached, inherited, gammas)."""
        p = self.params
        obstacles = field.statics + field.movers
        rows = np.array([ob.implicit.row3d() + [ob.gamma, *np.asarray(ob.normal, float).tolist()] for ob in obstacles],
                        dtype=float).reshape(-1, 20)
        gammas = np.zeros(len(obstacles))
        path = field.path
        frame = np.concatenate([path.origin, path.R.ravel()])
        params = np.array([field.k_p, field.k_r, field.l1, field.l2, p.epsilon, p.beta, x_end, max_steps, t0, speed,
                           path.x0, path.x1, BACKWARDS])
        xyz, out = np.empty((max_steps + 1, 3)), np.zeros(2, dtype=np.int64)
        loop = self._loops().steps3d or steps3d_loop
        times = np.zeros(0) if step_times is None else np.ascontiguousarray(step_times, dtype=float)
        code = loop(np.ascontiguousarray(start, dtype=float), xyz, rows, gammas, frame, path.knots, path.pieces,
                    params, times, out)
        if code == VANISHED:
            raise GuidanceError(f"the field vanishes at the start {np.round(start, 2).tolist()} "
                                "and there is no heading to inherit")
        return (xyz[:out[0]].copy(), code == REACHED, int(out[1]),
                tuple(None if g == 0.0 else float(g) for g in gammas))
