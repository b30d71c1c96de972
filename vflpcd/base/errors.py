"""The one error type for bad user input (missions, scenarios, plant files, models, DBC).

Every layer may raise it; the CLI turns it into exit code 2 and a single line.
"""

from __future__ import annotations

import sys

from pathlib import Path


class ConfigError(ValueError):
    """Bad user input, named by file and field.

    ``str(err)`` is one line: ``<file>: <field>: <what was expected>``.
    """

    def __init__(self, file: str | Path | None, field: str, message: str) -> None:
        self.file = str(file) if file is not None else "<input>"
        self.field = field
        self.message = message
        super().__init__(f"{self.file}: {field}: {message}")


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s %(message)s"   # one line per event, to stderr


def exit_code_of(prog: str, call) -> int:
    """``call()``'s exit code; bad input (a ``ConfigError``) is one line on stderr naming what was
    wrong, and exit code 2."""
    try:
        return call()
    except ConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2

