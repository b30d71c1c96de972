"""CasADi functions compiled with the system C compiler and cached by their generated source."""

import logging

import casadi as ca
import numpy as np
import pytest

from vflpcd.controllers import compiled as C

needs_cc = pytest.mark.skipif(C.c_compiler() is None, reason="no C compiler on this machine")


def function(name="f", k=2.0):
    x = ca.SX.sym("x", 3)
    return ca.Function(name, [x], [ca.sin(x) * k, ca.sumsqr(x)])


@needs_cc
def test_a_compiled_function_equals_the_interpreted_one_and_is_built_once(tmp_path, monkeypatch):
    monkeypatch.setenv("VFLPCD_CACHE_DIR", str(tmp_path / "cache"))
    f = function()
    fast = C.compiled(f)
    x = np.array([0.1, -2.0, 3.0])
    for a, b in zip(fast(x), f(x)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0.0, atol=1e-15)
    libs = list((tmp_path / "cache").glob("*.so"))
    assert len(libs) == 1
    stamp = libs[0].stat().st_mtime_ns
    C.compiled(function())                                   # the same source: the cached library
    assert list((tmp_path / "cache").glob("*.so")) == libs and libs[0].stat().st_mtime_ns == stamp
    C.compiled(function(k=3.0))                              # another source: another library
    assert len(list((tmp_path / "cache").glob("*.so"))) == 2


def test_without_a_compiler_or_when_it_fails_there_is_no_compiled_function(tmp_path, monkeypatch, caplog):
    monkeypatch.setenv("VFLPCD_CACHE_DIR", str(tmp_path))
    monkeypatch.setenv("CC", "no-such-compiler-here")
    assert C.c_compiler() is None and C.compiled(function()) is None
    monkeypatch.setenv("CC", "false")                        # a "compiler" that always fails
    with caplog.at_level(logging.WARNING, logger="vflpcd.controllers.compiled"):
        assert C.compiled(function()) is None
    assert "event=compile_failed" in caplog.text and not list(tmp_path.glob("*.so"))


@needs_cc
def test_an_unwritable_cache_is_replaced_by_a_private_folder(tmp_path, monkeypatch, caplog):
    blocked = tmp_path / "file"
    blocked.write_text("not a folder")
    monkeypatch.setenv("VFLPCD_CACHE_DIR", str(blocked / "cache"))
    with caplog.at_level(logging.WARNING, logger="vflpcd.controllers.compiled"):
        fast = C.compiled(function("g"))
    assert fast is not None and "event=compile_cache_unwritable" in caplog.text
    np.testing.assert_allclose(np.asarray(fast(np.ones(3))[1]), 3.0)
