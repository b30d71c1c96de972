"""Offline training of the deep Koopman model (paper section II-B; DDK, Xiao et al. 2023) with torch.

This is the only module of the project that imports torch, and it does so lazily (inside the
functions), so importing it without torch installed works; training then fails with a clear
message. Inference is numpy only (:class:`vflpcd.core.dynamics.koopman.KoopmanModel`).

Data
----
Windows of H + 1 consecutive rows (H = round(horizon_s / dt)) start every ``stride`` rows of
each training log (never across a gap, ``Log.window_starts``), are moved to their first pose's
frame (``to_window_frame``) and normalised per channel, x_n = (x - x_mean) / x_std,
u_n = (u - u_mean) / u_std, with the mean and std of the training windows' rows 0..H-1
(a channel with std < 1e-9 gets std 1). Validation windows come from whole validation logs
(``split_by_log``), never from rows of a training log.

Network and latent dynamics (normalised coordinates)
----------------------------------------------------
Encoder rho_e: MLP n_x -> hidden (tanh) -> ... -> n_e (linear), n_e = n_K - n_x - 1.
Lifted state Z_n(x) = [x_n, rho_e(x_n), 1] (n_K,), the last entry the constant observable of
``lifted.to_physical``. Latent dynamics Z_{k+1} = A_n Z_k + B_n u_n,k, with the constant's
row fixed (A_n last row e_last, B_n last row 0); the trainable parameters are the encoder
weights, A_n[:-1] (n_K - 1, n_K) and B_n[:-1] (n_K - 1, n_u). A_n[:n_x], B_n[:n_x] start from
the least-squares (DMDc) fit of the normalised one-step pairs, A_n[enc, enc] = 0.9 I, the
rest 0 -- so training starts from the DMDc model and improves on it. With ``--schedule s`` (a
state channel) the input matrix depends on it, Z_{k+1} = A_n Z_k + (B_n + s_n,k B_s,n) u_n,k
(``lifted`` module docstring), s_n,k = Z_k[s] the (predicted) normalised channel, B_s,n trainable
from zero: a car's steering gain, which grows with its speed, needs it (``bench dynamics`` prints
the steering response of both).

Loss (exact), for a batch of M windows (x_n,0..H, u_n,0..H-1), Z_hat_0 = Z_n(x_n,0) and
Z_hat_k = A_n Z_hat_{k-1} + B_n u_n,k-1 (k = 1..H, open loop from the first state only):

    L_pred = 1/(M H n_x)  sum_{m,k} |Z_hat_k[:n_x] - x_n,k|^2                  (state prediction)
    L_lin  = 1/(M H n_e)  sum_{m,k} |Z_hat_k[enc] - rho_e(x_n,k)|^2 / v_e      (lifted consistency)
    L      = L_pred + lambda_lin L_lin + lambda_w sum_i |W_i|_F^2

where v_e is the mean (over the encoder outputs) of the batch variance of rho_e(x_n,k)
(detached, + 1e-6), which makes L_lin invariant to the scale of the encoder (otherwise it
could be lowered by shrinking rho_e and enlarging its columns of A_n). DDK's reconstruction
loss |C Upsilon(x) - x|^2 is identically zero here: the decoder is the fixed projection
C = [I_{n_x} 0] because the lifted state starts with x itself (eq. latent_vehicle_dynamics), so
the state reconstruction of the whole predicted trajectory is the L_pred term.
Defaults: lambda_lin = 1e-3, lambda_w = 1e-6 (on the CarSim logs lambda_lin = 0.1 held the
validation L_pred at the DMDc level, 0.05, while 0 and 1e-3 reached 0.013 in 80 epochs: the
consistency term is kept as a light regulariser).

Optimisation: Adam (lr 1e-3, cosine-annealed to lr/20 over the epochs), gradient norm
clipped at 1, float32 on the GPU when ``torch.cuda.is_available()`` else the CPU, each epoch
``windows_per_epoch`` windows drawn without replacement from the training windows. Early
stopping on the validation L_pred (evaluated every epoch on a fixed set of validation
windows): the best epoch's weights are kept, training stops after ``patience`` epochs without
improvement. Seeds: ``torch.manual_seed``, numpy's ``default_rng(seed)`` (window sampling),
``torch.use_deterministic_algorithms(True)``; two runs with the same data, seed and thread count
give identical artifacts.

Export: the float32 weights become float64 arrays, (A_n, B_n) become the physical (A, B) with
``to_physical``; the artifact (``KoopmanModel.save``) and a JSON manifest
``<out stem>.manifest.json`` beside it (exact command line, seed, data fingerprint, wall
time, the ``open_loop_rmse`` tables of the validation logs at 0.5/1/2 s, stride 10, for the
Koopman model and the DMDc and EDMDc baselines fitted to the same training logs).

Command line (``main``): ``train koopman --data PATH_OR_FOLDER... [--carsim] [--schedule STATE] --val NAMES...
--n-lift N --horizon-s H --epochs E --seed S --out FILE``; also ``python -m
vflpcd.training.train_koopman ...``.
"""

