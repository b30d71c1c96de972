"""The deep Koopman encoder's arithmetic (``koopman`` module docstring), defined once, in two forms
that give the same bits: numpy layers for any batch (``encoder_layers``) and a loop to compile
(``encoder_loop``, which the tick's lift runs, ``tick_kernel.window_lift_loop``).

A layer, in float32 (the precision of the encoder's training):

    a_j = (((b_j + h_0 W[0, j]) + h_1 W[1, j]) + ... ) + h_{d-1} W[d-1, j]

each product and each sum rounded to float32 (no fused multiply-add), summed in the order of k;
a hidden layer's output is tanh(a_j) by ``tanh_ratio``, rounded to float32. A BLAS matrix product
sums in an order of its own (blocked, fused, machine-dependent), which no loop reproduces; this
order is one that both forms follow exactly.

tanh: an odd rational function t(v) = v P(v^2) / Q(v^2), P and Q of degree 6 in v^2, fitted to
tanh on [0, 9] for the least maximum relative error (1.3e-8), evaluated in float64 on the input
clamped to [-9, 9] and its output clamped to [-1, 1]. Rounded to float32 it is within one unit in
the last place of the correctly rounded tanh for every float32 input (off by one in 9.5 % of them,
numpy's own float32 tanh in 30 %); tests/unit/core/dynamics/test_encoder_kernel.py measures it.
Only +, * and / in a fixed order: the loop and numpy round alike, where a library tanh differs
between numpy's SIMD code and the C library by an ulp.
"""

from __future__ import annotations

import numpy as np

TANH_CLAMP = 9.0            # |v| beyond it: tanh(v) rounds to 1 in float32, and so does t(9)
#: P_0 .. P_6 and Q_0 .. Q_6 of ``tanh_ratio``, by powers of v^2
TANH_P = (1.0, -0.1588733102213263, 0.031421273763739724, 0.00795275675213108, 0.00022598786695518362,
          1.3411117996855841e-06, 8.500935753941175e-10)
TANH_Q = (1.0, 0.17445991436804908, -0.04375844365425349, 0.024073202685229826, 0.0016308713991116312,
          2.142135957290491e-05, 5.016537541098487e-08)


def tanh_ratio(v):
    """t(v) = v P(v^2) / Q(v^2) (module docstring), by Horner's rule from the highest power; v: a float64
    scalar or array, already within [-TANH_CLAMP, TANH_CLAMP]."""
    z = v * v
    p = TANH_P[6]
    q = TANH_Q[6]
    for i in range(5, -1, -1):
        p = p * z + TANH_P[i]
        q = q * z + TANH_Q[i]
    return v * p / q


def encoder_tanh(a: np.ndarray) -> np.ndarray:
    """The hidden layers' tanh of float32 a (...): ``tanh_ratio`` on a clamped, clamped to [-1, 1], float32."""
    v = np.clip(a.astype(np.float64), -TANH_CLAMP, TANH_CLAMP)
    return np.clip(tanh_ratio(v), -1.0, 1.0).astype(np.float32)


def encoder_layers(h: np.ndarray, weights, biases) -> np.ndarray:
    """The encoder's layers on h (..., d_0) float32 (W_i (d_{i-1}, d_i), b_i (d_i,) float32), the last
    layer's output (..., d_L) float32: each layer starts from its bias and adds h_k W[k] for k in
    order, all rows at once (the loop's sums, ``encoder_loop``)."""
    h = np.asarray(h, dtype=np.float32)
    last = len(weights) - 1
    for i, (W, b) in enumerate(zip(weights, biases)):
        rows = h.reshape(-1, W.shape[0])
        out = np.empty((len(rows), W.shape[1]), np.float32)
        out[:] = b
        term = np.empty_like(out)
        for k in range(W.shape[0]):
            np.multiply(rows[:, k, None], W[k], out=term)
            out += term
        if i < last:
            out = encoder_tanh(out)
        h = out.reshape(h.shape[:-1] + (W.shape[1],))
    return h


def encoder_loop(h, weights, biases, dims, work, U, first):
    """``encoder_layers`` on the rows of h (rows, d_0) float32, as a loop: weights (sum d_{i-1} d_i,) and
    biases (sum d_i,) float32, each layer's W_i (row-major) and b_i one after the other, dims (L + 1,)
    the widths d_0 .. d_L; work (2, rows, max d_i) float32, the hidden layers' outputs in turn; the last
    layer's output goes to U[:, first: first + d_L] (float64)."""
    R = h.shape[0]
    L = dims.shape[0] - 1
    w_at, b_at = 0, 0
    for i in range(L):
        D, M = dims[i], dims[i + 1]
        W = weights[w_at: w_at + D * M].reshape((D, M))
        b = biases[b_at: b_at + M]
        src = h if i == 0 else work[(i - 1) % 2]
        dst = work[i % 2]
        for r in range(R):
            acc = dst[r]
            for j in range(M):
                acc[j] = b[j]
            for k in range(D):
                a = src[r, k]
                w = W[k]
                for j in range(M):
                    acc[j] = acc[j] + a * w[j]
            if i < L - 1:
                for j in range(M):
                    v = np.float64(acc[j])
                    v = TANH_CLAMP if v > TANH_CLAMP else (-TANH_CLAMP if v < -TANH_CLAMP else v)
                    t = tanh_ratio(v)
                    acc[j] = np.float32(1.0 if t > 1.0 else (-1.0 if t < -1.0 else t))
            else:
                for j in range(M):
                    U[r, first + j] = np.float64(acc[j])
        w_at += D * M
        b_at += M
