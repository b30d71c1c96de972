"""Typed, validated reading of TOML tables with errors that name the file and the field.

Used by every TOML loader (scenarios, plant parameters, missions) so that a bad value is
reported the same way everywhere: ``ConfigError(file, "obstacles[2].radius", "expected ...")``.
"""

from __future__ import annotations

import math
import tomllib
from pathlib import Path
from typing import Any

import numpy as np

from vflpcd.base.errors import ConfigError
from vflpcd.base.inputfile import SYNTAX_FIELD, check_depth, read_text

_MISSING = object()


def load_toml(path: str | Path) -> dict[str, Any]:
    """Parse a TOML file (read by ``vflpcd.base.inputfile``: a regular file of at most
    ``TEXT_MAX_BYTES``); every reading or syntax error becomes a ConfigError."""
    return parse_toml(read_text(path), path)


def parse_toml(text: str, file: str | Path | None) -> dict[str, Any]:
    """Parse TOML text read from ``file``, nested at most ``MAX_DEPTH`` deep; a syntax error
    becomes a ConfigError."""
    check_depth(text, file)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(file, SYNTAX_FIELD, f"not valid TOML ({exc})") from None
    except RecursionError:
        raise ConfigError(file, SYNTAX_FIELD, "not valid TOML (nested too deeply)") from None


def load_table(path: str | Path) -> "Table":
    """The root table of a TOML file (``load_toml``), its errors naming the file."""
    return Table(load_toml(path), path)


class Table:
    """A view of one TOML table that knows its file and its dotted field path."""

    def __init__(self, data: dict[str, Any], file: str | Path | None, prefix: str = "") -> None:
        if not isinstance(data, dict):
            raise ConfigError(file, prefix or "<root>", f"expected a table, got {type(data).__name__}")
        self.data = data
        self.file = file
        self.prefix = prefix

    # ------------------------------------------------------------------ helpers
    def field(self, key: str) -> str:
        return f"{self.prefix}.{key}" if self.prefix else key

    def error(self, key: str, message: str) -> ConfigError:
        return ConfigError(self.file, self.field(key), message)

    def has(self, key: str) -> bool:
        return key in self.data

    def _raw(self, key: str, default: Any) -> Any:
        if key in self.data:
            return self.data[key]
        if default is _MISSING:
            raise self.error(key, "missing required field")
        return default

    def check_known(self, allowed: set[str]) -> None:
        """Reject keys this table does not define (typos must not pass silently)."""
        unknown = sorted(set(self.data) - allowed)
        if unknown:
            raise self.error(unknown[0], f"unknown field (allowed: {', '.join(sorted(allowed))})")

    # ------------------------------------------------------------------ scalars
    def number(self, key: str, default: Any = _MISSING, *, min: float | None = None,
               max: float | None = None, positive: bool = False) -> float:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.error(key, f"expected a number, got {_describe(value)}")
        value = float(value)
        if not math.isfinite(value):
            raise self.error(key, f"expected a finite number, got {value}")
        if positive and value <= 0.0:
            raise self.error(key, f"expected a positive number, got {value:g}")
        if min is not None and value < min:
            raise self.error(key, f"expected a number >= {min:g}, got {value:g}")
        if max is not None and value > max:
            raise self.error(key, f"expected a number <= {max:g}, got {value:g}")
        return value

    def integer(self, key: str, default: Any = _MISSING, *, min: int | None = None) -> int:
        value = self._raw(key, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.error(key, f"expected an integer, got {_describe(value)}")
        if min is not None and value < min:
            raise self.error(key, f"expected an integer >= {min}, got {value}")
        return value

    def string(self, key: str, default: Any = _MISSING, *, choices: tuple[str, ...] | None = None) -> str:
        value = self._raw(key, default)
        if not isinstance(value, str):
            raise self.error(key, f"expected a string, got {_describe(value)}")
        if choices is not None and value not in choices:
            raise self.error(key, f"expected one of {', '.join(choices)}, got {value!r}")
        return value

    def strings(self, key: str, default: Any = _MISSING, *, choices: tuple[str, ...] | None = None) -> tuple[str, ...]:
        """A non-empty list of distinct strings (each one of ``choices`` when given)."""
        value = self._raw(key, default)
        if not isinstance(value, (list, tuple)) or not value or not all(isinstance(v, str) for v in value):
            raise self.error(key, f"expected a non-empty list of strings, got {_describe(value)}")
        if len(set(value)) != len(value):
            raise self.error(key, f"expected distinct names, got {list(value)}")
        bad = [v for v in value if choices is not None and v not in choices]
        if bad:
            raise self.error(key, f"expected names among {', '.join(choices)}, got {bad[0]!r}")
        return tuple(value)

    def boolean(self, key: str, default: Any = _MISSING) -> bool:
        value = self._raw(key, default)
        if not isinstance(value, bool):
            raise self.error(key, f"expected true or false, got {_describe(value)}")
        return value

    def vector(self, key: str, length: int | None = None, default: Any = _MISSING) -> np.ndarray:
        """A list of finite numbers, shape (length,)."""
        value = self._raw(key, default)
        if value is None:
            return None  # type: ignore[return-value]
        if not isinstance(value, list) or any(isinstance(v, bool) or not isinstance(v, (int, float)) for v in value):
            raise self.error(key, f"expected a list of numbers, got {_describe(value)}")
        if length is not None and len(value) != length:
            raise self.error(key, f"expected {length} numbers, got {len(value)}")
        arr = np.asarray(value, dtype=float)
        if not np.all(np.isfinite(arr)):
            raise self.error(key, "expected finite numbers")
        return arr

    def matrix(self, key: str, columns: int, default: Any = _MISSING, *, min_rows: int = 1) -> np.ndarray:
        """A list of rows of finite numbers, shape (rows, columns)."""
        value = self._raw(key, default)
        ok = isinstance(value, list) and all(
            isinstance(row, list) and len(row) == columns
            and all(not isinstance(v, bool) and isinstance(v, (int, float)) for v in row)
            for row in value)
        if not ok:
            raise self.error(key, f"expected a list of [{columns} numbers] rows")
        arr = np.asarray(value, dtype=float).reshape(-1, columns)
        if arr.shape[0] < min_rows:
            raise self.error(key, f"expected at least {min_rows} rows, got {arr.shape[0]}")
        if not np.all(np.isfinite(arr)):
            raise self.error(key, "expected finite numbers")
        return arr

    # ------------------------------------------------------------------ nesting
    def table(self, key: str, default: Any = _MISSING) -> "Table":
        value = self._raw(key, default)
        return Table(value, self.file, self.field(key))

    def tables(self, key: str, default: Any = _MISSING) -> list["Table"]:
        value = self._raw(key, default)
        if not isinstance(value, list):
            raise self.error(key, f"expected an array of tables ([[{key}]]), got {_describe(value)}")
        return [Table(item, self.file, f"{self.field(key)}[{i}]") for i, item in enumerate(value)]


def _describe(value: Any) -> str:
    text = repr(value)
    if len(text) > 40:
        text = text[:37] + "..."
    return f"{type(value).__name__} {text}"
