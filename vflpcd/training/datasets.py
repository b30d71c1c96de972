"""Driving and flight logs for offline model learning: one validated type, loaders, splits.

A :class:`Log` is one continuous recording sampled every ``dt`` seconds: row k holds the
state x_k (``states[k]``, shape (n_x,)) and the control u_k (``controls[k]``, shape (n_u,))
applied from t_k to t_k + dt, so that x_{k+1} = f(x_k, u_k). SI units, float64.

Rows with a non-finite value are dropped when a Log is built; how many is kept in
``dropped_rows`` and the positions where rows are missing in ``breaks`` (row indices of the
kept arrays that do not follow their predecessor in time), so that windows never straddle a
gap (:meth:`Log.window_starts`).

Sources:

* ``load_carsim(folder)``: the CarSim D-Class SUV logs (``unit_NN.npz`` with arrays t, X, Y,
  yaw, vx, vy, yaw_rate, steer, throttle, brake; 50 ms); states [X, Y, yaw, vx, vy,
  yaw_rate], controls [steer, throttle, brake]; yaw kept unwrapped as logged.
* ``save_log`` / ``load_log``: the project's own ``.npz`` format with the arrays ``states``
  (N, n_x), ``controls`` (N, n_u), ``dt`` (), ``state_names`` (n_x,), ``control_names``
  (n_u,), ``name`` () and the optional ``breaks`` (n_breaks,) int64.

Bad input raises :class:`vflpcd.base.errors.ConfigError` naming the file and the field.
"""

from __future__ import annotations

import hashlib
import logging
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Sequence

import numpy as np

from vflpcd.base.npzfile import write_npz

from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import DATA_MAX_BYTES, open_npz

log = logging.getLogger("vflpcd.training.datasets")

CARSIM_STATES = ("X", "Y", "yaw", "vx", "vy", "yaw_rate")
CARSIM_CONTROLS = ("steer", "throttle", "brake")
CARSIM_DT = 0.05          # s, the sampling period of the published logs
DT_TOLERANCE = 1e-6       # s, allowed deviation of a logged time step from dt

_REQUIRED_KEYS = ("states", "controls", "dt", "state_names", "control_names", "name")


