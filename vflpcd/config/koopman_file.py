"""The deep Koopman model's file: one ``.npz`` archive (``KoopmanModel`` of ``vflpcd.core.dynamics.koopman``).

Arrays (float64 unless noted):

=================  ==================  ==================================================
key                shape               meaning
=================  ==================  ==================================================
A                  (n_K, n_K)          physical latent state matrix (last row e_{n_K})
B                  (n_K, n_u)          physical latent input matrix (last row 0)
B_s                (n_K, n_u)          optional: the input matrix's slope in the schedule channel
                                       (``lifted`` module: U' = A U + (B + s B_s) u; last row 0)
x_mean, x_std      (n_x,)              state normalisation (window frame, SI units)
u_mean, u_std      (n_u,)              control normalisation
enc_W1 .. enc_WL   (d_{i-1}, d_i)      encoder weights (x @ W + b convention)
enc_b1 .. enc_bL   (d_i,)              encoder biases
state_names        (n_x,) str          state channel names, in order
control_names      (n_u,) str          control channel names, in order
dt                 ()                  sampling period, s
metadata           () str              JSON object, below
=================  ==================  ==================================================

``metadata`` (JSON): ``format`` ("vflpcd-koopman/1"), ``activation`` ("tanh"),
``n_K`` (the lift dimension), ``n_x``, ``n_u``, ``n_encoder`` (n_e), ``encoder_layers``
(L), ``hidden`` (list of hidden widths), ``fingerprint`` (sha256 of the training logs,
``vflpcd.training.datasets.fingerprint``), ``metrics`` (training / validation metrics, a JSON
object) and free-form training settings (``training``); ``schedule``, the state channel s that
scales B_s, is there exactly when B_s is.

Every problem found by :func:`load_koopman` raises :class:`vflpcd.base.errors.ConfigError`
naming the file and the key (``metadata.<field>`` for a metadata field).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path
from typing import Sequence

import numpy as np

from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import MODEL_MAX_BYTES, open_npz, parse_json
from vflpcd.base.npzfile import write_npz
from vflpcd.core.dynamics.koopman import ACTIVATION, KoopmanModel

log = logging.getLogger("vflpcd.config.koopman_file")

FORMAT = "vflpcd-koopman/1"
_ARRAY_KEYS = ("A", "B", "x_mean", "x_std", "u_mean", "u_std", "state_names", "control_names", "dt", "metadata")
_META_KEYS = ("format", "activation", "n_K", "n_x", "n_u", "n_encoder", "encoder_layers", "hidden",
              "fingerprint", "metrics")
_CONST_TOL = 1e-9


def koopman_arrays(model: KoopmanModel) -> dict[str, np.ndarray]:
    """The artifact's arrays (module docstring), metadata completed with the sizes."""
    meta = dict(model.metadata)
    meta.update({"format": FORMAT, "activation": ACTIVATION, "n_K": model.n_K, "n_x": model.n_x,
                 "n_u": model.n_u, "n_encoder": model.n_encoder, "encoder_layers": len(model.enc_weights),
                 "hidden": [int(W.shape[1]) for W in model.enc_weights[:-1]]})
    meta.setdefault("fingerprint", "")
    meta.setdefault("metrics", {})
    out = {"A": model.A, "B": model.B, "x_mean": model.x_mean, "x_std": model.x_std,
           "u_mean": model.u_mean, "u_std": model.u_std}
    if model.scheduled:
        out["B_s"] = model.B_s
        meta["schedule"] = model.schedule
    else:
        meta.pop("schedule", None)
    for i, (W, b) in enumerate(zip(model.enc_weights, model.enc_biases), start=1):
        out[f"enc_W{i}"] = W
        out[f"enc_b{i}"] = b
    out = {k: np.ascontiguousarray(v, dtype="<f8") for k, v in out.items()}
    out["state_names"] = np.array(model.state_names, dtype=str)
    out["control_names"] = np.array(model.control_names, dtype=str)
    out["dt"] = np.array(model.dt, dtype="<f8")
    out["metadata"] = np.array(json.dumps(meta, sort_keys=True, allow_nan=False), dtype=str)
    return out



