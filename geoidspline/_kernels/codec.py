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


_template_code = function("gs_template_code", I64, PTR, I64, I64, I64, PTR, PTR, PTR, PTR, PTR, PTR,
                          restype=ctypes.c_int)
_template_rows = function("gs_template_rows", I64, PTR, I64, PTR, I64, PTR, PTR, restype=ctypes.c_int)
_template_taps = function("gs_template_taps", I64, restype=ctypes.c_int64)


def template_taps(small: bool = False) -> int:
    """How many rows format 4's whole (or ``small``) template predicts a row from (``src/codec.c``)."""
    return int(_template_taps(int(bool(small))))


def _address(array):
    return None if array is None else ptr(array)


def template_code(keys, order, column, decode, shift, weights, small, values, residuals, kinds):
    """Format 4's prediction of one level: format 3's (:func:`radial_code`), except rows
    whose whole template's rows (``shift``: 4 int64, see ``src/codec.c``) are all there,
    predicted by ``weights`` (int64, :func:`template_taps`, in 1/65536; None: not), and
    the others whose small template's are, by ``small`` (None: not). Writes as
    :func:`radial_code` does, and ``kinds`` (uint8: how each row was predicted, 0 by the
    whole template, 1 by the small one)."""
    k = c_in(keys, np.int64)
    s, w, m = (None if a is None else c_in(a, np.int64) for a in (shift, weights, small))
    c_out(values, np.int64)
    c_out(residuals, np.int64)
    c_out(kinds, np.uint8)
    if _template_code(k.size, ptr(k), int(order), int(bool(column)), int(bool(decode)), _address(s), _address(w),
                      _address(m), ptr(values), ptr(residuals), ptr(kinds)) != 0:
        raise MemoryError(f"the store codec's work arrays for {k.size} coefficients")


def template_rows(keys, order, shift, small: bool = False):
    """(taps (n, :func:`template_taps`) int64: each row's rows of the whole (or ``small``)
    template as positions in ``keys``, -1 where one is missing; whether they are all there)."""
    k = c_in(keys, np.int64)
    s = c_in(shift, np.int64)
    taps = np.empty((k.size, template_taps(small)), dtype=np.int64)
    kinds = np.empty(k.size, dtype=np.uint8)
    if _template_rows(k.size, ptr(k), int(order), ptr(s), int(bool(small)), ptr(taps), ptr(kinds)) != 0:
        raise MemoryError(f"the store codec's work arrays for {k.size} coefficients")
    return taps, kinds == 0
