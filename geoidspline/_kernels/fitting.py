"""Kernels of the least-squares fit: the domain test and the normal equations.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`.

The validated API is :mod:`geoidspline.fitting`. C: ``src/fitting.c``.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, function, ptr

_cells_meet_sphere = function("gs_cells_meet_sphere", PTR, I64, F64, F64, PTR)
_normal_table = function("gs_normal_table", PTR, PTR, I64, F64, I64, PTR, I64, I64, I64, PTR, PTR, restype=I64)
_normal_compress = function("gs_normal_compress", PTR, PTR, I64, I64, I64, I64, PTR, PTR, PTR)
_schwarz_apply = function("gs_schwarz_apply", I64, PTR, PTR, PTR, PTR, PTR, PTR, PTR)
_cholesky_packed = function("gs_cholesky_packed", PTR, I64, F64, PTR, restype=I64)


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



def normal_equations(points, values, h, order, keys, first=0, last=None, rhs=None):
    """Columns ``first <= c < last`` of the upper triangle of AᵀA (CSC, int32 row indices
    into ``keys``) and of Aᵀb for the B-splines ``keys`` (sorted) at sites ``points``.

    Accumulates straight into a (last - first, (2 order - 1)³) table indexed by the
    relative position of the second B-spline, so no sparse product or sort is needed; each
    site costs order⁶ multiply-adds. Slices of the columns bound the table (sites that
    reach no column of the slice only cost their lookup). Aᵀb of the slice's columns is
    added into ``rhs`` (len(keys), zeros when not given). Returns (indptr, indices, data, rhs).
    """
    points, values = c_in(points, np.float64), c_in(values, np.float64)
    keys = c_in(keys, np.int64)
    n = keys.shape[0]
    last = n if last is None else last
    span = 2 * order - 1
    table = np.zeros((last - first, span**3))
    rhs = np.zeros(n) if rhs is None else rhs
    if _normal_table(ptr(points), ptr(values), points.shape[0], h, order, ptr(keys), n, first, last, ptr(table),
                     ptr(rhs)) != 0:
        raise MemoryError("no memory for the scratch of the normal equations")
    count = int(np.count_nonzero(table))
    indptr = np.empty(last - first + 1, dtype=np.int64)
    indices = np.empty(count, dtype=np.int32)
    data = np.empty(count)
    _normal_compress(ptr(table), ptr(keys), n, first, last, order, ptr(indptr), ptr(indices), ptr(data))
    return indptr, indices, data, rhs


def cholesky_packed(lower, shift, out):
    """Cholesky factor of the symmetric matrix whose lower triangle is that of ``lower``
    (m x m), plus ``shift`` on its diagonal, packed by rows into ``out`` (m (m + 1) / 2, a
    view is written in place). Returns 0, or i + 1 when the pivot of row i is not positive."""
    lower = c_in(lower, np.float64)
    return int(_cholesky_packed(ptr(lower), lower.shape[0], shift, ptr(out)))


def schwarz_apply(block_at, index, factor_at, factors, r):
    """``Σ_b R_bᵀ (L_b L_bᵀ)⁻¹ R_b r`` over the blocks ``index[block_at[b]:block_at[b+1]]``
    with their Cholesky factors packed by rows at ``factors[factor_at[b]:]`` in float32
    (the solves accumulate in float64)."""
    block_at, index, factor_at = c_in(block_at, np.int64), c_in(index, np.int64), c_in(factor_at, np.int64)
    factors, r = c_in(factors, np.float32), c_in(r, np.float64)
    z = np.zeros_like(r)
    work = np.empty(int(np.diff(block_at).max()) if block_at.size > 1 else 0)
    _schwarz_apply(block_at.size - 1, ptr(block_at), ptr(index), ptr(factor_at), ptr(factors), ptr(r), ptr(z),
                   ptr(work))
    return z
