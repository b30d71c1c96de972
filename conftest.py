"""Test-session set-up: single-threaded BLAS before numpy is first imported (see vflpcd/__init__.py)."""

import vflpcd  # noqa: F401  (sets the BLAS thread variables)
