"""Core's loops compiled with numba: once per process, and in memory where no cache can be written."""

import logging

import pytest

numba = pytest.importorskip("numba")

from vflpcd.controllers import loops  # noqa: E402


def test_the_loop_is_compiled_once_per_process():
    loops.ebrhrl_loop.cache_clear()
    first = loops.ebrhrl_loop()
    assert first is not None and loops.ebrhrl_loop() is first
    assert first.__name__ == "solve_loop" and hasattr(first, "signatures")      # a numba dispatcher


def test_without_a_writable_cache_it_compiles_in_memory(monkeypatch, caplog):
    real = numba.njit

    def njit(*args, cache=False, **kw):
        if cache:
            raise RuntimeError("cannot cache function 'solve_loop': no locator available")
        return real(*args, cache=cache, **kw)

    monkeypatch.setattr(numba, "njit", njit)
    loops.ebrhrl_loop.cache_clear()
    try:
        with caplog.at_level(logging.WARNING, logger="vflpcd.controllers.loops"):
            loop = loops.ebrhrl_loop()
        assert loop is not None and "event=loop_cache_unavailable" in caplog.text
    finally:
        loops.ebrhrl_loop.cache_clear()
