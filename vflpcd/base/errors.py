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
        self.file = _one_line(str(file)) if file is not None else "<input>"
        self.field = _one_line(field)
        self.message = _one_line(message)
        super().__init__(f"{self.file}: {self.field}: {self.message}")


_LINE_BREAKS = {ord(c): repr(c)[1:-1] for c in "\n\r\v\f\x1c\x1d\x1e\x85\u2028\u2029"}   # str.splitlines()'s


def _one_line(text: str) -> str:
    """Line breaks (in a file name, in a parser's message) written as escapes."""
    return text.translate(_LINE_BREAKS)


LOG_FORMAT = "%(asctime)s %(levelname)s %(name)s %(message)s"   # one line per event, to stderr


def exit_code_of(prog: str, call) -> int:
    """``call()``'s exit code; bad input (a ``ConfigError``) is one line on stderr naming what was
    wrong, and exit code 2."""
    try:
        return call()
    except ConfigError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2