@dataclass(frozen=True)
class Log:
    """One continuous log. Fields:

    name: unique identifier (e.g. ``unit_01``); states: (N, n_x) float64; controls: (N, n_u)
    float64; dt: sampling period, s; state_names: (n_x,) str; control_names: (n_u,) str;
    dropped_rows: rows removed for non-finite values (computed; a value passed in is added
    to); breaks: sorted row indices i (0 < i < N) where row i does not follow row i-1 in time.

    The arrays are read-only copies. Construction raises ConfigError (file "<input>") on bad
    shapes, names or dt, and on fewer than two rows left after dropping.
    """

    name: str
    states: np.ndarray
    controls: np.ndarray
    dt: float
    state_names: tuple[str, ...]
    control_names: tuple[str, ...]
    dropped_rows: int = 0
    breaks: tuple[int, ...] = field(default=())

    def __post_init__(self) -> None:
        def bad(fld: str, msg: str) -> ConfigError:
            return ConfigError(None, fld, msg)

        if not isinstance(self.name, str) or not self.name:
            raise bad("name", f"expected a non-empty string, got {self.name!r}")
        snames = tuple(str(s) for s in self.state_names)
        cnames = tuple(str(s) for s in self.control_names)
        for fld, names in (("state_names", snames), ("control_names", cnames)):
            if not names or len(set(names)) != len(names):
                raise bad(fld, f"expected distinct names, got {list(names)}")
        try:
            states = np.array(self.states, dtype=np.float64)
            controls = np.array(self.controls, dtype=np.float64)
            dt = float(self.dt)
        except (TypeError, ValueError) as exc:
            raise bad("states", f"expected numeric arrays ({exc})") from None
        if states.ndim != 2 or states.shape[1] != len(snames):
            raise bad("states", f"expected shape (N, {len(snames)}), got {states.shape}")
        if controls.ndim != 2 or controls.shape[1] != len(cnames):
            raise bad("controls", f"expected shape (N, {len(cnames)}), got {controls.shape}")
        if controls.shape[0] != states.shape[0]:
            raise bad("controls", f"expected {states.shape[0]} rows like states, got {controls.shape[0]}")
        if not (np.isfinite(dt) and dt > 0.0):
            raise bad("dt", f"expected a positive sampling period in s, got {dt!r}")
        n = states.shape[0]
        breaks = sorted({int(b) for b in self.breaks})
        if any(b <= 0 or b >= n for b in breaks):
            raise bad("breaks", f"expected row indices in 1..{n - 1}, got {breaks}")
        # original-time index of every row (a break is a jump of one extra sample; exact size
        # is irrelevant, only that the rows are not consecutive)
        index = np.arange(n) + np.searchsorted(np.asarray(breaks, dtype=np.int64), np.arange(n), side="right")
        keep = np.all(np.isfinite(states), axis=1) & np.all(np.isfinite(controls), axis=1)
        dropped = int(n - keep.sum())
        if dropped:
            log.warning("log %s: dropped %d of %d rows with non-finite values", self.name, dropped, n)
            states, controls, index = states[keep], controls[keep], index[keep]
            breaks = [int(i) for i in np.flatnonzero(np.diff(index) != 1) + 1]
        if states.shape[0] < 2:
            raise bad("states", f"expected at least 2 finite rows, got {states.shape[0]}")
        states.setflags(write=False)
        controls.setflags(write=False)
        object.__setattr__(self, "states", states)
        object.__setattr__(self, "controls", controls)
        object.__setattr__(self, "dt", dt)
        object.__setattr__(self, "state_names", snames)
        object.__setattr__(self, "control_names", cnames)
        object.__setattr__(self, "dropped_rows", int(self.dropped_rows) + dropped)
        object.__setattr__(self, "breaks", tuple(breaks))

    @property
    def n_samples(self) -> int:
        return int(self.states.shape[0])

    @property
    def duration(self) -> float:
        """Recorded time, s: n_samples * dt (each row covers one period)."""
        return self.n_samples * self.dt

    def segments(self) -> list[tuple[int, int]]:
        """Contiguous row ranges [start, stop) between the breaks."""
        edges = [0, *self.breaks, self.n_samples]
        return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]

    def window_starts(self, length: int, stride: int = 1) -> np.ndarray:
        """Start rows s of every window of ``length`` consecutive rows [s, s + length) that lies
        inside one segment, s = segment start + j * stride. Shape (n_windows,), int64."""
        if length < 1 or stride < 1:
            raise ValueError(f"window length and stride must be >= 1, got {length}, {stride}")
        out = [np.arange(a, b - length + 1, stride) for a, b in self.segments() if b - a >= length]
        return np.concatenate(out).astype(np.int64) if out else np.zeros(0, dtype=np.int64)

    def index(self, names: Sequence[str], kind: str = "state") -> list[int]:
        """Column indices of ``names`` among the state (or control) names."""
        pool = self.state_names if kind == "state" else self.control_names
        return [pool.index(n) for n in names]


# ---------------------------------------------------------------------- helpers
def _rebrand(exc: ConfigError, file: Path) -> ConfigError:
    return ConfigError(file, exc.field, exc.message)


def _get(npz, path: Path, key: str) -> np.ndarray:
    if key not in npz.files:
        raise ConfigError(path, key, f"missing required array (have: {', '.join(sorted(npz.files))})")
    try:
        return npz[key]
    except Exception as exc:
        raise ConfigError(path, key, f"unreadable array ({type(exc).__name__})") from None


