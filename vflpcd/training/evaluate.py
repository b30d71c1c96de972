"""Open-loop multi-step prediction error: the protocol every learned dynamics model is compared by.

Protocol of :func:`open_loop_rmse` (exact):

1. Horizons h (s) become steps n_h = round(h / dt); each must be a whole number >= 1 of steps
   (|n_h dt - h| <= 1e-6 s). Let n_max be the largest.
2. Windows: in every log, every start row s = segment start + j * stride whose rows
   s .. s + n_max lie inside one contiguous segment (no dropped rows inside,
   ``Log.window_starts(n_max + 1, stride)``). The same windows serve every horizon.
3. Each window's logged states (n_max + 1, n_x) are moved to the window frame
   (``to_window_frame``: pose relative to the first pose). The model is rolled out open loop
   from the window's first (window-frame) state with the logged controls u_s .. u_{s+n_max-1}:
   ``model.rollout`` (batched), giving predictions x_hat_0 .. x_hat_{n_max}.
4. The error of a window at horizon h is e = x_hat_{n_h} - x_{s+n_h} (window frame) at that
   one step (the end of the horizon, not an average along it). The heading error is the plain
   difference of unwrapped angles (no wrapping).
5. RMSE per horizon and channel: sqrt of the mean of the squared error over all windows of all
   logs (each window weighs the same). "position" combines the position channels
   (X, Y for a ground vehicle; X, Y, Z for a quadrotor): sqrt(mean(|e_pos|^2)), m. Every other
   state channel is reported by its state name (yaw rad, vx m/s, vy m/s, yaw_rate rad/s, ...).
"""

from __future__ import annotations

import logging
from typing import Iterable, Mapping, Sequence

import numpy as np

from vflpcd.core.dynamics.lifted import LiftedLinearModel, PoseLayout, to_window_frame
from vflpcd.training.datasets import Log

log = logging.getLogger("vflpcd.training.evaluate")

HORIZON_TOLERANCE = 1e-6  # s


def horizon_steps(horizons_s: Sequence[float], dt: float) -> list[int]:
    """Steps per horizon; ValueError unless each horizon is a whole number (>= 1) of steps of dt."""
    steps = []
    for h in horizons_s:
        n = int(round(float(h) / dt))
        if n < 1 or abs(n * dt - float(h)) > HORIZON_TOLERANCE:
            raise ValueError(f"horizon {h} s is not a whole number of steps of {dt} s")
        steps.append(n)
    return steps


def error_channels(state_names: Sequence[str]) -> list[tuple[str, list[int]]]:
    """(reported name, state columns) pairs: "position" for the combined position channels (if the
    state has a pose), then every other state channel on its own, in state order."""
    lay = PoseLayout.of(state_names)
    pos = list(lay.position)
    out: list[tuple[str, list[int]]] = [("position", pos)] if pos else []
    out += [(name, [i]) for i, name in enumerate(state_names) if i not in pos]
    return out


def open_loop_rmse(model: LiftedLinearModel, logs: Iterable[Log], horizons_s: Sequence[float] = (0.5, 1.0, 2.0),
                   stride: int = 10) -> dict:
    """Open-loop RMSE of ``model`` on ``logs`` per horizon and channel (module docstring).

    Returns {"horizons_s": [...], "horizon_steps": [...], "stride": int, "n_windows": int,
    "logs": [names], "channels": [names], "rmse": {h: {channel: value}}} with h the given
    horizons as floats. ValueError on mismatched channel names or dt, or no window."""
    logs = list(logs)
    if not logs:
        raise ValueError("no evaluation logs")
    if stride < 1:
        raise ValueError(f"stride must be >= 1, got {stride}")
    names = tuple(model.state_names)
    for lg in logs:
        if lg.state_names != names or lg.control_names != tuple(model.control_names):
            raise ValueError(f"log {lg.name} has channels {lg.state_names}/{lg.control_names}, "
                             f"the model {names}/{tuple(model.control_names)}")
        if abs(lg.dt - model.dt) > 1e-9:
            raise ValueError(f"log {lg.name} has dt {lg.dt} s, the model {model.dt} s")
    steps = horizon_steps(horizons_s, model.dt)
    n_max = max(steps)
    channels = error_channels(names)
    sq = np.zeros((len(steps), len(channels)))
    n_windows = 0
    for lg in logs:
        starts = lg.window_starts(n_max + 1, stride)
        if starts.size == 0:
            continue
        rows = starts[:, None] + np.arange(n_max + 1)[None, :]
        truth = to_window_frame(lg.states[rows], names)                 # (M, n_max + 1, n_x)
        pred = model.rollout_batch(truth[:, 0], lg.controls[rows[:, :-1]])
        for i, n in enumerate(steps):
            e = pred[:, n] - truth[:, n]                                # (M, n_x)
            for j, (_, cols) in enumerate(channels):
                sq[i, j] += float(np.sum(e[:, cols] ** 2))
        n_windows += starts.size
    if n_windows == 0:
        raise ValueError(f"no window of {n_max + 1} rows in the evaluation logs")
    rmse = {float(h): {name: float(np.sqrt(sq[i, j] / n_windows)) for j, (name, _) in enumerate(channels)}
            for i, h in enumerate(horizons_s)}
    log.info("open-loop RMSE over %d windows of %d logs: %s", n_windows, len(logs),
             "; ".join(f"{h:g} s " + ", ".join(f"{k}={v:.3g}" for k, v in r.items()) for h, r in rmse.items()))
    return {"horizons_s": [float(h) for h in horizons_s], "horizon_steps": steps, "stride": int(stride),
            "n_windows": int(n_windows), "logs": [lg.name for lg in logs],
            "channels": [c for c, _ in channels], "rmse": rmse}


def format_table(results: Mapping[str, dict]) -> str:
    """A plain-text table of several ``open_loop_rmse`` results keyed by model name."""
    first = next(iter(results.values()))
    chans = first["channels"]
    head = f"{'model':<10} {'h [s]':>6} " + " ".join(f"{c:>10}" for c in chans)
    lines = [head, "-" * len(head)]
    for name, res in results.items():
        for h, r in res["rmse"].items():
            lines.append(f"{name:<10} {h:>6g} " + " ".join(f"{r[c]:>10.4f}" for c in chans))
    return "\n".join(lines)
