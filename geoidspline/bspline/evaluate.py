"""Pure-numpy evaluation of sparse ambient B-spline levels (no compiled kernels).

The small-batch path of :class:`geoidspline.hierarchy.AmbientSpline` and the reference
the compiled kernels (:mod:`geoidspline._kernels.query`) are tested against. It computes the
level-by-level sum Σ_ℓ Σ_k c_k B_k(x) directly: for each level, the order³ B-splines
touching each point are looked up in the level's sorted packed keys with one
``np.searchsorted`` over all points at once, and their values weighted with the
tensor-product cardinal B-spline weights (de Boor's recursion on uniform knots).

Cost: per level, M·order³ key searches (log₂ of the level's size each) and a few
(M, order, order, order) temporaries; a single point takes a few hundred µs for six
levels, dominated by numpy call overheads. Importing this module costs nothing beyond
numpy, which is what keeps ``geoid-query`` on one point fast in a cold process.

A point's result depends only on the coefficients of the B-splines non-zero at it
(missing keys contribute an exact 0.0), so evaluating a subset of a spline's tiles
that holds every such B-spline gives bitwise the same numbers as the whole spline.
"""

from __future__ import annotations

import numpy as np

from .basis import bspline_weights
from .keys import KEY_BITS, MAX_INDEX, pack_keys

#: Derivative multi-index (x, y, z) of each output column: value, gradient, Hessian
#: xx yy zz xy xz yz (the layout of every evaluator's output).
DERIVATIVE_COLUMNS = ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1),
                      (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1))


_WIDTH = {0: 1, 1: 4, 2: 10}


def _column_offsets(order):
    """Key offsets (order³,) of the B-splines touching a cell from the first one, p-major."""
    p, q, r = np.meshgrid(np.arange(order), np.arange(order), np.arange(order), indexing="ij")
    return ((p << (2 * KEY_BITS)) + (q << KEY_BITS) + r).astype(np.int64).ravel()


def evaluate_levels(levels, points, nderiv=0, out=None):
    """Σ over levels of the spline (nderiv 0) or value and derivatives (1, 2) at points.

    ``levels``: objects with ``h``, ``order``, sorted unique int64 ``keys`` and
    ``coefficients`` (:class:`geoidspline.bspline.level.LevelSpline`); ``points`` (M, 3)
    ambient points. Returns (or adds into ``out``) an (M, 1 | 4 | 10) array: value,
    gradient, Hessian xx yy zz xy xz yz, derivatives per unit length. Non-finite points
    give NaN in every column.
    """
    points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
    width = _WIDTH[nderiv]
    m = points.shape[0]
    if out is None:
        out = np.zeros((m, width))
    finite = np.isfinite(points).all(axis=1)
    safe = np.where(finite[:, None], points, 0.0)
    for lv in levels:
        if len(lv.keys) == 0 or m == 0:
            continue
        n, h = lv.order, lv.h
        scaled = safe / h
        cell = np.floor(scaled)
        t = scaled - cell
        # cells beyond the key range hold no B-spline (and would wrap when packed)
        inside = np.all(np.abs(cell) < MAX_INDEX - n, axis=1)
        cell = np.where(inside[:, None], cell, 0.0).astype(np.int64)
        t = np.where(inside[:, None], t, 0.0)
        wanted = pack_keys(cell - (n - 1))[:, None] + _column_offsets(n)[None, :]  # (M, n³)
        pos = np.searchsorted(lv.keys, wanted)
        np.minimum(pos, lv.keys.size - 1, out=pos)
        coef = np.where((lv.keys[pos] == wanted) & inside[:, None], lv.coefficients[pos], 0.0)
        coef = coef.reshape(m, n, n, n)
        wx, wy, wz = (bspline_weights(t[:, d], n, nderiv) for d in range(3))
        # contract z, then y, then x: (M, n, n) per z-derivative, (M, n) per (y, z)
        cz = [np.einsum("mpqr,mr->mpq", coef, wz[d]) for d in range(nderiv + 1)]
        for col, (dx, dy, dz) in enumerate(DERIVATIVE_COLUMNS[:width]):
            cyz = np.einsum("mpq,mq->mp", cz[dz], wy[dy])
            out[:, col] += np.einsum("mp,mp->m", cyz, wx[dx]) / h ** (dx + dy + dz)
    out[~finite] = np.nan
    return out