# ---------------------------------------------------------------------- CarSim
def _carsim_file(path: Path) -> Log:
    with open_npz(path, DATA_MAX_BYTES) as npz:
        cols = {}
        for key in ("t", *CARSIM_STATES, *CARSIM_CONTROLS):
            arr = _get(npz, path, key)
            if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.number):
                raise ConfigError(path, key, f"expected a 1-D numeric array, got shape {arr.shape} dtype {arr.dtype}")
            cols[key] = arr.astype(np.float64)
    n = cols["t"].shape[0]
    for key, arr in cols.items():
        if arr.shape[0] != n:
            raise ConfigError(path, key, f"expected {n} samples like t, got {arr.shape[0]}")
    t = cols["t"]
    states = np.stack([cols[k] for k in CARSIM_STATES], axis=1)
    controls = np.stack([cols[k] for k in CARSIM_CONTROLS], axis=1)
    states[~np.isfinite(t)] = np.nan  # a row without a time stamp is dropped like any other
    keep = np.all(np.isfinite(states), axis=1) & np.all(np.isfinite(controls), axis=1)
    idx = np.flatnonzero(keep)
    if idx.size < 2:
        raise ConfigError(path, "t", f"expected at least 2 finite samples, got {idx.size}")
    steps = np.diff(idx)
    dts = np.diff(t[idx]) / steps
    dt = float((t[idx[-1]] - t[idx[0]]) / (idx[-1] - idx[0]))
    worst = float(np.max(np.abs(dts - dt)))
    if abs(dt - CARSIM_DT) > DT_TOLERANCE or worst > DT_TOLERANCE:
        raise ConfigError(path, "t", f"expected a constant step of {CARSIM_DT} s (tolerance {DT_TOLERANCE} s), "
                          f"got mean {dt:.9g} s, worst deviation {worst:.3g} s")
    try:
        return Log(path.stem, states, controls, round(dt, 9), CARSIM_STATES, CARSIM_CONTROLS)
    except ConfigError as exc:
        raise _rebrand(exc, path) from None


def load_carsim(folder: str | Path) -> list[Log]:
    """Every ``unit_*.npz`` of the CarSim folder, sorted by name, as Logs.

    dt is taken from the t column ((t_last - t_first) / (rows - 1), rounded to 1 ns) and must be
    0.05 s with every step within 1e-6 s. ConfigError for a missing folder, no log files, a
    missing array or a bad shape / time column."""
    folder = Path(folder)
    if not folder.is_dir():
        raise ConfigError(folder, "<folder>", "folder not found")
    files = sorted(folder.glob("unit_*.npz"))
    if not files:
        raise ConfigError(folder, "<folder>", "no unit_*.npz files")
    logs = [_carsim_file(f) for f in files]
    log.info("loaded %d CarSim logs from %s (%d samples)", len(logs), folder, sum(l.n_samples for l in logs))
    return logs


