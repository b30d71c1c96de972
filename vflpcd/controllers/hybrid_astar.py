"""Hybrid A* (Dolgov, Thrun, Montemerlo, Diebel 2010) for a forward-only kinematic car.

A planning baseline: it finds a collision-free, kinematically feasible path from a start pose
to a goal pose among static 2-D obstacles. It does not reverse (no Reeds-Shepp words).

Vehicle model and reference point
---------------------------------
Poses passed in and returned are those of the CoG, [x, y, psi] (the scenarios' and the
footprint's reference point). Internally the search runs on the rear-axle pose: with the
kinematic bicycle about the rear axle,

    x_r' = v cos psi,   y_r' = v sin psi,   psi' = v tan(delta) / L,

a primitive of constant steering delta is an exact circular arc of curvature
kappa = tan(delta) / L, so the rear axle is a Dubins car with minimum turning radius
R_min = L / tan(delta_max). The CoG lies lr ahead on the body axis,
[x, y] = [x_r, y_r] + lr [cos psi, sin psi], which is exactly the kinematic bicycle about
the CoG (slip angle beta = atan(lr / L tan delta)); the two descriptions are one model.
Along the CoG path the heading changes at most at dpsi/ds = 1 / sqrt(R_min^2 + lr^2).
The search cost g and the heuristics are rear-axle arc lengths; ``HybridAStarResult.length``
is the CoG path length, sum_i len_i sqrt(1 + (lr kappa_i)^2) over the path's arcs.

The algorithm, with the paper's names
-------------------------------------
* Discretisation: a node is a continuous pose; two nodes are the same search state when they
  fall into the same cell (``xy_resolution`` m, ``heading_bins`` headings); per cell only the
  cheapest node is kept (open list), a cell once expanded is closed.
* Node expansion: ``n_steer`` arcs of length ``step_length`` with steering angles evenly
  spread over [-delta_max, delta_max] (0 included), sampled every <= ``collision_step`` m from
  the exact arc solution. Cost g: arc length times (1 + steer_penalty |delta| +
  steer_change_penalty |delta - delta_parent|), the start's steering taken as 0.
* Heuristics: h = max(h_nonholonomic, h_holonomic) [paper sec. "Heuristics"]:
  - non-holonomic-without-obstacles: the Dubins (forward-only) shortest path length from the
    node to the goal (``dubins_shortest``, the six words LSL, RSR, LSR, RSL, RLR, LRL);
  - holonomic-with-obstacles: a 2-D Dijkstra distance to the goal over an 8-connected grid
    of the free cells, computed once per query (scipy.sparse.csgraph.dijkstra). A cell is
    blocked when its centre is closer to an obstacle than rho + safety_margin - (half cell
    diagonal), rho being the radius of the largest disc about the rear axle inside the
    footprint's cover (the footprint half-width seen from the rear axle): every rear-axle
    position in a blocked cell collides, so no feasible path is cut off. A node whose cell
    cannot reach the goal is dropped. (Not strictly admissible: the 8-connected distance
    between cell centres can exceed the Euclidean one by up to 8 % plus a cell.)
* Analytic expansion: every ``analytic_every`` expansions, and at every expansion whose CoG
  is within ``analytic_radius`` of the goal, the Dubins shot from the node to the goal is
  tried; a collision-free shot ends the search and reaches the goal exactly.
* Goal: a node whose CoG is within ``goal_tolerance`` and whose heading is within
  ``goal_heading_tolerance`` of the goal also ends the search.

Collision check
---------------
The car body is covered by discs on its long axis (``Footprint.rectangle(..., n=n_discs)``:
centres ``offsets``, radius r); when the footprint carries its rectangle ``outline`` the
rectangle is re-covered with ``n_discs`` discs: the scenarios' 3-disc cover reaches 0.30 m
beyond each side of the 1.9 m wide car, which with a 0.3 m margin closes the way through
dense_static (a footprint without an outline is used with its own discs). The cover contains
the rectangle, so the margin also holds for the exact ``Footprint.clearance``. Every sampled
pose's discs are tested against every obstacle's exact ``signed_distance`` at once (discs
that an obstacle's bounding circle and box show to be far are skipped). A pose is free when
every disc keeps sd - r >= safety_margin + slack and the CoG lies inside the bounds (the
bounds limit the search region; the body may reach past them). The
slack, half the largest distance a disc centre moves between two checked poses,
(collision_step / 2) sqrt(1 + (o_max / R_min)^2), makes the margin hold along the continuous
path, not only at the samples (sd is 1-Lipschitz). The start and the goal pose themselves
must keep the plain safety_margin.

Units SI, angles in radians wrapped to (-pi, pi], arrays float64.
"""

from __future__ import annotations

import heapq
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import dijkstra

from vflpcd.core.footprint import Footprint
from vflpcd.core.angles import wrap_angle
from vflpcd.base.paths import config_dir
from vflpcd.base.tomlread import load_table