def save_koopman(model: KoopmanModel, path: str | Path) -> Path:
    """Write the model's archive to ``path`` (.npz). The bytes depend only on the model (fixed zip
    time stamps, sorted JSON), so equal models give identical files. Returns path."""
    path = write_npz(path, koopman_arrays(model))
    log.info("event=koopman_saved path=%s n_K=%d n_x=%d n_u=%d", path, model.n_K, model.n_x, model.n_u)
    return path


# ---------------------------------------------------------------------- loading
def _array(npz, path: Path, key: str, shape: tuple | None = None) -> np.ndarray:
    if key not in npz.files:
        raise ConfigError(path, key, f"missing required array (have: {', '.join(sorted(npz.files))})")
    try:
        arr = npz[key]
    except Exception as exc:
        raise ConfigError(path, key, f"unreadable array ({type(exc).__name__})") from None
    if shape is None:
        return arr
    if not np.issubdtype(arr.dtype, np.number) or arr.dtype.kind == "c":
        raise ConfigError(path, key, f"expected a real numeric array, got dtype {arr.dtype}")
    if arr.shape != shape:
        raise ConfigError(path, key, f"expected shape {shape}, got {arr.shape}")
    arr = arr.astype(np.float64)
    if not np.all(np.isfinite(arr)):
        raise ConfigError(path, key, f"expected finite values, found {int(np.sum(~np.isfinite(arr)))} non-finite")
    return arr


def _names(npz, path: Path, key: str) -> tuple[str, ...]:
    arr = _array(npz, path, key)
    if arr.ndim != 1 or arr.dtype.kind not in "US" or arr.size == 0:
        raise ConfigError(path, key, f"expected a non-empty 1-D array of strings, got shape {arr.shape} dtype {arr.dtype}")
    names = tuple(str(s) for s in arr)
    if len(set(names)) != len(names):
        raise ConfigError(path, key, f"expected distinct names, got {list(names)}")
    return names


def _meta_int(meta: dict, path: Path, key: str, minimum: int) -> int:
    v = meta[key]
    if isinstance(v, bool) or not isinstance(v, int) or v < minimum:
        raise ConfigError(path, f"metadata.{key}", f"expected an integer >= {minimum}, got {v!r}")
    return v