# ---------------------------------------------------------------------- own format
def save_log(log_: Log, path: str | Path) -> Path:
    """Write ``log_`` to ``path`` (a .npz archive, see the module docstring). The bytes depend
    only on the log (fixed zip time stamps), so equal logs give identical files. Returns path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {
        "states": np.ascontiguousarray(log_.states, dtype="<f8"),
        "controls": np.ascontiguousarray(log_.controls, dtype="<f8"),
        "dt": np.array(log_.dt, dtype="<f8"),
        "state_names": np.array(log_.state_names, dtype=str),
        "control_names": np.array(log_.control_names, dtype=str),
        "name": np.array(log_.name, dtype=str),
        "breaks": np.array(log_.breaks, dtype="<i8"),
        "dropped_rows": np.array(log_.dropped_rows, dtype="<i8"),
    }
    write_npz(path, arrays)
    log.info("wrote log %s (%d samples, %.1f s) to %s", log_.name, log_.n_samples, log_.duration, path)
    return path


def _names(npz, path: Path, key: str) -> tuple[str, ...]:
    arr = _get(npz, path, key)
    if arr.ndim != 1 or arr.dtype.kind not in "US":
        raise ConfigError(path, key, f"expected a 1-D array of strings, got shape {arr.shape} dtype {arr.dtype}")
    return tuple(str(s) for s in arr)


def load_log(path: str | Path) -> Log:
    """Read a log written by :func:`save_log`. ConfigError naming the file and the field."""
    path = Path(path)
    with open_npz(path, DATA_MAX_BYTES) as npz:
        for key in _REQUIRED_KEYS:
            if key not in npz.files:
                raise ConfigError(path, key, f"missing required array (have: {', '.join(sorted(npz.files))})")
        states = _get(npz, path, "states")
        controls = _get(npz, path, "controls")
        for key, arr in (("states", states), ("controls", controls)):
            if arr.ndim != 2 or not np.issubdtype(arr.dtype, np.number):
                raise ConfigError(path, key, f"expected a 2-D numeric array, got shape {arr.shape} dtype {arr.dtype}")
        dt = _get(npz, path, "dt")
        if dt.shape != () or not np.issubdtype(dt.dtype, np.number):
            raise ConfigError(path, "dt", f"expected a number, got shape {dt.shape} dtype {dt.dtype}")
        name = _get(npz, path, "name")
        if name.shape != () or name.dtype.kind not in "US":
            raise ConfigError(path, "name", "expected a string")
        state_names = _names(npz, path, "state_names")
        control_names = _names(npz, path, "control_names")
        breaks = _get(npz, path, "breaks") if "breaks" in npz.files else np.zeros(0, dtype=np.int64)
        dropped = int(_get(npz, path, "dropped_rows")) if "dropped_rows" in npz.files else 0
        try:
            return Log(str(name), states, controls, float(dt), state_names, control_names,
                       dropped_rows=dropped, breaks=tuple(int(b) for b in np.ravel(breaks)))
        except ConfigError as exc:
            raise _rebrand(exc, path) from None


def _load_any(path: Path) -> Log:
    with open_npz(path, DATA_MAX_BYTES) as npz:
        own = "states" in npz.files
    return load_log(path) if own else _carsim_file(path)


def load_logs(paths_or_folder: str | Path | Iterable[str | Path]) -> list[Log]:
    """Logs from a folder (every ``*.npz`` in it, sorted by file name) or from a list of files
    and folders. Each file may be in the project's format or a CarSim ``unit_NN.npz``.
    ConfigError on a missing path, an empty selection or two logs with the same name."""
    items = [paths_or_folder] if isinstance(paths_or_folder, (str, Path)) else list(paths_or_folder)
    files: list[Path] = []
    for item in items:
        p = Path(item)
        if p.is_dir():
            found = sorted(p.glob("*.npz"))
            if not found:
                raise ConfigError(p, "<folder>", "no .npz files")
            files.extend(found)
        elif p.is_file():
            files.append(p)
        else:
            raise ConfigError(p, "<file>", "file or folder not found")
    if not files:
        raise ConfigError(None, "<paths>", "no log files given")
    logs: list[Log] = []
    seen: dict[str, Path] = {}
    for f in files:
        lg = _load_any(f)
        if lg.name in seen:
            raise ConfigError(f, "name", f"log name {lg.name!r} already used by {seen[lg.name]}")
        seen[lg.name] = f
        logs.append(lg)
    log.info("loaded %d logs (%d samples)", len(logs), sum(l.n_samples for l in logs))
    return logs


# ---------------------------------------------------------------------- splits, identity
def split_by_log(logs: Sequence[Log], val_names: Iterable[str]) -> tuple[list[Log], list[Log]]:
    """(train, val): whole logs, val those named in ``val_names``, train the rest (order kept).

    ValueError if a name in ``val_names`` is not a log's name, or if two logs share a name
    (one of them could end up on each side)."""
    names = [lg.name for lg in logs]
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ValueError(f"log names must be unique for a split; duplicated: {', '.join(dup)}")
    wanted = set(val_names)
    unknown = sorted(wanted - set(names))
    if unknown:
        raise ValueError(f"unknown validation log(s): {', '.join(unknown)}")
    train = [lg for lg in logs if lg.name not in wanted]
    val = [lg for lg in logs if lg.name in wanted]
    log.info("split %d logs: %d train, %d validation", len(names), len(train), len(val))
    return train, val


def fingerprint(logs: Iterable[Log]) -> str:
    """sha256 hex digest of the logs' names, dt, channel names, breaks and array bytes
    (little-endian float64), taken in name order so that it identifies the set of logs."""
    h = hashlib.sha256()
    for lg in sorted(logs, key=lambda l: l.name):
        h.update(b"log\0" + lg.name.encode() + b"\0")
        h.update(np.array(lg.dt, dtype="<f8").tobytes())
        h.update(("\x1f".join(lg.state_names) + "\0" + "\x1f".join(lg.control_names) + "\0").encode())
        h.update(np.array(lg.breaks, dtype="<i8").tobytes())
        h.update(np.array(lg.states.shape, dtype="<i8").tobytes())
        h.update(np.ascontiguousarray(lg.states, dtype="<f8").tobytes())
        h.update(np.array(lg.controls.shape, dtype="<i8").tobytes())
        h.update(np.ascontiguousarray(lg.controls, dtype="<f8").tobytes())
    return h.hexdigest()
