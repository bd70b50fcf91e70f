"""The B-spline weights of the compiled kernels, for Python callers and tests.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`. C:
``gs_weights`` of ``src/gs_common.h``, the one definition the fitting and query kernels
inline (key packing and binary search live there too; Python has
:mod:`geoidspline.bspline.keys` and ``np.searchsorted``).
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_out, function, ptr

_bspline_weights = function("gs_bspline_weights_into", F64, I64, I64, PTR, I64)


def bspline_weights(t, order, nderiv, out):
    """Cardinal B-spline values (and derivatives) touching a point.

    ``t`` in [0, 1) is the position inside the cell. ``out[d, j]`` receives the
    d-th derivative (d = 0..nderiv, with respect to x/h) of ``B_order(t + order-1-j)``,
    the weight of the B-spline ``k = a - order + 1 + j``. Uses the uniform-knot
    de Boor recursion ``w_q[j] = ((t+q-1-j) w_{q-1}[j-1] + (1+j-t) w_{q-1}[j]) / (q-1)``
    and ``B_q' = B_{q-1}(x) - B_{q-1}(x-1)``; closed forms for the values of orders 4 and 6.
    ``out``: C-contiguous float64 of shape (>= nderiv + 1, >= order); order <= 16.
    """
    c_out(out, np.float64)
    _bspline_weights(t, order, nderiv, ptr(out), out.shape[1])