def load_koopman(path: str | Path, state_names: Sequence[str] | None = None,
                 control_names: Sequence[str] | None = None) -> KoopmanModel:
    """Read and validate a deep Koopman artifact (module docstring).

    ``state_names`` / ``control_names``: the layout the caller needs (e.g. a mission's); when
    given, the artifact must hold the same names in the same order. Raises ConfigError(file,
    key, message) on a missing file or key, a bad shape, a non-finite value, inconsistent
    sizes, a layout mismatch or a constant row of A / B that is not the constant observable's."""
    path = Path(path)
    with open_npz(path, MODEL_MAX_BYTES) as npz:
        for key in _ARRAY_KEYS:
            if key not in npz.files:
                raise ConfigError(path, key, f"missing required array (have: {', '.join(sorted(npz.files))})")
        raw = _array(npz, path, "metadata")
        if raw.shape != () or raw.dtype.kind not in "US":
            raise ConfigError(path, "metadata", "expected a JSON string")
        meta = parse_json(str(raw), path, "metadata")
        if not isinstance(meta, dict):
            raise ConfigError(path, "metadata", "expected a JSON object")
        for key in _META_KEYS:
            if key not in meta:
                raise ConfigError(path, f"metadata.{key}", "missing required field")
        if meta["format"] != FORMAT:
            raise ConfigError(path, "metadata.format", f"expected {FORMAT!r}, got {meta['format']!r}")
        if meta["activation"] != ACTIVATION:
            raise ConfigError(path, "metadata.activation", f"expected {ACTIVATION!r}, got {meta['activation']!r}")
        if not isinstance(meta["metrics"], dict):
            raise ConfigError(path, "metadata.metrics", "expected a JSON object")
        if not isinstance(meta["fingerprint"], str):
            raise ConfigError(path, "metadata.fingerprint", "expected a string")

        snames = _names(npz, path, "state_names")
        cnames = _names(npz, path, "control_names")
        if state_names is not None and tuple(state_names) != snames:
            raise ConfigError(path, "state_names", f"expected {list(state_names)} (in this order), got {list(snames)}")
        if control_names is not None and tuple(control_names) != cnames:
            raise ConfigError(path, "control_names",
                              f"expected {list(control_names)} (in this order), got {list(cnames)}")
        n_x, n_u = len(snames), len(cnames)
        n_K = _meta_int(meta, path, "n_K", n_x + 2)
        if _meta_int(meta, path, "n_x", 1) != n_x:
            raise ConfigError(path, "metadata.n_x", f"expected {n_x} (the state names), got {meta['n_x']}")
        if _meta_int(meta, path, "n_u", 1) != n_u:
            raise ConfigError(path, "metadata.n_u", f"expected {n_u} (the control names), got {meta['n_u']}")
        n_e = n_K - n_x - 1
        if _meta_int(meta, path, "n_encoder", 1) != n_e:
            raise ConfigError(path, "metadata.n_encoder", f"expected n_K - n_x - 1 = {n_e}, got {meta['n_encoder']}")
        L = _meta_int(meta, path, "encoder_layers", 1)
        hidden = meta["hidden"]
        if (not isinstance(hidden, list) or len(hidden) != L - 1
                or any(isinstance(h, bool) or not isinstance(h, int) or h < 1 for h in hidden)):
            raise ConfigError(path, "metadata.hidden", f"expected {L - 1} positive integer widths, got {hidden!r}")

        A = _array(npz, path, "A", (n_K, n_K))
        B = _array(npz, path, "B", (n_K, n_u))
        e_last = np.zeros(n_K)
        e_last[-1] = 1.0
        if np.max(np.abs(A[-1] - e_last)) > _CONST_TOL:
            raise ConfigError(path, "A", "last row must keep the constant observable (e_last)")
        if np.max(np.abs(B[-1])) > _CONST_TOL:
            raise ConfigError(path, "B", "last row must be zero (the constant observable)")
        schedule = meta.get("schedule")
        if ("B_s" in npz.files) != (schedule is not None):
            raise ConfigError(path, "B_s", "a scheduled input matrix needs both the array B_s and metadata.schedule")
        scheduled = {}
        if schedule is not None:
            if schedule not in snames:
                raise ConfigError(path, "metadata.schedule", f"expected one of the state names {list(snames)}, "
                                  f"got {schedule!r}")
            B_s = _array(npz, path, "B_s", (n_K, n_u))
            if np.max(np.abs(B_s[-1])) > _CONST_TOL:
                raise ConfigError(path, "B_s", "last row must be zero (the constant observable)")
            scheduled = {"B_s": B_s, "schedule": schedule}
        stats = {k: _array(npz, path, k, (n,)) for k, n in
                 (("x_mean", n_x), ("x_std", n_x), ("u_mean", n_u), ("u_std", n_u))}
        for k in ("x_std", "u_std"):
            if np.any(stats[k] <= 0.0):
                raise ConfigError(path, k, "expected positive standard deviations")
        dims = [n_x, *hidden, n_e]
        Ws, bs = [], []
        for i in range(1, L + 1):
            Ws.append(_array(npz, path, f"enc_W{i}", (dims[i - 1], dims[i])))
            bs.append(_array(npz, path, f"enc_b{i}", (dims[i],)))
        if f"enc_W{L + 1}" in npz.files:
            raise ConfigError(path, f"enc_W{L + 1}", f"unexpected encoder layer (metadata.encoder_layers = {L})")
        dt = _array(npz, path, "dt", ())
        if not float(dt) > 0.0:
            raise ConfigError(path, "dt", f"expected a positive sampling period in s, got {float(dt)}")
    model = KoopmanModel(A, B, enc_weights=Ws, enc_biases=bs, metadata=meta, state_names=snames,
                         control_names=cnames, dt=float(dt), **stats, **scheduled)
    log.info("event=koopman_loaded path=%s n_K=%d n_x=%d n_u=%d fingerprint=%s", path, n_K, n_x, n_u,
             meta["fingerprint"][:12])
    return model
