"""PNG of a closed-loop run: map with obstacles and trajectory, speed, errors, commands, clearance."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from sim.runner import RunRecord
from vflpcd.config.scenarios import Scenario
from vflpcd.core.angles import wrap_angle
from vflpcd.core.shapes import top_view




def save_png(fig, out: str | Path, dpi: int) -> Path:
    """Write the matplotlib figure to ``out`` (its folder made if missing), close it, return the path."""
    import matplotlib.pyplot as plt

    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=dpi)
    plt.close(fig)
    return out


def plot_run(record: RunRecord, scenario: Scenario, out: str | Path) -> Path:
    """Write the run's figure to ``out`` (PNG) and return its path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    fig = plt.figure(figsize=(13, 11), constrained_layout=True)
    grid = fig.add_gridspec(3, 2, height_ratios=[1.6, 1, 1])
    ax_map = fig.add_subplot(grid[0, :])
    _draw_map(ax_map, record, scenario)

    t = record.t
    ax = fig.add_subplot(grid[1, 0])
    speed = np.linalg.norm(record.velocity, axis=1)
    ax.plot(t, speed, label="speed")
    ax.axhline(scenario.v_desired, color="k", ls="--", lw=0.8, label="$v_d$")
    ax.set(xlabel="t (s)", ylabel="speed (m/s)", title="Speed")
    ax.legend(loc="lower right")

    ax = fig.add_subplot(grid[1, 1])
    ax.plot(t, record.lateral, label="lateral error (m)")
    ax.plot(t, wrap_angle(record.psi - record.ref_heading), label="heading error (rad)")
    ax.set(xlabel="t (s)", title="Tracking errors against the reference path")
    ax.legend(loc="upper right")

    ax = fig.add_subplot(grid[2, 0])
    for j, name in enumerate(record.control_names):
        ax.plot(t, record.applied[:, j], label=f"{name} (applied)")
    ax.set(xlabel="t (s)", title="Commands after actuator limits")
    ax.legend(loc="upper right")

    ax = fig.add_subplot(grid[2, 1])
    for j, o in enumerate(scenario.obstacles):
        ax.plot(t, record.clearance[:, j], label=o.id)
    ax.axhline(0.0, color="r", lw=1.0)
    finite = record.clearance[np.isfinite(record.clearance)]
    if finite.size:
        ax.set_ylim(min(-0.5, finite.min() - 0.2), min(15.0, finite.max() + 0.5))
    ax.set(xlabel="t (s)", ylabel="m", title="Clearance of the body to each obstacle (< 0: collision)")
    if scenario.obstacles:
        ax.legend(loc="upper right", fontsize=7, ncol=2)

    m = record.metrics
    fig.suptitle(f"{scenario.name} / {record.controller} (seed {record.seed}): {record.outcome}, "
                 f"J_MC {m['J_MC']:.3f}, L_p {m['L_p']:.1f} m, collisions {m['collisions']}")
    return save_png(fig, out, 110)


def _draw_map(ax, record: RunRecord, scenario: Scenario) -> None:
    path = scenario.path.points
    ax.plot(path[:, 0], path[:, 1], color="k", lw=0.8, label="reference path")
    if not scenario.path.closed:
        goal = scenario.path.point_at(scenario.goal_at)
        ax.plot(goal[0], goal[1], marker="|", ms=14, mew=2, color="k", ls="none",
                label="goal" if scenario.stop_at_goal else "goal (the road goes on)")
    n_frames = 6
    frames = np.linspace(0, len(record.t) - 1, n_frames).astype(int)
    for j, o in enumerate(scenario.obstacles):
        shape2d = top_view(o.shape)
        centers = record.obstacle_center[:, j, :2]
        present = np.isfinite(record.clearance[:, j])
        moves = np.ptp(centers[present], axis=0).max() > 1e-6 if present.any() else False
        if moves:  # positions at several instants, darkest first (paper's convention)
            for n, k in enumerate(frames[present[frames]]):
                xy = shape2d.outline(centers[k], o.yaw)
                ax.fill(xy[:, 0], xy[:, 1], color=str(0.25 + 0.6 * n / n_frames), alpha=0.7, lw=0)
            first = np.argmax(present)
            ax.annotate("", xy=centers[-1], xytext=centers[first],
                        arrowprops=dict(arrowstyle="->", color="k", lw=1.2))
        elif present.any():
            k = int(np.argmax(present))
            xy = shape2d.outline(centers[k], o.yaw)
            ax.fill(xy[:, 0], xy[:, 1], color="0.45", alpha=0.8, lw=0)
        if not present.any():  # never appeared: outline only
            xy = shape2d.outline(centers[0], o.yaw)
            ax.plot(xy[:, 0], xy[:, 1], color="0.6", ls=":", lw=1)
        r = float(np.max(shape2d.support_extent()))
        ax.annotate(o.id, centers[0] + [0.0, r], fontsize=7, ha="center", va="bottom", color="0.2")
    pos = record.position
    speed = np.linalg.norm(record.velocity, axis=1)
    sc = ax.scatter(pos[:, 0], pos[:, 1], c=speed, s=3, cmap="viridis", label="trajectory")
    plt_colorbar(ax, sc)
    hit = np.any(np.nan_to_num(record.clearance, nan=1.0) < 0.0, axis=1)
    if hit.any():
        ax.plot(pos[hit, 0], pos[hit, 1], "rx", ms=4, label="in collision")
    ax.annotate("SP", pos[0, :2], fontsize=9, weight="bold")
    ax.annotate("EP", pos[-1, :2], fontsize=9, weight="bold")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set(xlabel="X (m)", ylabel="Y (m)",
           title="Trajectory (colour: speed, m/s); obstacles: physical boundary" +
                 (" (top view)" if scenario.dim == 3 else ""))
    ax.legend(loc="best", fontsize=8)


def plt_colorbar(ax, mappable) -> None:
    ax.figure.colorbar(mappable, ax=ax, shrink=0.8, pad=0.01)
