"""Euclidean norms with ``np.linalg.norm``'s numbers, without its per-call overhead (a control tick
takes many norms of small arrays).

``np.linalg.norm(v)`` of a real vector is sqrt(v . v) (``ndarray.dot``), and ``np.linalg.norm(x,
axis=-1)`` of real rows is sqrt of ``np.add.reduce(x * x, axis=-1)``: these functions do the same
operations in the same order, so they give the same numbers to the last bit.
"""

from __future__ import annotations

import math

import numpy as np


def vector_norm(v: np.ndarray) -> float:
    """||v|| of a real vector v (n,): ``float(np.linalg.norm(v))``."""
    return math.sqrt(v.dot(v))


def row_norms(x: np.ndarray, keepdims: bool = False) -> np.ndarray:
    """||x_i|| of each row of a real array x (..., n): ``np.linalg.norm(x, axis=-1, keepdims=keepdims)``."""
    return np.sqrt(np.add.reduce(x * x, axis=-1, keepdims=keepdims))
