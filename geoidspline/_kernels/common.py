"""Kernels shared by the fitting and query kernels: key packing, search, B-spline weights.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`.
"""

from __future__ import annotations

import numpy as np

from .layout import KEY_BITS, KEY_OFFSET
from ._jit import jit as _jit


@_jit
def pack(i, j, k):
    return ((i + KEY_OFFSET) << (2 * KEY_BITS)) | ((j + KEY_OFFSET) << KEY_BITS) | (k + KEY_OFFSET)


@_jit
def bspline_weights(t, order, nderiv, out):
    """Cardinal B-spline values (and derivatives) touching a point.

    ``t`` in [0, 1) is the position inside the cell. ``out[d, j]`` receives the
    d-th derivative (d = 0..nderiv, with respect to x/h) of ``B_order(t + order-1-j)``,
    the weight of the B-spline ``k = a - order + 1 + j``. Uses the uniform-knot
    de Boor recursion ``w_q[j] = ((t+q-1-j) w_{q-1}[j-1] + (1+j-t) w_{q-1}[j]) / (q-1)``
    and ``B_q' = B_{q-1}(x) - B_{q-1}(x-1)``.
    """
    if order == 4:
        # closed form of the cubic case: the hot path of every query
        s = 1.0 - t
        t2 = t * t
        t3 = t2 * t
        out[0, 0] = s * s * s / 6.0
        out[0, 1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
        out[0, 2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
        out[0, 3] = t3 / 6.0
        if nderiv >= 1:
            out[1, 0] = -0.5 * s * s
            out[1, 1] = 1.5 * t2 - 2.0 * t
            out[1, 2] = -1.5 * t2 + t + 0.5
            out[1, 3] = 0.5 * t2
        if nderiv >= 2:
            out[2, 0] = s
            out[2, 1] = 3.0 * t - 2.0
            out[2, 2] = 1.0 - 3.0 * t
            out[2, 3] = t
        return
    work = np.zeros((order + 1, order + 1))
    work[1, 0] = 1.0
    for q in range(2, order + 1):
        for j in range(q):
            left = work[q - 1, j - 1] if j >= 1 else 0.0
            right = work[q - 1, j] if j <= q - 2 else 0.0
            work[q, j] = ((t + q - 1 - j) * left + (1 + j - t) * right) / (q - 1)
    for j in range(order):
        out[0, j] = work[order, j]
    if nderiv >= 1:
        q = order - 1
        for j in range(order):
            left = work[q, j - 1] if j >= 1 else 0.0
            right = work[q, j] if j <= q - 1 else 0.0
            out[1, j] = left - right
    if nderiv >= 2:
        q = order - 2
        for j in range(order):
            a = work[q, j - 2] if j >= 2 else 0.0
            b = work[q, j - 1] if (j >= 1 and j - 1 <= q - 1) else 0.0
            c = work[q, j] if j <= q - 1 else 0.0
            out[2, j] = a - 2.0 * b + c


@_jit
def lower_bound(keys, value):
    lo = 0
    hi = keys.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo
