"""Kernels of spline quasi-interpolation, free of validation.

Keys are packed as in :mod:`geoidspline.bspline.keys` (sorted keys sort by (i, j, k); an
offset of ``t`` along an axis adds ``t * step`` to a key). The validated API is
:mod:`geoidspline.fitting.interpolation`. C: ``src/interpolation.c``.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, c_out, function, ptr, threads

_filter_axis = function("gs_filter_axis", PTR, PTR, I64, PTR, I64, I64, PTR, I64, PTR, I64)
_lattice_lookup = function("gs_lattice_lookup", PTR, I64, F64, F64, I64, F64, F64, PTR, PTR, I64, PTR, I64)
_key_directions = function("gs_key_directions", PTR, I64, I64, I64, F64, F64, PTR, PTR, I64)


def filter_axis(in_keys, in_values, out_keys, step, taps, out):
    """``out[m] = sum_t taps[t] * in_values[key(out_keys[m] + (t - T) * step)]``.

    ``in_keys`` (sorted) must hold every key the sum reads: ``out_keys`` (sorted) is
    shifted by a constant per tap, so each tap is one merge walk of two sorted arrays
    (linear, no binary search per point). The output is split into chunks walked in
    parallel, each starting its walk with one binary search.
    """
    in_keys, out_keys = c_in(in_keys, np.int64), c_in(out_keys, np.int64)
    in_values, taps = c_in(in_values, np.float64), c_in(taps, np.float64)
    c_out(out, np.float64)
    _filter_axis(ptr(in_keys), ptr(in_values), in_keys.size, ptr(out_keys), out_keys.size, int(step), ptr(taps),
                 taps.size, ptr(out), threads())


def lattice_lookup(grid, lat0, dlat, lon0, dlon, latitude, longitude, out, first_row=0):
    """6x6-point Lagrange interpolation on a padded latitude/longitude lattice.

    ``grid[i, j]`` holds the value at latitude ``lat0 + (first_row + i) dlat`` and longitude
    ``lon0 + j dlon`` (degrees): ``grid`` may hold a band of the rows of a lattice whose
    row 0 is at ``lat0``, and a point's weights are those of the whole lattice (its row
    position is shifted by the integer ``first_row``, exactly). The caller pads it so that
    every point has its 6x6 neighbourhood inside (reflected across the poles, wrapped in longitude).
    Longitudes are taken modulo 360 into [lon0 + 2 dlon, lon0 + 2 dlon + 360).
    """
    grid = c_in(grid, np.float64)
    latitude, longitude = c_in(latitude, np.float64), c_in(longitude, np.float64)
    c_out(out, np.float64)
    _lattice_lookup(ptr(grid), grid.shape[1], lat0, dlat, int(first_row), lon0, dlon, ptr(latitude), ptr(longitude),
                    latitude.size, ptr(out), threads())


def key_directions(keys, key_offset, key_bits, position_offset, h, latitude, longitude):
    """Geodetic latitude/longitude (degrees) of the directions of lattice points.

    The lattice point of packed key ``k`` (index triple ``a``) sits at
    ``(a + position_offset) h``; its direction is read as ``u = (cos φ cos λ, cos φ sin λ,
    sin φ)``, the mapping of :func:`geoidspline.sphere.coordinates.directions`.
    """
    keys = c_in(keys, np.int64)
    c_out(latitude, np.float64)
    c_out(longitude, np.float64)
    _key_directions(ptr(keys), keys.size, key_offset, key_bits, position_offset, h, ptr(latitude), ptr(longitude),
                    threads())
