"""The store codec's prediction of a format-3 tile level's quantised values along the
radius (:func:`geoidspline.store.codec.radial_residuals`): one pass in slab order, each
row predicted from rows before it, encoding and decoding by the same code. In numpy the
decode needs a pass per slab and the foot lookups cost ~50 ms for a 93,000-coefficient
tile, against ~2 ms for the whole format-2 decode. C: ``src/codec.c``.
"""

from __future__ import annotations

import ctypes

import numpy as np

from ._clib import I64, PTR, c_in, c_out, function, ptr

_radial_code = function("gs_radial_code", I64, PTR, I64, I64, I64, PTR, PTR, restype=ctypes.c_int)


def radial_code(keys, order, column, decode, values, residuals):
    """Format 3's radial prediction of one level (``keys``: its sorted packed keys; ``order``:
    the spline's order; ``column``: the previous row's foot error is predicted too). ``decode``: writes ``values`` (int64 holding int32) from
    ``residuals``; else writes ``residuals`` (int64) from ``values``. The rule:
    ``src/codec.c``. :class:`MemoryError` when its work arrays cannot be allocated."""
    k = c_in(keys, np.int64)
    c_out(values, np.int64)
    c_out(residuals, np.int64)
    if _radial_code(k.size, ptr(k), int(order), int(bool(column)), int(bool(decode)), ptr(values),
                    ptr(residuals)) != 0:
        raise MemoryError(f"the store codec's work arrays for {k.size} coefficients")
