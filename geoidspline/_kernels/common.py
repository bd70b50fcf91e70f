"""Kernels shared by the fitting and query kernels: key packing, search, B-spline weights.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`. C:
``src/common.c`` (the C kernels use the inline versions of ``src/gs_common.h``); these
wrappers serve Python callers and tests.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, c_out, function, ptr

_pack = function("gs_pack_key", I64, I64, I64, restype=I64)
_lower_bound = function("gs_lower_bound_of", PTR, I64, I64, restype=I64)
_bspline_weights = function("gs_bspline_weights_into", F64, I64, I64, PTR, I64)


def pack(i, j, k):
    """The packed key of index triple (i, j, k)."""
    return _pack(i, j, k)


def bspline_weights(t, order, nderiv, out):
    """Cardinal B-spline values (and derivatives) touching a point.

    ``t`` in [0, 1) is the position inside the cell. ``out[d, j]`` receives the
    d-th derivative (d = 0..nderiv, with respect to x/h) of ``B_order(t + order-1-j)``,
    the weight of the B-spline ``k = a - order + 1 + j``. Uses the uniform-knot
    de Boor recursion ``w_q[j] = ((t+q-1-j) w_{q-1}[j-1] + (1+j-t) w_{q-1}[j]) / (q-1)``
    and ``B_q' = B_{q-1}(x) - B_{q-1}(x-1)``; a closed form for order 4. ``out``: C-contiguous
    float64 of shape (>= nderiv + 1, >= order); order <= 16.
    """
    c_out(out, np.float64)
    _bspline_weights(t, order, nderiv, ptr(out), out.shape[1])


def lower_bound(keys, value):
    """First position in sorted ``keys`` whose key is >= ``value`` (``len(keys)`` if none)."""
    keys = c_in(keys, np.int64)
    return _lower_bound(ptr(keys), keys.size, value)
