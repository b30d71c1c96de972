"""The nearest-segment searches of ``path.ReferencePath`` and of ``path.nearest_on_polyline`` as plain
loops to compile.

The candidate segments are those of ``window_runs`` (which ``ReferencePath._searched`` uses too: the
binary searches on the arc lengths, the seam of a closed path included), scanned in ascending order. For each segment i (first vertex a = points[i], direction v = seg_vec[i]) the foot
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

import math

import numpy as np


def window_runs(s, lo, span, closed):
    """The segments of a path with vertex arc lengths s (n + 1,) that overlap the window [lo, lo +
    span] (``ReferencePath._searched``), as up to two ascending runs [a0, a1), [b0, b1) (an empty
    run has stop <= start): on an open path those overlapping it, else its first or last segment;
    on a closed one the window taken modulo its length, across the seam too (a segment touching an
    end within rounding counts), all of them where it is as long as the path."""
    n = s.shape[0] - 1
    L = s[n]
    a0, a1, b0, b1 = 0, n, 0, 0
    if not closed:                              # s is sorted
        a0 = np.searchsorted(s[1:], lo, side="left")
        a1 = np.searchsorted(s[:-1], lo + span, side="right")
        if a1 <= a0:
            a0 = n - 1 if lo > 0 else 0
            a1 = a0 + 1
    elif span < L:
        lo = lo % L
        a, b = lo - 1e-9, lo + span + 1e-9
        i0 = np.searchsorted(s[1:], max(a, 0.0), side="left")        # the first segment ending at or after a
        i1 = np.searchsorted(s[:-1], min(b, L), side="right")        # past the last one starting by b
        if b > L:                                   # across the seam: the path's start too
            j = min(i0, np.searchsorted(s[:-1], b - L, side="right"))
            if j < i0:
                a0, a1, b0, b1 = 0, j, i0, i1
            else:
                a0, a1 = 0, i1
        elif a < 0.0:                               # across the seam: the path's end too
            a0, a1, b0, b1 = i0, i1, max(i1, np.searchsorted(s[1:], a + L, side="left")), n
        else:
            a0, a1 = i0, i1
        if max(a1 - a0, 0) + max(b1 - b0, 0) == 0:
            a0 = n - 1 if lo > 0 else 0
            a1, b0, b1 = a0 + 1, 0, 0
    return a0, a1, b0, b1


def nearest_arc_length(p, points, s, seg_vec, seg_len2, lo, span, closed, everything):
    """The arc length of the point nearest to p (d,) on the segments of ``window_runs`` for the window
    [lo, lo + span] (all of them with ``everything``), scanned in ascending order."""
    a0, a1, b0, b1 = (0, seg_vec.shape[0], 0, 0) if everything else window_runs(s, lo, span, closed)
    d = p.shape[0]
    best_i, best_w, best_d2 = -1, 0.0, 0.0
    for r in range(2):
        start, stop = (a0, a1) if r == 0 else (b0, b1)
        for i in range(start, stop):
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
                return s[i] + w * math.sqrt(seg_len2[i])
            if best_i < 0 or d2 < best_d2:
                best_i, best_w, best_d2 = i, w, d2
    return s[best_i] + best_w * math.sqrt(seg_len2[best_i])


def polyline_nearest(p, xy):
    """``path.nearest_on_polyline``'s search over the polyline through xy (K, d), K >= 2, in its order
    of operations: (the least squared distance from p (d,), the index of its segment's first
    vertex), the first of equals (np.argmin's choice; a NaN wins at once)."""
    d = p.shape[0]
    best_i, best_d2 = -1, 0.0
    for i in range(xy.shape[0] - 1):
        w = 0.0
        dot = 0.0
        for j in range(d):
            ab = xy[i + 1, j] - xy[i, j]
            w += ab * ab
            dot += (p[j] - xy[i, j]) * ab
        h = min(max(dot / max(w, 1e-12), 0.0), 1.0)
        d2 = 0.0
        for j in range(d):
            e = xy[i, j] + h * (xy[i + 1, j] - xy[i, j]) - p[j]
            d2 += e * e
        if d2 != d2:                        # NaN
            return d2, i
        if best_i < 0 or d2 < best_d2:
            best_i, best_d2 = i, d2
    return best_d2, best_i
