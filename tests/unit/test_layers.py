"""The import rules of the layers, checked on every module's syntax tree (function-local imports too).

- core (``vflpcd.core``): numpy, scipy, itself and pure standard-library modules only (no files,
  clocks, threads, sockets or TOML);
- the production path (``vflpcd`` outside ``training``, and ``drivers``): never ``sim``;
- ``sim``: never the app (``vflpcd.app``);
- torch: only in ``vflpcd.training``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("vflpcd", "drivers", "sim")

CORE_STDLIB = {"__future__", "abc", "bisect", "collections", "dataclasses", "enum", "functools", "heapq",
               "itertools", "logging", "math", "numbers", "operator", "typing", "warnings"}


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def imports(source: str, module: str, is_package: bool = False) -> list[tuple[int, str]]:
    """(line, imported module) of every import in source, relative ones resolved against module."""
    out = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = module.split(".")[: len(module.split(".")) - node.level + (1 if is_package else 0)]
                name = ".".join(base + ([node.module] if node.module else []))
            else:
                name = node.module or ""
            out.append((node.lineno, name))
    return out


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def violations(module: str, imported: str) -> str | None:
    """Why ``module`` may not import ``imported`` (None when it may)."""
    top = imported.split(".")[0]
    if top == "torch" and not _under(module, "vflpcd.training"):
        return "torch outside vflpcd.training"
    if _under(module, "vflpcd.core"):
        if top in ("numpy", "scipy") or _under(imported, "vflpcd.core") or top in CORE_STDLIB:
            return None
        return "core imports only numpy, scipy, pure standard-library modules and itself"
    if (_under(module, "vflpcd") and not _under(module, "vflpcd.training") or _under(module, "drivers")) \
            and top == "sim":
        return "the production path (vflpcd, drivers) never imports sim"
    if _under(module, "sim") and _under(imported, "vflpcd.app"):
        return "sim never imports the app (vflpcd.app)"
    return None


def check(path: Path) -> list[str]:
    module = module_name(path)
    return [f"{path.relative_to(ROOT)}:{line}: {module} imports {name}: {why}"
            for line, name in imports(path.read_text(), module, path.name == "__init__.py")
            if (why := violations(module, name))]


def test_every_module_keeps_the_import_rules():
    files = [p for pkg in PACKAGES for p in sorted((ROOT / pkg).rglob("*.py"))]
    assert len(files) > 100
    found = [v for p in files for v in check(p)]
    assert not found, "\n".join(found)


@pytest.mark.parametrize("module, source, rule", [
    ("vflpcd.core.vflpc", "def f():\n    from sim.plants import make_plant\n", "core imports only"),
    ("vflpcd.core.path", "import tomllib\n", "core imports only"),
    ("vflpcd.core.dynamics.koopman", "from ...base import paths\n", "core imports only"),
    ("vflpcd.daemon.service", "def f():\n    import sim.runner\n", "never imports sim"),
    ("drivers.can_vehicle", "from sim.plants.dynamic_bicycle import DynamicBicycle\n", "never imports sim"),
    ("sim.sitl.can_ecu", "from vflpcd.app.mission import load_mission\n", "never imports the app"),
    ("vflpcd.controllers.nmpc_cbf", "import torch\n", "torch outside"),
])
def test_a_forbidden_import_is_found(module, source, rule):
    found = [why for _, name in imports(source, module) if (why := violations(module, name))]
    assert found and rule in found[0]


@pytest.mark.parametrize("module, source", [
    ("vflpcd.core.vflpc", "import numpy as np\nfrom scipy import linalg\nfrom .guidance import planner\n"),
    ("vflpcd.training.train_koopman", "import torch\n"),
    ("sim.runner", "from vflpcd.core.safety.guard import SafetyGuard\n"),
])
def test_an_allowed_import_passes(module, source):
    assert not [why for _, name in imports(source, module) if (why := violations(module, name))]
