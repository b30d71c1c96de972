"""Small linear algebra written as plain loops, for the loops that ``vflpcd.controllers.loops``
compiles with numba (it registers these with them; run as Python they are plain functions)."""

from __future__ import annotations


def matvec(M, x, out):
    """out (n,) = M (n, m) x (m,), each entry one sum in column order."""
    for i in range(M.shape[0]):
        acc = 0.0
        for j in range(M.shape[1]):
            acc += M[i, j] * x[j]
        out[i] = acc


def row_sq_distance(A, j, z):
    """|A[j] - z|^2 for A (m, n) and z (n,), one sum in column order."""
    acc = 0.0
    for i in range(z.shape[0]):
        e = A[j, i] - z[i]
        acc += e * e
    return acc
