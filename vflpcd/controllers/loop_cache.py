"""Names for the compiled loops' cache entries that change with every project file a loop is built from.

numba's on-disk cache (``njit(cache=True)``) checks the stamp (time and size) of the loop's own source
file only. A loop is compiled together with the functions it calls (``register_jitable``: the tick's
horizon kernel holds the linearisation, the GP's correction, Eb-RHRL's iterations ...) and with the
module constants it reads, which live in other files; after a change to one of those files (a
``git pull`` that leaves the loop's own file as it was) the cache would load the old machine code.
``cache_named`` gives the loop a qualified name that carries a digest of the contents of the project
files its module imports from, transitively, so that such a change compiles a new entry.
"""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import inspect
import types
from functools import lru_cache
from pathlib import Path

PACKAGE = "vflpcd"


@lru_cache(maxsize=None)
def imported_files(path: str, package: str = PACKAGE) -> tuple[str, ...]:
    """The source files of ``package`` that the module at ``path`` imports from (``from vflpcd... import``,
    at any depth of the module), and those they import from, in turn; sorted, ``path`` itself left out."""
    seen: set[str] = set()
    todo = [path]
    while todo:
        tree = ast.parse(Path(todo.pop()).read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module \
                    and node.module.split(".")[0] == package:
                spec = importlib.util.find_spec(node.module)
                origin = spec.origin if spec is not None else None
                if origin and origin != path and origin not in seen:
                    seen.add(origin)
                    todo.append(origin)
    return tuple(sorted(seen))


def sources_digest(files: tuple[str, ...]) -> str:
    """12 hex digits of the SHA-256 of the files' names and contents."""
    h = hashlib.sha256()
    for f in files:
        h.update(Path(f).name.encode() + b"\0" + Path(f).read_bytes() + b"\0")
    return h.hexdigest()[:12]


def cache_named(fn, package: str = PACKAGE):
    """fn itself when its module imports nothing of ``package``'s, else a copy of it (the same code,
    globals and defaults) whose ``__qualname__`` ends in the digest of the files it imports from."""
    files = imported_files(inspect.getsourcefile(fn), package)
    if not files:
        return fn
    named = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__, fn.__defaults__, fn.__closure__)
    named.__qualname__ = f"{fn.__qualname__}_{sources_digest(files)}"
    named.__module__, named.__doc__, named.__kwdefaults__ = fn.__module__, fn.__doc__, fn.__kwdefaults__
    return named
