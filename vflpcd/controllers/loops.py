"""Core's loops compiled with numba (``njit``), for the controllers that run them.

Core stays pure (numpy and scipy only, no files): it writes a loop as plain Python
(``vflpcd.core.control.ebrhrl_kernel.solve_loop``) and takes the compiled function as an
argument. This module compiles it once per process, with numba's on-disk cache (beside the
source, or numba's user-wide cache where that is read-only, or ``$NUMBA_CACHE_DIR``; the systemd
unit sets it), so a later process loads it in milliseconds; with no writable place it compiles in
memory at every start. Without numba ``ebrhrl_loop()`` returns None and the solver runs its numpy path.
"""

from __future__ import annotations

import logging
from functools import lru_cache

log = logging.getLogger(__name__)


@lru_cache(maxsize=1)
def ebrhrl_loop():
    """``solve_loop`` compiled and loaded (``_warm``), or None without numba."""
    try:
        from numba import njit
    except ImportError:
        log.info("event=loop_interpreted loop=ebrhrl reason=numba is not installed (numpy path)")
        return None
    from vflpcd.core.control.ebrhrl_kernel import solve_loop

    try:
        loop = njit(cache=True)(solve_loop)
    except RuntimeError as exc:          # no writable cache location (numba's "no locator available")
        log.warning("event=loop_cache_unavailable loop=ebrhrl reason=%s (compiling in memory; set NUMBA_CACHE_DIR)", exc)
        loop = njit(cache=False)(solve_loop)
    _warm(loop)
    return loop


def _warm(loop) -> None:
    """Compile (or load) the loop now, for the argument types EbRHRL passes, so that a controller's
    first tick does not pay for it (a daemon's first deadline)."""
    import numpy as np

    z = np.zeros
    loop(z((1, 1, 1)), z((1, 1, 1)), z((1, 1)), z(1), z((1, 1, 1)), z((1, 1)), z((1, 1)), z((1, 1)), z((1, 1, 1)),
         1.0, z((1, 1, 1)), z((2, 1, 1)), z(1), z((1, 1)), z(1), z(1, np.int64), z((2, 1)), z((0, 2, 1)),
         z((0, 2, 1)), z(0), 1.0, 1.0, 1, 1e-8, 1e-2)
