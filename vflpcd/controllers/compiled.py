"""CasADi functions compiled to C with the system compiler, once per generated source.

``compiled(fn)`` writes ``fn`` out with CasADi's code generator, names the shared library after
the SHA-256 of that source, the compiler and its flags, builds it only when the cache does not
hold it yet, and loads it back as a CasADi ``external``: a second process (another bench run, a
test worker) reuses the library instead of compiling again. The cache is ``$VFLPCD_CACHE_DIR``,
else ``$XDG_CACHE_HOME/vflpcd/casadi``, else ``~/.cache/vflpcd/casadi``; a cache that cannot be
written is replaced by a private temporary folder. The compiler is ``$CC``, else ``gcc``, else
``cc``; with none, or when compiling fails, ``compiled`` returns None (and logs why) and the
caller keeps CasADi's interpreted function.
"""

from __future__ import annotations

import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import casadi as ca

log = logging.getLogger(__name__)

COMPILE_TIMEOUT_S = 900.0


def c_compiler() -> str | None:
    """The C compiler to use, or None when the system has none."""
    cc = os.environ.get("CC")
    if cc:
        return shutil.which(cc)
    return shutil.which("gcc") or shutil.which("cc")


def cache_dir() -> Path:
    """Where compiled libraries are kept (module docstring)."""
    if os.environ.get("VFLPCD_CACHE_DIR"):
        return Path(os.environ["VFLPCD_CACHE_DIR"])
    base = Path(os.environ["XDG_CACHE_HOME"]) if os.environ.get("XDG_CACHE_HOME") else Path.home() / ".cache"
    return base / "vflpcd" / "casadi"


def _writable(folder: Path) -> Path:
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = tempfile.NamedTemporaryFile(dir=folder, delete=True)
        probe.close()
        return folder
    except OSError as exc:
        private = Path(tempfile.mkdtemp(prefix="vflpcd-casadi-"))
        log.warning("event=compile_cache_unwritable path=%s reason=%s using=%s", folder, exc, private)
        return private


def compiled(fn: ca.Function, flags: tuple[str, ...] = ("-O1",)) -> ca.Function | None:
    """``fn`` compiled and loaded (module docstring); None without a compiler or when it fails."""
    cc = c_compiler()
    if cc is None:
        log.info("event=compile_skipped function=%s reason=no C compiler found", fn.name())
        return None
    name = fn.name()
    with tempfile.TemporaryDirectory(prefix="vflpcd-cg-") as tmp:
        gen = ca.CodeGenerator(f"{name}.c", {"with_header": False})
        gen.add(fn)
        gen.generate(tmp + os.sep)
        source = Path(tmp) / f"{name}.c"
        digest = hashlib.sha256(source.read_bytes() + "\0".join((cc, *flags)).encode()).hexdigest()[:20]
        folder = _writable(cache_dir())
        lib = folder / f"{name}-{digest}.so"
        if not lib.exists():
            partial = Path(tmp) / f"{name}.so"
            try:
                subprocess.run([cc, *flags, "-fPIC", "-shared", str(source), "-o", str(partial), "-lm"],
                               check=True, capture_output=True, timeout=COMPILE_TIMEOUT_S)
            except (OSError, subprocess.SubprocessError) as exc:
                detail = getattr(exc, "stderr", b"") or b""
                log.warning("event=compile_failed function=%s compiler=%s reason=%s %s", name, cc,
                            type(exc).__name__, detail.decode(errors="replace").strip()[:200])
                return None
            staged = folder / f".{lib.name}.{os.getpid()}"
            shutil.copyfile(partial, staged)
            os.replace(staged, lib)          # atomic: a concurrent process sees the whole library or none
            log.info("event=compiled function=%s library=%s", name, lib)
    return ca.external(name, str(lib))
