"""The nearest-segment search of ``path.ReferencePath`` as one plain loop to compile.

For each candidate segment i (first vertex a = points[i], direction v = seg_vec[i]) the foot
parameter w = clip((p - a) . v / |v|^2, 0, 1) and the squared distance |p - (a + w v)|^2, in the
order of the numpy path's operations; the first segment of least distance wins (np.argmin's
choice; a NaN distance wins at once, as np.argmin takes the first NaN). A loop compiler (numba's
``njit``: ``vflpcd.controllers.loops`` compiles it, outside core) turns it into machine code.

The numbers are the numpy path's exactly for planar paths (each dot product is one sum of two
products); numpy's einsum adds three products in an order that depends on its SIMD build, so on a
3-D path they agree to a rounding (1e-12), and where two segments lie within a rounding of the
same distance either may be taken (their feet then lie within a rounding of each other).
"""

from __future__ import annotations


def nearest_segment(p, points, seg_vec, seg_len2, idx):
    """The nearest of the segments idx (K,) int to p (d,): (its index i, its foot parameter w)."""
    d = p.shape[0]
    best_i, best_w, best_d2 = -1, 0.0, 0.0
    for k in range(idx.shape[0]):
        i = idx[k]
        dot = 0.0
        for j in range(d):
            dot += (p[j] - points[i, j]) * seg_vec[i, j]
        w = dot / seg_len2[i]
        if w < 0.0:
            w = 0.0
        if w > 1.0:
            w = 1.0
        d2 = 0.0
        for j in range(d):
            e = p[j] - (points[i, j] + w * seg_vec[i, j])
            d2 += e * e
        if d2 != d2:                    # NaN
            return i, w
        if best_i < 0 or d2 < best_d2:
            best_i, best_w, best_d2 = i, w, d2
    return best_i, best_w