from __future__ import annotations

import argparse
import functools
import json
import logging
import math
import os
import platform
import shlex
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np

from vflpcd.config.koopman_file import save_koopman
from vflpcd.core.dynamics.koopman import ACTIVATION, KoopmanModel
from vflpcd.core.dynamics.lifted import LiftedLinearModel, to_physical, to_physical_scheduled, to_window_frame
from vflpcd.base.errors import ConfigError
from vflpcd.training.datasets import Log, fingerprint, load_carsim, load_logs, split_by_log
from vflpcd.training.dmdc import check_logs, robust_std
from vflpcd.training.evaluate import open_loop_rmse

log = logging.getLogger("vflpcd.training.train_koopman")

EVAL_HORIZONS_S = (0.5, 1.0, 2.0)
EVAL_STRIDE = 10
_A_ENC_INIT = 0.9


def _torch():
    try:
        import torch
    except ImportError:  # pragma: no cover - depends on the environment
        raise RuntimeError("torch is not installed; install the training extra: pip install '.[train]' "
                           "(torch==2.13.0)") from None
    return torch


# ---------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class TrainConfig:
    """Training settings. n_lift: n_K, the lifted dimension including the state and the
    constant (n_K - n_x - 1 encoder outputs); horizon_s: prediction horizon of the loss, s;
    stride: rows between training window starts; val_stride: rows between validation window
    starts; hidden: encoder hidden widths; windows_per_epoch: windows drawn per epoch; batch:
    windows per step; lr: Adam learning rate; lambda_lin, lambda_w: loss weights (module
    docstring); patience: epochs without validation improvement before stopping; threads:
    torch CPU threads; schedule: the state channel that scales a second input matrix (B + s B_s,
    ``vflpcd.core.dynamics.lifted``), None for the linear model."""

    n_lift: int
    horizon_s: float = 2.0
    epochs: int = 200
    seed: int = 0
    stride: int = 5
    val_stride: int = 10
    hidden: tuple[int, ...] = (64, 64)
    windows_per_epoch: int = 8192
    batch: int = 256
    lr: float = 1e-3
    lambda_lin: float = 1e-3
    lambda_w: float = 1e-6
    patience: int = 30
    threads: int = 1
    schedule: str | None = None

    def check(self) -> None:
        for name in ("epochs", "stride", "val_stride", "windows_per_epoch", "batch", "patience", "threads"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if not (math.isfinite(self.horizon_s) and self.horizon_s > 0):
            raise ValueError(f"horizon_s must be positive, got {self.horizon_s}")
        if not (self.lr > 0 and self.lambda_lin >= 0 and self.lambda_w >= 0):
            raise ValueError("lr must be > 0 and lambda_lin, lambda_w >= 0")
        if not self.hidden or any(h < 1 for h in self.hidden):
            raise ValueError(f"hidden widths must be >= 1, got {self.hidden}")


@dataclass
class TrainResult:
    """What :func:`train_koopman` returns: the exported numpy model, the torch network (CPU,
    float32, best weights), the normalisation stats and the per-epoch history
    (list of dicts: epoch, train_loss, val_pred, lr)."""

    model: KoopmanModel
    net: object
    stats: dict
    history: list = field(default_factory=list)
    best_epoch: int = 0


# ---------------------------------------------------------------------- data
def make_windows(logs: Sequence[Log], steps: int, stride: int) -> tuple[np.ndarray, np.ndarray]:
    """Window-frame windows: states (M, steps + 1, n_x) and controls (M, steps, n_u), float64."""
    Xs, Us = [], []
    for lg in logs:
        starts = lg.window_starts(steps + 1, stride)
        if starts.size == 0:
            continue
        rows = starts[:, None] + np.arange(steps + 1)[None, :]
        Xs.append(to_window_frame(lg.states[rows], lg.state_names))
        Us.append(lg.controls[rows[:, :-1]])
    if not Xs:
        raise ValueError(f"no window of {steps + 1} rows in the logs")
    return np.concatenate(Xs), np.concatenate(Us)


# ---------------------------------------------------------------------- network
@functools.lru_cache(maxsize=1)
def _net_class():
    torch = _torch()
    nn = torch.nn

    class KoopmanNet(nn.Module):
        """Encoder + latent (A_n, B_n) in normalised coordinates (module docstring)."""

        def __init__(self, n_x: int, n_u: int, n_K: int, hidden: Sequence[int], schedule: int | None) -> None:
            super().__init__()
            n_e = n_K - n_x - 1
            if n_e < 1:
                raise ValueError(f"n_lift = {n_K} leaves no encoder output (need >= n_x + 2 = {n_x + 2})")
            self.n_x, self.n_u, self.n_K, self.n_e = n_x, n_u, n_K, n_e
            layers, d = [], n_x
            for h in hidden:
                layers += [nn.Linear(d, h), nn.Tanh()]
                d = h
            layers.append(nn.Linear(d, n_e))
            self.encoder = nn.Sequential(*layers)
            self.A_top = nn.Parameter(torch.zeros(n_K - 1, n_K))
            self.B_top = nn.Parameter(torch.zeros(n_K - 1, n_u))
            self.schedule = schedule          # column of Z_n whose value scales B_s (None: linear)
            self.B_s_top = nn.Parameter(torch.zeros(n_K - 1, n_u)) if schedule is not None else None

        def linears(self):
            return [m for m in self.encoder if isinstance(m, nn.Linear)]

        def lift(self, x_n):
            """x_n (..., n_x) -> Z_n (..., n_K) = [x_n, rho_e(x_n), 1]."""
            one = torch.ones(x_n.shape[:-1] + (1,), dtype=x_n.dtype, device=x_n.device)
            return torch.cat([x_n, self.encoder(x_n), one], dim=-1)

        def rollout(self, x_n0, u_n):
            """Open loop: x_n0 (M, n_x), u_n (M, H, n_u) -> Z_hat (M, H + 1, n_K)."""
            Z = self.lift(x_n0)
            out = [Z]
            At, Bt = self.A_top.t(), self.B_top.t()
            j = self.schedule
            for k in range(u_n.shape[1]):
                nxt = Z @ At + u_n[:, k] @ Bt
                if j is not None:                   # (B_n + s_n B_s_n) u_n
                    nxt = nxt + Z[:, j:j + 1] * (u_n[:, k] @ self.B_s_top.t())
                Z = torch.cat([nxt, Z[:, -1:]], dim=-1)
                out.append(Z)
            return torch.stack(out, dim=1)

    return KoopmanNet


def build_network(n_x: int, n_u: int, n_lift: int, hidden: Sequence[int] = (64, 64), schedule: int | None = None):
    """A fresh torch network (float32, default PyTorch initialisation of the encoder, zero
    A_n / B_n, and zero B_s_n when ``schedule``, a state column, is given). Seed torch before
    calling for a reproducible initialisation."""
    return _net_class()(n_x, n_u, n_lift, tuple(hidden), schedule)


def export_model(net, stats: dict, state_names: Sequence[str], control_names: Sequence[str], dt: float,
                 metadata: dict | None = None) -> KoopmanModel:
    """The numpy :class:`KoopmanModel` of a torch network: weights as float64 arrays, the
    physical (A, B) from ``to_physical``. stats: x_mean, x_std (n_x,), u_mean, u_std (n_u,)."""
    torch = _torch()
    with torch.no_grad():
        n_K = net.n_K
        A_n = np.zeros((n_K, n_K))
        B_n = np.zeros((n_K, net.n_u))
        A_n[:-1] = net.A_top.detach().cpu().double().numpy()
        A_n[-1, -1] = 1.0
        B_n[:-1] = net.B_top.detach().cpu().double().numpy()
        B_s_n = np.zeros((n_K, net.n_u))
        if net.schedule is not None:
            B_s_n[:-1] = net.B_s_top.detach().cpu().double().numpy()
        Ws = [m.weight.detach().cpu().double().numpy().T.copy() for m in net.linears()]
        bs = [m.bias.detach().cpu().double().numpy().copy() for m in net.linears()]
    scheduled = {}
    if net.schedule is None:
        A, B = to_physical(A_n, B_n, stats["x_mean"], stats["x_std"], stats["u_mean"], stats["u_std"])
    else:
        A, B, B_s = to_physical_scheduled(A_n, B_n, B_s_n, net.schedule, stats["x_mean"], stats["x_std"],
                                          stats["u_mean"], stats["u_std"])
        scheduled = {"B_s": B_s, "schedule": state_names[net.schedule]}
    return KoopmanModel(A, B, enc_weights=Ws, enc_biases=bs, metadata=metadata or {}, state_names=state_names,
                        control_names=control_names, dt=dt, x_mean=stats["x_mean"], x_std=stats["x_std"],
                        u_mean=stats["u_mean"], u_std=stats["u_std"], **scheduled)


def network_rollout(net, stats: dict, x0: np.ndarray, controls: np.ndarray) -> np.ndarray:
    """The torch network's open-loop prediction in physical units, computed in float64 on a
    copy of the network: x0 (M, n_x) window frame, controls (M, H, n_u) -> (M, H + 1, n_x)."""
    torch = _torch()
    import copy

    net64 = copy.deepcopy(net).to("cpu").double()
    xm, xs = (torch.as_tensor(np.asarray(stats[k], dtype=np.float64)) for k in ("x_mean", "x_std"))
    um, us = (torch.as_tensor(np.asarray(stats[k], dtype=np.float64)) for k in ("u_mean", "u_std"))
    with torch.no_grad():
        x_n0 = (torch.as_tensor(np.asarray(x0, dtype=np.float64)) - xm) / xs
        u_n = (torch.as_tensor(np.asarray(controls, dtype=np.float64)) - um) / us
        Z = net64.rollout(x_n0, u_n)
        return (Z[..., : net.n_x] * xs + xm).numpy()


# ---------------------------------------------------------------------- losses
def _losses(torch, net, xw, uw, lambda_lin: float):
    """(L_pred, L_lin) of windows xw (M, H + 1, n_x), uw (M, H, n_u) (normalised)."""
    n_x = net.n_x
    Z = net.rollout(xw[:, 0], uw)[:, 1:]                    # (M, H, n_K)
    l_pred = torch.mean((Z[..., :n_x] - xw[:, 1:]) ** 2)
    if lambda_lin > 0.0:
        enc = net.encoder(xw[:, 1:])                        # (M, H, n_e)
        v = enc.detach().reshape(-1, net.n_e).var(dim=0).mean() + 1e-6
        l_lin = torch.mean((Z[..., n_x:n_x + net.n_e] - enc) ** 2) / v
    else:
        l_lin = torch.zeros((), dtype=xw.dtype, device=xw.device)
    return l_pred, l_lin


def validation_mse(model: LiftedLinearModel, logs: Sequence[Log], horizon_s: float, x_std: np.ndarray,
                   stride: int = EVAL_STRIDE) -> float:
    """The state-prediction loss L_pred of any lifted linear model, in numpy: mean over windows
    (window frame, ``stride`` rows apart), steps 1..H and channels of ((x_hat - x) / x_std)^2."""
    H = int(round(horizon_s / model.dt))
    X, U = make_windows(logs, H, stride)
    pred = model.rollout_batch(X[:, 0], U)
    return float(np.mean(((pred[:, 1:] - X[:, 1:]) / np.asarray(x_std, dtype=np.float64)) ** 2))


def _dmdc_init(X: np.ndarray, U: np.ndarray, n_x: int, n_u: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least squares x_n' = F x_n + c + G u_n on all normalised pairs of the windows."""
    xs = X[:, :-1].reshape(-1, n_x)
    ys = X[:, 1:].reshape(-1, n_x)
    us = U.reshape(-1, n_u)
    R = np.concatenate([xs, np.ones((xs.shape[0], 1)), us], axis=1)
    G = R.T @ R / R.shape[0] + 1e-8 * np.eye(R.shape[1])
    W = np.linalg.solve(G, R.T @ ys / R.shape[0])             # (n_x + 1 + n_u, n_x)
    return W[:n_x].T, W[n_x], W[n_x + 1:].T


# ---------------------------------------------------------------------- training
def train_koopman(train_logs: Sequence[Log], val_logs: Sequence[Log], cfg: TrainConfig, *,
                  progress: bool = False) -> TrainResult:
    """Train the deep Koopman model on ``train_logs``, early-stopped on ``val_logs`` (module
    docstring). Returns a :class:`TrainResult` whose ``model`` carries the metadata
    (fingerprint of the training logs, settings, final losses)."""
    torch = _torch()
    cfg.check()
    state_names, control_names, dt = check_logs(train_logs, "training")
    v_names = check_logs(val_logs, "validation")
    if v_names[:2] != (state_names, control_names) or abs(v_names[2] - dt) > 1e-9:
        raise ValueError("validation logs differ from the training logs in channel names or dt")
    n_x, n_u = len(state_names), len(control_names)
    if cfg.n_lift < n_x + 2:
        raise ValueError(f"n_lift must be at least n_x + 2 = {n_x + 2} (state, one encoder output, constant), "
                         f"got {cfg.n_lift}")
    H = int(round(cfg.horizon_s / dt))
    if H < 1:
        raise ValueError(f"horizon_s = {cfg.horizon_s} s is shorter than one step of {dt} s")

    t0 = time.perf_counter()
    torch.manual_seed(cfg.seed)
    rng = np.random.default_rng(cfg.seed)
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True, warn_only=True)
    torch.set_num_threads(cfg.threads)
    device = torch.device("cuda" if torch.cuda.is_available() else "cpu")

    Xtr, Utr = make_windows(train_logs, H, cfg.stride)
    Xva, Uva = make_windows(val_logs, H, cfg.val_stride)
    stats = {"x_mean": Xtr[:, :-1].reshape(-1, n_x).mean(axis=0), "x_std": robust_std(Xtr[:, :-1].reshape(-1, n_x)),
             "u_mean": Utr.reshape(-1, n_u).mean(axis=0), "u_std": robust_std(Utr.reshape(-1, n_u))}
    Xtr_n = (Xtr - stats["x_mean"]) / stats["x_std"]
    Utr_n = (Utr - stats["u_mean"]) / stats["u_std"]
    Xva_n = (Xva - stats["x_mean"]) / stats["x_std"]
    Uva_n = (Uva - stats["u_mean"]) / stats["u_std"]

    if cfg.schedule is not None and cfg.schedule not in state_names:
        raise ValueError(f"the schedule channel {cfg.schedule!r} is not a state of the logs ({', '.join(state_names)})")
    net = build_network(n_x, n_u, cfg.n_lift, cfg.hidden,
                        state_names.index(cfg.schedule) if cfg.schedule is not None else None)
    F, c, Gm = _dmdc_init(Xtr_n, Utr_n, n_x, n_u)
    with torch.no_grad():
        A0 = np.zeros((cfg.n_lift - 1, cfg.n_lift))
        A0[:n_x, :n_x] = F
        A0[:n_x, -1] = c
        A0[n_x:, n_x:-1] = _A_ENC_INIT * np.eye(cfg.n_lift - n_x - 1)
        B0 = np.zeros((cfg.n_lift - 1, n_u))
        B0[:n_x] = Gm
        net.A_top.copy_(torch.as_tensor(A0, dtype=torch.float32))
        net.B_top.copy_(torch.as_tensor(B0, dtype=torch.float32))
    net.to(device)

    xt = torch.as_tensor(Xtr_n, dtype=torch.float32, device=device)
    ut = torch.as_tensor(Utr_n, dtype=torch.float32, device=device)
    xv = torch.as_tensor(Xva_n, dtype=torch.float32, device=device)
    uv = torch.as_tensor(Uva_n, dtype=torch.float32, device=device)
    opt = torch.optim.Adam(net.parameters(), lr=cfg.lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=cfg.epochs, eta_min=cfg.lr / 20.0)
    weights = [m.weight for m in net.linears()]

    def val_loss() -> tuple[float, float]:
        net.eval()
        with torch.no_grad():
            lp, ll = 0.0, 0.0
            n = xv.shape[0]
            for a in range(0, n, 4096):
                p, q = _losses(torch, net, xv[a:a + 4096], uv[a:a + 4096], cfg.lambda_lin)
                w = min(4096, n - a) / n
                lp += float(p) * w
                ll += float(q) * w
        net.train()
        return lp, ll

    best = val_loss()
    best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
    best_epoch, since = 0, 0
    history = [{"epoch": 0, "train_loss": None, "val_pred": best[0], "val_lin": best[1], "lr": cfg.lr}]
    log.info("event=koopman_train_start windows_train=%d windows_val=%d H=%d n_K=%d n_x=%d n_u=%d device=%s "
             "val_pred_init=%.5g", xt.shape[0], xv.shape[0], H, cfg.n_lift, n_x, n_u, device, best[0])
    n_train = xt.shape[0]
    per_epoch = min(cfg.windows_per_epoch, n_train)
    stopped = "epochs"
    for epoch in range(1, cfg.epochs + 1):
        idx = rng.permutation(n_train)[:per_epoch]
        tot, nb = 0.0, 0
        for a in range(0, per_epoch, cfg.batch):
            b = torch.as_tensor(idx[a:a + cfg.batch], device=device)
            lp, ll = _losses(torch, net, xt[b], ut[b], cfg.lambda_lin)
            loss = lp + cfg.lambda_lin * ll
            if cfg.lambda_w > 0.0:
                loss = loss + cfg.lambda_w * sum(torch.sum(W ** 2) for W in weights)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(net.parameters(), 1.0)
            opt.step()
            tot += float(loss.detach())
            nb += 1
        sched.step()
        vp, vl = val_loss()
        lr_now = opt.param_groups[0]["lr"]
        history.append({"epoch": epoch, "train_loss": tot / nb, "val_pred": vp, "val_lin": vl, "lr": lr_now})
        improved = vp < best[0]
        if improved:
            best, best_epoch, since = (vp, vl), epoch, 0
            best_state = {k: v.detach().clone() for k, v in net.state_dict().items()}
        else:
            since += 1
        if progress:
            print(f"koopman epoch {epoch}/{cfg.epochs} train {tot / nb:.5f} val_pred {vp:.5f} "
                  f"best {best[0]:.5f}@{best_epoch} ({time.perf_counter() - t0:.0f} s)", file=sys.stderr, flush=True)
        if not math.isfinite(tot):
            stopped = "non-finite loss"
            break
        if since >= cfg.patience:
            stopped = "early stopping"
            break
    net.load_state_dict(best_state)
    net.to("cpu")
    net.eval()
    wall = time.perf_counter() - t0
    metadata = {
        "fingerprint": fingerprint(train_logs),
        "train_logs": [lg.name for lg in train_logs],
        "val_logs": [lg.name for lg in val_logs],
        "metrics": {"val_pred_mse": best[0], "val_lin": best[1], "best_epoch": best_epoch,
                    "epochs_run": len(history) - 1, "stopped": stopped,
                    "val_pred_mse_init_dmdc": history[0]["val_pred"]},
        "training": {**{k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(cfg).items()},
                     "horizon_steps": H, "loss": "L_pred + lambda_lin * L_lin + lambda_w * sum |W|^2",
                     "activation": ACTIVATION},
    }
    model = export_model(net, stats, state_names, control_names, dt, metadata)
    log.info("event=koopman_train_done epochs=%d best_epoch=%d val_pred=%.5g stopped=%s wall_s=%.1f",
             len(history) - 1, best_epoch, best[0], stopped.replace(" ", "_"), wall)
    return TrainResult(model=model, net=net, stats=stats, history=history, best_epoch=best_epoch)


# ---------------------------------------------------------------------- evaluation / manifest
def evaluate_models(models: dict, val_logs: Sequence[Log], horizons_s: Sequence[float] = EVAL_HORIZONS_S,
                    stride: int = EVAL_STRIDE) -> dict:
    """{name: open_loop_rmse(...)} for each model on the validation logs (the horizons that fit
    in the logs; a horizon longer than every log is left out)."""
    dt = next(iter(models.values())).dt
    longest = max(lg.n_samples for lg in val_logs)
    hs = [h for h in horizons_s if round(h / dt) + 1 <= longest]
    return {name: open_loop_rmse(m, val_logs, hs, stride=stride) for name, m in models.items()}


def _json_table(res: dict) -> dict:
    return {"horizons_s": res["horizons_s"], "stride": res["stride"], "n_windows": res["n_windows"],
            "logs": res["logs"], "rmse": {f"{h:g}": r for h, r in res["rmse"].items()}}


# ---------------------------------------------------------------------- command line
class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line on stderr, exit code 2
        print(f"{self.prog}: error: {message}", file=sys.stderr)
        raise SystemExit(2)


def _parser() -> _Parser:
    p = _Parser(prog="vflpcd train koopman",
                description="train the deep Koopman model offline (torch) and export a numpy artifact")
    p.add_argument("--data", nargs="+", required=True, help="log files or folders (.npz)")
    p.add_argument("--carsim", action="store_true", help="--data is a CarSim folder of unit_*.npz logs")
    p.add_argument("--val", nargs="+", required=True, metavar="NAME", help="names of the validation logs")
    p.add_argument("--n-lift", type=int, required=True, help="n_K: lifted dimension incl. the state and constant")
    p.add_argument("--horizon-s", type=float, default=2.0, help="prediction horizon of the loss, s (default 2)")
    p.add_argument("--epochs", type=int, default=200, help="maximum epochs (default 200)")
    p.add_argument("--seed", type=int, default=0, help="seed of every random source (default 0)")
    p.add_argument("--out", type=Path, required=True, help="artifact file (.npz); the manifest goes beside it")
    p.add_argument("--hidden", type=int, nargs="+", default=[64, 64], help="encoder hidden widths (default 64 64)")
    p.add_argument("--stride", type=int, default=5, help="rows between training window starts (default 5)")
    p.add_argument("--windows-per-epoch", type=int, default=8192, help="windows drawn per epoch (default 8192)")
    p.add_argument("--batch", type=int, default=256, help="windows per step (default 256)")
    p.add_argument("--lr", type=float, default=1e-3, help="Adam learning rate (default 1e-3)")
    p.add_argument("--lambda-lin", type=float, default=1e-3, help="weight of the lifted consistency loss (default 1e-3)")
    p.add_argument("--patience", type=int, default=30, help="early-stopping patience, epochs (default 30)")
    p.add_argument("--threads", type=int, default=1, help="torch CPU threads (default 1)")
    p.add_argument("--data-command", default=None, help="the command that produced --data (kept in the manifest)")
    p.add_argument("--schedule", default=None, metavar="STATE",
                   help="a state channel that scales a second input matrix, B + s B_s (e.g. vx: a car's steering "
                        "gain grows with its speed); default: the linear model")
    p.add_argument("--no-compare", action="store_true", help="skip the DMDc/EDMDc baselines in the manifest")
    p.add_argument("--quiet", action="store_true", help="no progress line")
    return p


def main(argv: list[str] | None = None) -> int:
    """``[train koopman] --data ... --val ... --n-lift N --out FILE [options]``; the leading
    words ``train koopman`` are optional. Returns 0 when done, 2 on bad arguments, data or a
    missing torch (one line on stderr)."""
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:2] == ["train", "koopman"]:
        argv = argv[2:]
    prog = "vflpcd train koopman"
    try:
        args = _parser().parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)

    def fail(msg: str) -> int:
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2

    if args.out.suffix != ".npz":
        return fail(f"--out must end in .npz, got {args.out}")
    try:
        cfg = TrainConfig(n_lift=args.n_lift, horizon_s=args.horizon_s, epochs=args.epochs, seed=args.seed,
                          stride=args.stride, hidden=tuple(args.hidden), windows_per_epoch=args.windows_per_epoch,
                          batch=args.batch, lr=args.lr, lambda_lin=args.lambda_lin, patience=args.patience,
                          threads=args.threads, schedule=args.schedule)
        cfg.check()
    except ValueError as exc:
        return fail(str(exc))
    try:
        _torch()
    except RuntimeError as exc:
        return fail(str(exc))
    t0 = time.perf_counter()
    try:
        if args.carsim:
            if len(args.data) != 1:
                return fail("--carsim takes one folder")
            logs = load_carsim(args.data[0])
        else:
            logs = load_logs(args.data)
        train, val = split_by_log(logs, args.val)
        if not train:
            return fail("no training logs left after removing the validation logs")
        res = train_koopman(train, val, cfg, progress=not args.quiet)
        models = {"koopman": res.model}
        if not args.no_compare:
            from vflpcd.training.dmdc import fit_dmdc, fit_edmdc

            models["dmdc"] = fit_dmdc(train)
            models["edmdc"] = fit_edmdc(train)
        tables = evaluate_models(models, val)
    except (ConfigError, ValueError) as exc:
        return fail(str(exc))
    # the evaluation goes into the artifact's metadata (deterministic) and the manifest
    res.model.metadata["metrics"]["val_open_loop_rmse"] = _json_table(tables["koopman"])
    save_koopman(res.model, args.out)
    wall = time.perf_counter() - t0
    import torch

    manifest = {
        "artifact": args.out.name,
        "command": "python -m vflpcd.training.train_koopman " + shlex.join(argv),
        "cli_command": "vflpcd train koopman " + shlex.join(argv),
        "data_command": args.data_command,
        "seed": args.seed,
        "data_fingerprint": fingerprint(logs),
        "train_fingerprint": res.model.metadata["fingerprint"],
        "train_logs": [lg.name for lg in train],
        "val_logs": [lg.name for lg in val],
        "n_K": res.model.n_K, "n_x": res.model.n_x, "n_u": res.model.n_u,
        "state_names": list(res.model.state_names), "control_names": list(res.model.control_names),
        "dt": res.model.dt,
        "training": res.model.metadata["training"],
        "metrics": {"training": {k: v for k, v in res.model.metadata["metrics"].items() if k != "val_open_loop_rmse"},
                    "val_open_loop_rmse": {name: _json_table(t) for name, t in tables.items()}},
        "wall_time_s": round(wall, 1),
        "environment": {"python": platform.python_version(), "torch": torch.__version__, "numpy": np.__version__,
                        "device": "cuda" if torch.cuda.is_available() else "cpu"},
    }
    from vflpcd.training.evaluate import format_table

    man_path = args.out.with_suffix(".manifest.json")
    man_path.write_text(json.dumps(manifest, indent=2, sort_keys=False) + "\n")
    print(format_table(tables))
    print(f"wrote {args.out} (n_K={res.model.n_K}) and {man_path} in {wall:.1f} s")
    return 0


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, stream=sys.stderr, format="%(asctime)s %(levelname)s %(name)s %(message)s")
    sys.exit(main())
