"""Child processes that die with the daemon.

Both ways take the parent's pid as read in the parent before the child starts, so that a parent
that died before the child got this far is seen too: the child has then been re-parented and its
``getppid()`` differs, and it is killed at once.

- ``watch(parent_pid)`` (POSIX), from inside the child: a daemon thread that SIGKILLs its own
  process within ``WATCH_PERIOD_S`` of ``getppid()`` changing. It follows the parent *process*,
  whichever of the parent's threads started the child (the daemon's process workers).
- ``preexec(parent_pid)`` (Linux): a ``preexec_fn`` for ``subprocess.Popen`` that sets
  ``PR_SET_PDEATHSIG`` to SIGKILL; it lasts across ``exec``, so it also covers programs that
  cannot watch for themselves. The kernel's "parent" is the *thread* that started the child: the
  child is killed when that thread ends, so start such children from a thread that lives as long
  as the process (the main thread). Elsewhere than Linux it does nothing.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import signal
import sys
import threading
import time

log = logging.getLogger("vflpcd.daemon.lifeline")

WATCH_PERIOD_S = 0.05     # how often the watch thread reads getppid(): the bound on dying late
PR_SET_PDEATHSIG = 1      # <linux/prctl.h>


def _die() -> None:
    os.kill(os.getpid(), signal.SIGKILL)


def watch(parent_pid: int, period_s: float = WATCH_PERIOD_S) -> threading.Thread:
    """Kill this process when its parent ``parent_pid`` is gone (now, or later: a daemon thread)."""
    if os.getppid() != parent_pid:
        _die()

    def run() -> None:
        while os.getppid() == parent_pid:
            time.sleep(period_s)
        try:
            log.error("event=parent_lost pid=%d parent=%d action=exit", os.getpid(), parent_pid)
        finally:
            _die()

    thread = threading.Thread(target=run, name="lifeline", daemon=True)
    thread.start()
    return thread


@functools.cache
def _prctl():
    return ctypes.CDLL(None, use_errno=True).prctl


def arm(parent_pid: int) -> bool:
    """Linux: have the kernel SIGKILL this process when the thread that started it ends, and kill
    it now if ``parent_pid`` is no longer its parent; True when armed, False where there is no
    ``PR_SET_PDEATHSIG``. OSError if the kernel refuses."""
    if not sys.platform.startswith("linux"):
        return False
    if _prctl()(PR_SET_PDEATHSIG, signal.SIGKILL, 0, 0, 0) != 0:
        err = ctypes.get_errno()
        raise OSError(err, f"prctl(PR_SET_PDEATHSIG): {os.strerror(err)}")
    if os.getppid() != parent_pid:
        _die()
    return True


def preexec(parent_pid: int | None = None):
    """``preexec_fn`` for ``subprocess.Popen``: ``arm`` in the child, between fork and exec.
    ``parent_pid``: this process (the default). libc is looked up here, in the parent."""
    parent_pid = os.getpid() if parent_pid is None else parent_pid
    if sys.platform.startswith("linux"):
        _prctl()
    return functools.partial(arm, parent_pid)
