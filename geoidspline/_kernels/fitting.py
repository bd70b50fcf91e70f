"""Kernels of the least-squares fit: the domain test and the normal equations.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`.

The validated API is :mod:`geoidspline.fitting`.
"""

from __future__ import annotations

import numpy as np

from .layout import KEY_BITS
from ._jit import jit as _jit
from .common import bspline_weights
from .common import lower_bound as _lower_bound
from .common import pack as _pack


@_jit
def cells_meet_sphere(cells, h, radius):
    """Whether each cell (M, 3) of spacing h meets the sphere |x| = radius.

    The box is convex and |x| continuous, so it meets the sphere exactly when the
    nearest point is inside or on it and the farthest outside or on it. "On" has a
    relative slack of 1e-9: where the sphere touches a cell face (the poles and the four
    equator points on the axes, whenever 1/h is an integer) rounding of ``k h`` must not
    drop the outer cell (at h = 0.005, -201 h + h rounds below -1): level 0 then misses
    the B-splines outside the south pole, and an overlay fitting the residual at the
    outer sites there made a 70 mm error at the pole.
    """
    m = cells.shape[0]
    out = np.empty(m, dtype=np.bool_)
    r2 = radius * radius
    for s in range(m):
        near = 0.0
        far = 0.0
        for d in range(3):
            lo = cells[s, d] * h
            hi = lo + h
            if lo > 0.0:
                near += lo * lo
            elif hi < 0.0:
                near += hi * hi
            far += max(lo * lo, hi * hi)
        out[s] = near <= r2 * (1.0 + 1e-9) and r2 * (1.0 - 1e-9) <= far
    return out


@_jit
def normal_equations(points, values, h, order, keys):
    """Upper triangle of AᵀA (CSC) and Aᵀb for the B-splines ``keys`` at sites ``points``.

    Accumulates straight into a (len(keys), (2 order - 1)³) table indexed by the
    relative position of the second B-spline, so no sparse product or sort is needed;
    each site costs order⁶ multiply-adds. Returns (indptr, indices, data, rhs).
    """
    n = keys.shape[0]
    span = 2 * order - 1
    width = span * span * span
    table = np.zeros((n, width))
    rhs = np.zeros(n)
    inv_h = 1.0 / h
    block = order * order * order
    cols = np.empty(block, dtype=np.int64)
    vals = np.empty(block)
    loc = np.empty((block, 3), dtype=np.int64)
    wx = np.empty((3, order))
    wy = np.empty((3, order))
    wz = np.empty((3, order))
    for s in range(points.shape[0]):
        fx = points[s, 0] * inv_h
        fy = points[s, 1] * inv_h
        fz = points[s, 2] * inv_h
        ax = int(np.floor(fx))
        ay = int(np.floor(fy))
        az = int(np.floor(fz))
        bspline_weights(fx - ax, order, 0, wx)
        bspline_weights(fy - ay, order, 0, wy)
        bspline_weights(fz - az, order, 0, wz)
        found = 0
        k0 = az - order + 1
        for p in range(order):
            i = ax - order + 1 + p
            for q in range(order):
                j = ay - order + 1 + q
                base = _pack(i, j, k0)
                pos = _lower_bound(keys, base)
                while pos < n and keys[pos] < base + order:
                    r = keys[pos] - base
                    cols[found] = pos
                    vals[found] = wx[0, p] * wy[0, q] * wz[0, r]
                    loc[found, 0] = p
                    loc[found, 1] = q
                    loc[found, 2] = r
                    found += 1
                    pos += 1
        value = values[s]
        for e2 in range(found):
            c2 = cols[e2]
            v2 = vals[e2]
            rhs[c2] += v2 * value
            for e1 in range(found):
                if cols[e1] > c2:
                    continue
                off = ((loc[e1, 0] - loc[e2, 0] + order - 1) * span
                       + (loc[e1, 1] - loc[e2, 1] + order - 1)) * span + (loc[e1, 2] - loc[e2, 2] + order - 1)
                table[c2, off] += vals[e1] * v2
    # compress: column c2 holds rows c1 <= c2; offsets in lexicographic order are
    # increasing key deltas, hence increasing row positions
    count = 0
    for c in range(n):
        for off in range(width):
            if table[c, off] != 0.0:
                count += 1
    indptr = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(count, dtype=np.int64)
    data = np.empty(count)
    at = 0
    for c in range(n):
        for off in range(width):
            v = table[c, off]
            if v != 0.0:
                dr = off % span - (order - 1)
                dq = (off // span) % span - (order - 1)
                dp = off // (span * span) - (order - 1)
                target = keys[c] + (dp << (2 * KEY_BITS)) + (dq << KEY_BITS) + dr
                indices[at] = _lower_bound(keys, target)
                data[at] = v
                at += 1
        indptr[c + 1] = at
    return indptr, indices, data, rhs
