"""The compiled loops' cache entries change with the files a loop is built from (``loop_cache``): a
callee's change in another file compiles the loop anew, where numba's own stamp (the loop's file
only) would load the old machine code."""

import inspect
import os
import subprocess
import sys
import textwrap

import pytest

import vflpcd
from vflpcd.controllers.loop_cache import cache_named, imported_files, sources_digest
from vflpcd.core.control import horizon_kernel, rate_kernel, tick_kernel


def _names(files):
    return {os.path.relpath(f, os.path.dirname(os.path.dirname(tick_kernel.__file__))) for f in files}


def test_the_files_a_loop_is_built_from_are_its_imports_in_turn():
    lift = _names(imported_files(tick_kernel.__file__))
    assert {"dynamics/encoder_kernel.py", "loop_algebra.py"} <= lift
    horizon = _names(imported_files(horizon_kernel.__file__))
    assert {"control/ebrhrl_kernel.py", "control/tick_kernel.py", "dynamics/encoder_kernel.py",
            "dynamics/gp_kernel.py", "control/barrier.py"} <= horizon      # barrier: Eb-RHRL's PI_MIN, in turn
    assert "control/horizon_kernel.py" not in horizon
    assert imported_files(rate_kernel.__file__) == ()


def test_a_loop_is_named_after_the_digest_of_those_files():
    named = cache_named(tick_kernel.window_lift_loop)
    digest = sources_digest(imported_files(inspect.getsourcefile(tick_kernel.window_lift_loop)))
    assert named.__qualname__ == f"window_lift_loop_{digest}" and named.__code__ is tick_kernel.window_lift_loop.__code__
    assert cache_named(rate_kernel.increment_loop) is rate_kernel.increment_loop        # no project imports


def test_the_digest_follows_the_contents(tmp_path):
    a, b = tmp_path / "a.py", tmp_path / "b.py"
    a.write_text("X = 1\n")
    b.write_text("Y = 2\n")
    first = sources_digest((str(a), str(b)))
    a.write_text("X = 3\n")                 # the same size
    assert sources_digest((str(a), str(b))) != first
    a.write_text("X = 1\n")
    assert sources_digest((str(a), str(b))) == first


RUN = textwrap.dedent("""
    import sys
    from numba import njit
    from numba.extending import register_jitable
    from vflpcd.controllers.loop_cache import cache_named
    import kpkg.callee, kpkg.kernel
    register_jitable(kpkg.callee.f)
    fn = cache_named(kpkg.kernel.k, "kpkg") if sys.argv[1] == "named" else kpkg.kernel.k
    print(njit(cache=True)(fn)(1.0))
""")


@pytest.mark.parametrize("naming", ["named", "numba's own"])
def test_a_callee_changed_in_another_file_is_compiled_in(tmp_path, naming):
    """A loop in one file calls a function of another; after the callee changes (the loop's file
    untouched), a new process runs the new callee with the named cache entry, and the old one with
    numba's own naming: what the naming is for (were numba to check the callees' files one day, the
    second case would fail, and the naming could go)."""
    pytest.importorskip("numba")
    pkg = tmp_path / "kpkg"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "callee.py").write_text("def f(x):\n    return x + 1.0\n")
    (pkg / "kernel.py").write_text("from kpkg.callee import f\n\n\ndef k(x):\n    return f(x)\n")
    root = os.path.dirname(os.path.dirname(vflpcd.__file__))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(tmp_path), root]),
               NUMBA_CACHE_DIR=str(tmp_path / "cache"))
    mode = "named" if naming == "named" else "plain"

    def run() -> float:
        out = subprocess.run([sys.executable, "-c", RUN, mode], env=env, capture_output=True, text=True, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        return float(out.stdout.split()[-1])

    assert run() == 2.0
    (pkg / "callee.py").write_text("def f(x):\n    return x + 2.0\n")
    assert run() == (3.0 if naming == "named" else 2.0)
