"""The numba decorators every kernel module uses, in one place.

``cache=True`` keeps compiled code in ``__pycache__`` (or ``NUMBA_CACHE_DIR``), so a
second process does not compile again; ``nogil`` lets threads run kernels at once.

Transition (until :mod:`.query` moves to C too, and numba leaves): :mod:`.common` is
C now, and its Python wrappers cannot be called from numba code, so numba versions of
:func:`.common.pack` and :func:`.common.bspline_weights` are registered here as their
numba implementations (``overload``); :mod:`.query`'s kernels call them as before.
"""

from __future__ import annotations

import numba
import numpy as np
from numba.extending import overload

from . import common
from .layout import KEY_BITS, KEY_OFFSET

jit = numba.njit(cache=True, nogil=True, fastmath=False)
pjit = numba.njit(cache=True, nogil=True, parallel=True, fastmath=False)
# small helpers of the query loop, inlined into it at numba's IR level
ijit = numba.njit(cache=True, nogil=True, fastmath=False, inline="always")


def numba_threads() -> int:
    """Threads numba's parallel loops use now (``numba.set_num_threads``)."""
    return numba.get_num_threads()


@overload(common.pack, jit_options={"cache": True, "nogil": True})
def _pack_numba(i, j, k):
    def impl(i, j, k):
        return ((i + KEY_OFFSET) << (2 * KEY_BITS)) | ((j + KEY_OFFSET) << KEY_BITS) | (k + KEY_OFFSET)
    return impl


@overload(common.bspline_weights, jit_options={"cache": True, "nogil": True})
def _bspline_weights_numba(t, order, nderiv, out):
    # the arithmetic of gs_bspline_weights (src/common.c), step for step
    def impl(t, order, nderiv, out):
        if order == 4:
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
    return impl