__all__ = [
    "HybridAStarParams", "HybridAStarResult", "DubinsPath", "dubins_paths", "dubins_shortest",
    "plan_hybrid_astar", "plan_scenario",
]

_TWO_PI = 2.0 * math.pi
DUBINS_WORDS = ("LSL", "RSR", "LSR", "RSL", "RLR", "LRL")
_TURN = {"L": 1.0, "S": 0.0, "R": -1.0}  # sign of the curvature of each letter (L = counter-clockwise)


# =========================================================================== parameters
@dataclass(frozen=True)
class HybridAStarParams:
    """Tunable numbers of the planner, read from ``config/planners/hybrid_astar.toml``."""

    xy_resolution: float          # m
    heading_bins: int             # 1
    step_length: float            # m
    n_steer: int                  # 1, odd
    collision_step: float         # m
    steer_penalty: float          # 1/rad
    steer_change_penalty: float   # 1/rad
    heuristic_weight: float       # 1
    max_expansions: int           # 1
    analytic_every: int           # 1
    analytic_radius: float        # m
    safety_margin: float          # m
    n_discs: int                  # 1
    goal_tolerance: float         # m
    goal_heading_tolerance: float  # rad
    path_step: float              # m
    bounds_padding: float         # m

    @classmethod
    def load(cls, path: str | Path | None = None) -> "HybridAStarParams":
        """Read and validate the parameter file; any bad value raises ConfigError naming the field."""
        path = Path(path) if path is not None else config_dir() / "planners" / "hybrid_astar.toml"
        root = load_table(path)
        root.check_known({"grid", "motion", "cost", "search", "collision", "goal", "output", "scenario"})
        grid, motion, cost = root.table("grid"), root.table("motion"), root.table("cost")
        search, coll, goal = root.table("search"), root.table("collision"), root.table("goal")
        out, scen = root.table("output"), root.table("scenario")
        grid.check_known({"xy_resolution", "heading_bins"})
        motion.check_known({"step_length", "n_steer", "collision_step"})
        cost.check_known({"steer_penalty", "steer_change_penalty", "heuristic_weight"})
        search.check_known({"max_expansions", "analytic_every", "analytic_radius"})
        coll.check_known({"safety_margin", "n_discs"})
        goal.check_known({"goal_tolerance", "goal_heading_tolerance"})
        out.check_known({"path_step"})
        scen.check_known({"bounds_padding"})

        res = grid.number("xy_resolution", positive=True)
        step = motion.number("step_length", positive=True)
        if step <= res * math.sqrt(2.0):
            raise motion.error("step_length", f"expected more than the cell diagonal {res * math.sqrt(2.0):g} m "
                                              f"(a primitive must leave its cell), got {step:g}")
        n_steer = motion.integer("n_steer", min=3)
        if n_steer % 2 == 0:
            raise motion.error("n_steer", f"expected an odd number (so that 0 is one of the angles), got {n_steer}")
        return cls(
            xy_resolution=res, heading_bins=grid.integer("heading_bins", min=8),
            step_length=step, n_steer=n_steer,
            collision_step=motion.number("collision_step", positive=True, max=step),
            steer_penalty=cost.number("steer_penalty", min=0.0),
            steer_change_penalty=cost.number("steer_change_penalty", min=0.0),
            heuristic_weight=cost.number("heuristic_weight", min=1.0),
            max_expansions=search.integer("max_expansions", min=1),
            analytic_every=search.integer("analytic_every", min=1),
            analytic_radius=search.number("analytic_radius", min=0.0),
            safety_margin=coll.number("safety_margin", min=0.0), n_discs=coll.integer("n_discs", min=1),
            goal_tolerance=goal.number("goal_tolerance", positive=True),
            goal_heading_tolerance=goal.number("goal_heading_tolerance", positive=True, max=math.pi),
            path_step=out.number("path_step", positive=True),
            bounds_padding=scen.number("bounds_padding", min=0.0))


@dataclass(frozen=True)
class HybridAStarResult:
    """Outcome of one query.

    success: a path was found; path: (N, 3) CoG poses [x, y, psi] from the start to the goal,
    at most ``path_step`` m of rear-axle travel apart (empty (0, 3) on failure); length: CoG
    path length (m, 0 on failure); expansions: nodes expanded; reason: how the search ended.
    """

    success: bool
    path: np.ndarray
    length: float
    expansions: int
    reason: str


# =========================================================================== arcs
def _arc_poses(x0, y0, th0, kappa, s) -> np.ndarray:
    """Exact poses after driving arc length s on a circle of signed curvature kappa (0: straight).

    All arguments broadcast together (scalars or arrays of one shape S); returns (*S, 3)
    [x, y, theta] with theta unwrapped. The chord has length s sinc(kappa s / 2) and the
    direction th0 + kappa s / 2, which stays exact as kappa -> 0.
    """
    half = 0.5 * np.asarray(kappa, float) * np.asarray(s, float)
    chord = np.asarray(s, float) * np.sinc(half / np.pi)
    mid = np.asarray(th0, float) + half
    x = np.asarray(x0, float) + chord * np.cos(mid)
    y = np.asarray(y0, float) + chord * np.sin(mid)
    th = np.asarray(th0, float) + 2.0 * half
    return np.stack(np.broadcast_arrays(x, y, th), axis=-1)


def _segment_starts(start: np.ndarray, kappas: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """Start pose (m, 3) of each of m consecutive arcs (kappas (m,), lengths (m,)) from start (3,)."""
    starts = np.empty((len(kappas), 3))
    pose = np.asarray(start, float)
    for i, (k, ln) in enumerate(zip(kappas, lengths)):
        starts[i] = pose
        pose = _arc_poses(pose[0], pose[1], pose[2], k, ln)
    return starts


def _sample_segments(starts: np.ndarray, kappas: np.ndarray, lengths: np.ndarray, step: float) -> np.ndarray:
    """Poses (N, 3) along consecutive arcs, at most ``step`` m apart, with every arc's end included.

    starts (m, 3), kappas (m,), lengths (m,); the first row is starts[0]; zero-length arcs add
    nothing. Headings are wrapped to (-pi, pi].
    """
    chunks = [np.asarray(starts[0], float)[None, :]]
    for p0, k, ln in zip(starts, kappas, lengths):
        if ln <= 0.0:
            continue
        n = max(1, math.ceil(ln / step - 1e-9))
        s = ln * np.arange(1, n + 1) / n
        chunks.append(_arc_poses(p0[0], p0[1], p0[2], k, s))
    out = np.concatenate(chunks)
    out[:, 2] = wrap_angle(out[:, 2])
    return out


# =========================================================================== Dubins
@dataclass(frozen=True)
class DubinsPath:
    """A forward-only shortest-path candidate: three arcs (a word of L, S, R) from ``start``.

    start: (3,) [x, y, theta]; radius: turning radius (m); word: e.g. "LSR";
    segment_lengths: (3,) arc lengths (m) of the three letters.
    """

    start: np.ndarray
    radius: float
    word: str
    segment_lengths: np.ndarray

    @property
    def length(self) -> float:
        """Total length (m)."""
        return float(np.sum(self.segment_lengths))

    @property
    def curvatures(self) -> np.ndarray:
        """Signed curvature (3,) of the three letters (1/m): +1/R for L, 0 for S, -1/R for R."""
        return np.array([_TURN[c] / self.radius for c in self.word])

    def segment_starts(self) -> np.ndarray:
        """Start pose (3, 3) of each letter."""
        return _segment_starts(self.start, self.curvatures, self.segment_lengths)

    def end(self) -> np.ndarray:
        """Final pose (3,), heading wrapped."""
        p0 = self.segment_starts()[-1]
        e = _arc_poses(p0[0], p0[1], p0[2], self.curvatures[-1], self.segment_lengths[-1])
        return np.array([e[0], e[1], wrap_angle(e[2])])

    def sample(self, step: float) -> np.ndarray:
        """Poses (N, 3) from start to end, at most ``step`` m apart, letter ends included."""
        return _sample_segments(self.segment_starts(), self.curvatures, self.segment_lengths, step)


def _dubins_words(start, goal, radius: float) -> list[tuple[str, float, float, float]]:
    """Feasible words and their normalised lengths (t, p, q) (arc angles in rad, straight in radii).

    Standard normalisation (Shkel & Lumelsky 2001): rotate so that the goal lies on the +x
    axis at distance d = |goal - start| / R; alpha, beta are the start and goal headings in
    that frame. CSC words follow from the tangent between the two turning circles, CCC words
    from the triangle of three tangent circles.
    """
    dx, dy = goal[0] - start[0], goal[1] - start[1]
    d = math.hypot(dx, dy) / radius
    phi = math.atan2(dy, dx)
    a = (start[2] - phi) % _TWO_PI
    b = (goal[2] - phi) % _TWO_PI
    sa, ca, sb, cb = math.sin(a), math.cos(a), math.sin(b), math.cos(b)
    cab = math.cos(a - b)
    out = []
    # LSL: outer tangent of the two left circles
    p2 = 2.0 + d * d - 2.0 * cab + 2.0 * d * (sa - sb)
    if p2 >= 0.0:
        th = math.atan2(cb - ca, d + sa - sb)
        out.append(("LSL", (th - a) % _TWO_PI, math.sqrt(p2), (b - th) % _TWO_PI))
    # RSR: outer tangent of the two right circles
    p2 = 2.0 + d * d - 2.0 * cab + 2.0 * d * (sb - sa)
    if p2 >= 0.0:
        th = math.atan2(ca - cb, d - sa + sb)
        out.append(("RSR", (a - th) % _TWO_PI, math.sqrt(p2), (th - b) % _TWO_PI))
    # LSR: inner tangent, start left circle to goal right circle
    p2 = -2.0 + d * d + 2.0 * cab + 2.0 * d * (sa + sb)
    if p2 >= 0.0:
        p = math.sqrt(p2)
        th = math.atan2(-ca - cb, d + sa + sb) - math.atan2(-2.0, p)
        out.append(("LSR", (th - a) % _TWO_PI, p, (th - b) % _TWO_PI))
    # RSL: inner tangent, start right circle to goal left circle
    p2 = -2.0 + d * d + 2.0 * cab - 2.0 * d * (sa + sb)
    if p2 >= 0.0:
        p = math.sqrt(p2)
        th = math.atan2(ca + cb, d - sa - sb) - math.atan2(2.0, p)
        out.append(("RSL", (a - th) % _TWO_PI, p, (b - th) % _TWO_PI))
    # RLR: a left circle tangent to both right circles
    c = (6.0 - d * d + 2.0 * cab + 2.0 * d * (sa - sb)) / 8.0
    if abs(c) <= 1.0:
        p = (_TWO_PI - math.acos(c)) % _TWO_PI
        t = (a - math.atan2(ca - cb, d - sa + sb) + 0.5 * p) % _TWO_PI
        out.append(("RLR", t, p, (a - b - t + p) % _TWO_PI))
    # LRL: a right circle tangent to both left circles
    c = (6.0 - d * d + 2.0 * cab + 2.0 * d * (sb - sa)) / 8.0
    if abs(c) <= 1.0:
        p = (_TWO_PI - math.acos(c)) % _TWO_PI
        t = (-a + math.atan2(cb - ca, d + sa - sb) + 0.5 * p) % _TWO_PI
        out.append(("LRL", t, p, (b - a - t + p) % _TWO_PI))
    return out


def _check_pose(q, name: str) -> np.ndarray:
    q = np.asarray(q, dtype=float)
    if q.shape != (3,) or not np.all(np.isfinite(q)):
        raise ValueError(f"{name} must be a finite pose [x, y, psi] of shape (3,), got {q!r}")
    return q


def dubins_paths(start, goal, radius: float) -> list[DubinsPath]:
    """All feasible Dubins words from ``start`` (3,) to ``goal`` (3,) [x, y, theta] at turning radius (m)."""
    start, goal = _check_pose(start, "start"), _check_pose(goal, "goal")
    if not radius > 0.0:
        raise ValueError(f"radius must be positive, got {radius}")
    return [DubinsPath(start=start.copy(), radius=float(radius), word=w, segment_lengths=radius * np.array([t, p, q]))
            for w, t, p, q in _dubins_words(start, goal, radius)]


def dubins_shortest(start, goal, radius: float) -> DubinsPath:
    """The shortest forward-only path from ``start`` (3,) to ``goal`` (3,) [x, y, theta] at turning radius (m).

    Returns a DubinsPath: ``.length`` (m), ``.word`` (e.g. "LSL"), ``.sample(step)`` -> (N, 3).
    """
    return min(dubins_paths(start, goal, radius), key=lambda path: path.length)


def _dubins_length(x0: float, y0: float, th0: float, goal: tuple[float, float, float], radius: float) -> float:
    """Length (m) of the shortest Dubins path (the non-holonomic-without-obstacles heuristic)."""
    words = _dubins_words((x0, y0, th0), goal, radius)
    return radius * min(t + p + q for _, t, p, q in words)


# =========================================================================== the planner
class _Query:
    """Everything fixed during one query: obstacles, footprint in the rear-axle frame, bounds, grid."""

    def __init__(self, obstacles, footprint: Footprint, wheelbase: float, lr: float, delta_max: float,
                 bounds, params: HybridAStarParams) -> None:
        if footprint.dim != 2:
            raise ValueError(f"Hybrid A* plans for a 2-D footprint, got dim = {footprint.dim}")
        if not (wheelbase > 0.0 and 0.0 <= lr <= wheelbase and 0.0 < delta_max < 0.5 * math.pi):
            raise ValueError(f"need wheelbase > 0, 0 <= lr <= wheelbase, 0 < delta_max < pi/2; got "
                             f"wheelbase={wheelbase}, lr={lr}, delta_max={delta_max}")
        self.xmin, self.xmax, self.ymin, self.ymax = (float(b) for b in bounds)
        if not (self.xmin < self.xmax and self.ymin < self.ymax):
            raise ValueError(f"bounds must be (xmin, xmax, ymin, ymax) with xmin < xmax, ymin < ymax, got {bounds}")
        self.p = params
        self.L, self.lr = float(wheelbase), float(lr)
        self.radius_min = self.L / math.tan(delta_max)
        self.obstacles = []  # (shape, center (2,), yaw, bounding radius, body-frame half-extents (2,))
        for shape, center, yaw in obstacles:
            br, ext = getattr(shape, "bounding_radius", None), getattr(shape, "support_extent", None)
            self.obstacles.append((shape, np.asarray(center, float), float(yaw),
                                   float(br()) if br is not None else math.inf,
                                   np.asarray(ext(), float) if ext is not None else np.full(2, math.inf)))
        cover = _disc_cover(footprint, params.n_discs)
        self.offsets = np.asarray(cover.offsets, float) + self.lr  # disc centres ahead of the rear axle
        self.disc_r = float(cover.radius)
        self.steers = np.linspace(-delta_max, delta_max, params.n_steer)
        self.steers[params.n_steer // 2] = 0.0
        self.kappas = np.tan(self.steers) / self.L
        self.n_sub = max(1, math.ceil(params.step_length / params.collision_step - 1e-9))
        self.sub_s = params.step_length * np.arange(1, self.n_sub + 1) / self.n_sub
        o_max = float(np.max(np.abs(self.offsets)))
        slack = 0.5 * params.collision_step * math.sqrt(1.0 + (o_max / self.radius_min) ** 2)
        self.need = self.disc_r + params.safety_margin + slack  # least sd of a disc centre at a sample

    # ------------------------------------------------------------------ frames
    def rear_of(self, cog: np.ndarray) -> np.ndarray:
        """CoG pose (3,) -> rear-axle pose (3,)."""
        return np.array([cog[0] - self.lr * math.cos(cog[2]), cog[1] - self.lr * math.sin(cog[2]), cog[2]])

    def cog_of(self, rear: np.ndarray) -> np.ndarray:
        """Rear-axle poses (..., 3) -> CoG poses (..., 3), headings wrapped."""
        out = np.array(rear, float, copy=True)
        out[..., 0] += self.lr * np.cos(rear[..., 2])
        out[..., 1] += self.lr * np.sin(rear[..., 2])
        out[..., 2] = wrap_angle(rear[..., 2])
        return out

    # ------------------------------------------------------------------ collision check
    def free(self, rear: np.ndarray) -> np.ndarray:
        """Which of B sampled arcs are free. rear: (B, K, 3) rear-axle poses -> (B,) bool.

        Free: the CoG of every pose inside the bounds and every covering disc centre at
        signed distance >= ``self.need`` (radius + safety_margin + slack) from every obstacle.
        """
        need = self.need
        B, K = rear.shape[:2]
        c, s = np.cos(rear[..., 2]), np.sin(rear[..., 2])
        cx, cy = rear[..., 0] + self.lr * c, rear[..., 1] + self.lr * s
        ok = np.all((cx >= self.xmin) & (cx <= self.xmax) & (cy >= self.ymin) & (cy <= self.ymax), axis=1)
        if not self.obstacles or not ok.any():
            return ok
        n = len(self.offsets)
        pts = np.empty((B, K, n, 2))
        pts[..., 0] = rear[..., 0, None] + self.offsets * c[..., None]
        pts[..., 1] = rear[..., 1, None] + self.offsets * s[..., None]
        pts = pts.reshape(-1, 2)
        per_arc = K * n
        lo, hi = pts.min(axis=0), pts.max(axis=0)  # the points' bounding box: skips far obstacles at once
        for shape, center, yaw, br, ext in self.obstacles:
            if math.hypot(*np.maximum(np.maximum(lo - center, center - hi), 0.0)) - br >= need:
                continue
            live = np.repeat(ok, per_arc)
            near = live & (_distance_lower_bound(pts, center, yaw, br, ext) < need)
            idx = np.flatnonzero(near)
            if idx.size == 0:
                continue
            sd = shape.signed_distance(pts[idx], center, yaw)
            ok[idx[sd < need] // per_arc] = False
            if not ok.any():
                break
        return ok

    def pose_clearance(self, cog: np.ndarray) -> tuple[float, int]:
        """Least disc-to-obstacle gap (m) of one CoG pose (3,) and the obstacle's index (-1: none)."""
        rear = self.rear_of(cog)
        pts = rear[None, :2] + self.offsets[:, None] * np.array([math.cos(rear[2]), math.sin(rear[2])])
        best, which = math.inf, -1
        for i, (shape, center, yaw, _, _) in enumerate(self.obstacles):
            gap = float(np.min(shape.signed_distance(pts, center, yaw))) - self.disc_r
            if gap < best:
                best, which = gap, i
        return best, which

    def in_bounds(self, cog: np.ndarray) -> bool:
        return self.xmin <= cog[0] <= self.xmax and self.ymin <= cog[1] <= self.ymax

    # ------------------------------------------------------------------ holonomic-with-obstacles heuristic
    def build_grid(self, goal_rear: np.ndarray) -> None:
        """2-D Dijkstra distance (m) from every cell to the goal's cell over free cells (8-connected)."""
        res = self.p.xy_resolution
        pad = self.lr + res
        self.gx0, self.gy0 = self.xmin - pad, self.ymin - pad
        self.nx = math.ceil((self.xmax + pad - self.gx0) / res)
        self.ny = math.ceil((self.ymax + pad - self.gy0) / res)
        xs = self.gx0 + res * (np.arange(self.nx) + 0.5)
        ys = self.gy0 + res * (np.arange(self.ny) + 0.5)
        centres = np.stack(np.meshgrid(xs, ys, indexing="xy"), axis=-1).reshape(-1, 2)  # row-major (iy, ix)
        # rho: radius of the largest disc about the rear axle (body-axis offset 0) inside the disc cover
        o, r = self.offsets, self.disc_r
        rho = max(0.0, r - float(np.min(np.abs(o))))  # inside the nearest disc
        if len(o) >= 2 and np.allclose(np.diff(o), o[1] - o[0]) and r >= 0.5 * (o[1] - o[0]):
            # evenly spaced discs contain the rectangle [o0 - h, o_n + h] x [-w, w]
            h = 0.5 * float(o[1] - o[0])
            w = math.sqrt(max(r * r - h * h, 0.0))
            rho = max(rho, min(w, -(o[0] - h), o[-1] + h))
        limit = rho + self.p.safety_margin - 0.5 * math.sqrt(2.0) * res
        blocked = np.zeros(len(centres), bool)
        for shape, center, yaw, br, ext in self.obstacles:
            near = _distance_lower_bound(centres, center, yaw, br, ext) < limit
            idx = np.flatnonzero(near)
            if idx.size:
                blocked[idx[shape.signed_distance(centres[idx], center, yaw) < limit]] = True
        free = ~blocked.reshape(self.ny, self.nx)
        ids = np.arange(self.ny * self.nx).reshape(self.ny, self.nx)
        rows, cols, wts = [], [], []
        for di, dj, w in ((0, 1, res), (1, 0, res), (1, 1, res * math.sqrt(2.0)), (1, -1, res * math.sqrt(2.0))):
            a = (slice(0, self.ny - di), slice(max(0, -dj), self.nx + min(0, -dj)))  # cell (iy, ix)
            b = (slice(di, self.ny), slice(max(0, dj), self.nx + min(0, dj)))         # cell (iy + di, ix + dj)
            both = free[a] & free[b]
            rows.append(ids[a][both])
            cols.append(ids[b][both])
            wts.append(np.full(int(both.sum()), w))
        n = self.ny * self.nx
        graph = coo_matrix((np.concatenate(wts), (np.concatenate(rows), np.concatenate(cols))), shape=(n, n)).tocsr()
        gi, gj = self.cell(goal_rear[0], goal_rear[1])
        dist = dijkstra(graph, directed=False, indices=gi * self.nx + gj)
        self.h_grid = dist.reshape(self.ny, self.nx)

    def cell(self, x: float, y: float) -> tuple[int, int]:
        """(iy, ix) of the grid cell holding a rear-axle position."""
        res = self.p.xy_resolution
        return int((y - self.gy0) // res), int((x - self.gx0) // res)

    def h_holonomic(self, x: float, y: float) -> float:
        iy, ix = self.cell(x, y)
        if 0 <= iy < self.ny and 0 <= ix < self.nx:
            return float(self.h_grid[iy, ix])
        return math.inf

    def key(self, x: float, y: float, th: float) -> tuple[int, int, int]:
        """Search cell (ix, iy, i_heading) of a rear-axle pose."""
        iy, ix = self.cell(x, y)
        ih = int((th + math.pi) / _TWO_PI * self.p.heading_bins) % self.p.heading_bins
        return ix, iy, ih


def _distance_lower_bound(pts: np.ndarray, center: np.ndarray, yaw: float, br: float, ext: np.ndarray) -> np.ndarray:
    """Cheap lower bound (M,) on a shape's signed distance at points (M, 2).

    The larger of the signed distances to its bounding circle (radius br) and to its body-frame
    bounding box (half-extents ext (2,)): a shape inside a region has sd >= the region's sd.
    """
    dx, dy = pts[:, 0] - center[0], pts[:, 1] - center[1]
    c, s = math.cos(yaw), math.sin(yaw)
    qx, qy = np.abs(c * dx + s * dy) - ext[0], np.abs(c * dy - s * dx) - ext[1]
    box = np.hypot(np.maximum(qx, 0.0), np.maximum(qy, 0.0)) + np.minimum(np.maximum(qx, qy), 0.0)
    return np.maximum(np.hypot(dx, dy) - br, box)


def _disc_cover(footprint: Footprint, n_discs: int) -> Footprint:
    """The footprint's rectangle covered by n_discs discs, or the footprint itself if it has no outline."""
    outline = getattr(footprint, "outline", None)
    if outline is None or len(outline) == 0:
        return footprint
    lo, hi = np.min(outline, axis=0), np.max(outline, axis=0)
    if abs(lo[1] + hi[1]) > 1e-9 * max(1.0, hi[1]):
        raise ValueError("the footprint's rectangle must be centred on its body axis")
    return Footprint.rectangle(float(hi[0] - lo[0]), float(hi[1] - lo[1]), float(-lo[0]), n=n_discs)


def _fail(reason: str, expansions: int) -> HybridAStarResult:
    return HybridAStarResult(success=False, path=np.empty((0, 3)), length=0.0, expansions=expansions, reason=reason)


def plan_hybrid_astar(start, goal, obstacles: Sequence[tuple[object, np.ndarray, float]], footprint: Footprint,
                      wheelbase: float, lr: float, delta_max: float, bounds: tuple[float, float, float, float],
                      params: HybridAStarParams) -> HybridAStarResult:
    """Plan a forward-only path for the CoG from ``start`` to ``goal``.

    start, goal: (3,) CoG poses [x, y, psi] (m, m, rad); obstacles: (shape, center (2,), yaw)
    with a vectorised ``shape.signed_distance(points (M, 2), center, yaw) -> (M,)``;
    footprint: the car body about the CoG (its rectangle is re-covered with ``params.n_discs``
    discs, see the module notes); wheelbase, lr (CoG to rear axle): m;
    delta_max: front-wheel angle limit (rad); bounds: (xmin, xmax, ymin, ymax) the CoG must
    stay in (m). Returns HybridAStarResult; "no path" is a result with success False, never an
    exception. Raises ValueError when the start or the goal pose is outside the bounds or in
    collision (covering-disc gap below ``params.safety_margin``), naming which.
    """
    start, goal = _check_pose(start, "start"), _check_pose(goal, "goal")
    start = np.array([start[0], start[1], wrap_angle(start[2])])
    goal = np.array([goal[0], goal[1], wrap_angle(goal[2])])
    q = _Query(obstacles, footprint, wheelbase, lr, delta_max, bounds, params)
    for name, pose in (("start", start), ("goal", goal)):
        if not q.in_bounds(pose):
            raise ValueError(f"{name} pose ({pose[0]:.3f}, {pose[1]:.3f}) lies outside the bounds "
                             f"x in [{q.xmin:g}, {q.xmax:g}], y in [{q.ymin:g}, {q.ymax:g}]")
        gap, which = q.pose_clearance(pose)
        if gap < params.safety_margin:
            raise ValueError(f"{name} pose ({pose[0]:.3f}, {pose[1]:.3f}, {pose[2]:.3f}) is in collision with "
                             f"obstacle {which}: clearance {gap:.3f} m < safety_margin {params.safety_margin:g} m")

    start_r, goal_r = q.rear_of(start), q.rear_of(goal)
    goal_t = (float(goal_r[0]), float(goal_r[1]), float(goal_r[2]))
    R = q.radius_min
    q.build_grid(goal_r)

    def heuristic(x: float, y: float, th: float) -> float:
        return max(_dubins_length(x, y, th, goal_t, R), q.h_holonomic(x, y))

    h0 = heuristic(*start_r)
    if not math.isfinite(h0):
        return _fail("no path: the start and the goal are separated in the obstacle-inflated grid "
                     "(holonomic-with-obstacles heuristic is infinite)", 0)

    # node arrays: rear-axle pose, cost-so-far, parent, steering of the arc from the parent
    X, Y, TH, G, PARENT, STEER = [start_r[0]], [start_r[1]], [start_r[2]], [0.0], [-1], [0.0]
    k0 = q.key(*start_r)
    best_g = {k0: 0.0}
    keys = [k0]
    closed: set[tuple[int, int, int]] = set()
    open_list = [(params.heuristic_weight * h0, 0, 0)]
    counter = 1
    expansions = 0
    w = params.heuristic_weight
    ds = params.step_length

    while open_list:
        _, _, i = heapq.heappop(open_list)
        key = keys[i]
        if key in closed or G[i] > best_g[key]:
            continue  # a stale open-list entry
        if expansions >= params.max_expansions:
            return _fail(f"max_expansions ({params.max_expansions}) reached without reaching the goal", expansions)
        closed.add(key)
        expansions += 1
        x, y, th = X[i], Y[i], TH[i]
        cog = q.cog_of(np.array([x, y, th]))

        # goal test (tolerance)
        dist_goal = math.hypot(cog[0] - goal[0], cog[1] - goal[1])
        if dist_goal <= params.goal_tolerance and abs(wrap_angle(cog[2] - goal[2])) <= params.goal_heading_tolerance:
            return _result(q, i, None, X, Y, TH, PARENT, STEER, expansions, "reached the goal region")

        # analytic expansion: the Dubins shot
        if (expansions - 1) % params.analytic_every == 0 or dist_goal <= params.analytic_radius:
            shot = dubins_shortest(np.array([x, y, th]), goal_r, R)
            samples = shot.sample(params.collision_step)
            if q.free(samples[None])[0]:
                return _result(q, i, shot, X, Y, TH, PARENT, STEER, expansions, f"analytic expansion ({shot.word})")

        # node expansion: n_steer arcs of step_length, all sub-poses checked at once
        arcs = _arc_poses(x, y, th, q.kappas[:, None], q.sub_s[None, :])  # (n_steer, n_sub, 3)
        ok = q.free(arcs)
        for j in np.flatnonzero(ok):
            ex, ey, eth = float(arcs[j, -1, 0]), float(arcs[j, -1, 1]), float(wrap_angle(arcs[j, -1, 2]))
            ck = q.key(ex, ey, eth)
            if ck in closed:
                continue
            delta = float(q.steers[j])
            g = G[i] + ds * (1.0 + params.steer_penalty * abs(delta)
                             + params.steer_change_penalty * abs(delta - STEER[i]))
            if g >= best_g.get(ck, math.inf):
                continue
            h = heuristic(ex, ey, eth)
            if not math.isfinite(h):
                continue
            best_g[ck] = g
            for column, value in ((X, ex), (Y, ey), (TH, eth), (G, g), (PARENT, i), (STEER, delta), (keys, ck)):
                column.append(value)
            heapq.heappush(open_list, (g + w * h, counter, len(X) - 1))
            counter += 1

    return _fail("open list exhausted: no collision-free forward path within the bounds", expansions)


def _result(q: _Query, i: int, shot: DubinsPath | None, X, Y, TH, PARENT, STEER,
            expansions: int, reason: str) -> HybridAStarResult:
    """Path from the root to node i (then along ``shot``), sampled and converted to the CoG."""
    chain = []
    while i >= 0:
        chain.append(i)
        i = PARENT[i]
    chain.reverse()
    starts = [np.array([X[a], Y[a], TH[a]]) for a in chain[:-1]]
    kappas = [math.tan(STEER[b]) / q.L for b in chain[1:]]
    lengths = [q.p.step_length] * (len(chain) - 1)
    if shot is not None:
        starts.extend(shot.segment_starts())
        kappas.extend(shot.curvatures)
        lengths.extend(shot.segment_lengths)
    if not starts:  # the start already satisfies the goal tolerance
        starts, kappas, lengths = [np.array([X[chain[0]], Y[chain[0]], TH[chain[0]]])], [0.0], [0.0]
    kappas_a, lengths_a = np.asarray(kappas, float), np.asarray(lengths, float)
    rear = _sample_segments(np.asarray(starts), kappas_a, lengths_a, q.p.path_step)
    length = float(np.sum(lengths_a * np.sqrt(1.0 + (q.lr * kappas_a) ** 2)))
    return HybridAStarResult(success=True, path=q.cog_of(rear), length=length, expansions=expansions, reason=reason)


# =========================================================================== scenario helper
def plan_scenario(scenario, params: HybridAStarParams | None = None) -> HybridAStarResult:
    """The standard query on a ground scenario (``vflpcd.config.scenarios.Scenario`` or its name).

    start = scenario.start[:3]; goal = the scenario's goal with the path's heading there; bounds =
    the path's bounding box grown by ``params.bounds_padding``; obstacles = the scenario's
    obstacles at their initial poses; vehicle = the scenario's bicycle parameter set.
    """
    from vflpcd.config.vehicles import BicycleConfig
    from vflpcd.config.scenarios import load_scenario

    sc = load_scenario(scenario) if isinstance(scenario, (str, Path)) else scenario
    if sc.platform != "ground":
        raise ValueError(f"Hybrid A* plans for ground scenarios, {sc.name!r} is {sc.platform}")
    params = HybridAStarParams.load() if params is None else params
    bike = BicycleConfig.load(sc.params)
    pts, pad = sc.path.points, params.bounds_padding
    bounds = (pts[:, 0].min() - pad, pts[:, 0].max() + pad, pts[:, 1].min() - pad, pts[:, 1].max() + pad)
    end = sc.path.point_at(sc.goal_at)
    goal = np.array([end[0], end[1], float(sc.path.heading_at(sc.goal_at))])
    obstacles = [(o.shape, o.center, o.yaw) for o in sc.obstacles]
    return plan_hybrid_astar(sc.start[:3], goal, obstacles, sc.footprint, bike.params.wheelbase, bike.params.lr,
                             bike.limits.delta_max, bounds, params)


if __name__ == "__main__":  # python -m vflpcd.controllers.hybrid_astar [scenario]
    import sys

    name = sys.argv[1] if len(sys.argv) > 1 else "dense_static"
    t0 = time.perf_counter()
    res = plan_scenario(name)
    dt = time.perf_counter() - t0
    print(f"{name}: success={res.success} length={res.length:.2f} m expansions={res.expansions} "
          f"poses={len(res.path)} time={dt:.3f} s ({res.reason})")
