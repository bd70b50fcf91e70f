"""Kernels of the least-squares fit: the domain test and the normal equations.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`.

The validated API is :mod:`geoidspline.fitting`. C: ``src/fitting.c``.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, function, ptr

_cells_meet_sphere = function("gs_cells_meet_sphere", PTR, I64, F64, F64, PTR)
_normal_table = function("gs_normal_table", PTR, PTR, I64, F64, I64, PTR, I64, PTR, PTR, restype=I64)
_normal_compress = function("gs_normal_compress", PTR, PTR, I64, I64, PTR, PTR, PTR)


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
    cells = c_in(cells, np.int64)
    out = np.empty(cells.shape[0], dtype=np.bool_)
    _cells_meet_sphere(ptr(cells), cells.shape[0], h, radius, ptr(out))
    return out



def normal_equations(points, values, h, order, keys):
    """Upper triangle of AᵀA (CSC) and Aᵀb for the B-splines ``keys`` at sites ``points``.

    Accumulates straight into a (len(keys), (2 order - 1)³) table indexed by the
    relative position of the second B-spline, so no sparse product or sort is needed;
    each site costs order⁶ multiply-adds. Returns (indptr, indices, data, rhs).
    """
    points, values = c_in(points, np.float64), c_in(values, np.float64)
    keys = c_in(keys, np.int64)
    n = keys.shape[0]
    span = 2 * order - 1
    table = np.zeros((n, span**3))
    rhs = np.zeros(n)
    if _normal_table(ptr(points), ptr(values), points.shape[0], h, order, ptr(keys), n, ptr(table), ptr(rhs)) != 0:
        raise MemoryError("no memory for the scratch of the normal equations")
    count = int(np.count_nonzero(table))
    indptr = np.empty(n + 1, dtype=np.int64)
    indices = np.empty(count, dtype=np.int64)
    data = np.empty(count)
    _normal_compress(ptr(table), ptr(keys), n, order, ptr(indptr), ptr(indices), ptr(data))
    return indptr, indices, data, rhs
