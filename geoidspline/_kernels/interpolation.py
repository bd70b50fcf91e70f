"""Kernels of spline quasi-interpolation, free of validation.

Keys are packed as in :mod:`geoidspline.bspline.keys` (sorted keys sort by (i, j, k); an
offset of ``t`` along an axis adds ``t * step`` to a key). The validated API is
:mod:`geoidspline.fitting.interpolation`.
"""

from __future__ import annotations

import math

import numba
import numpy as np

from ._jit import jit as _jit
from ._jit import pjit as _pjit


@_pjit
def filter_axis(in_keys, in_values, out_keys, step, taps, out):
    """``out[m] = sum_t taps[t] * in_values[key(out_keys[m] + (t - T) * step)]``.

    ``in_keys`` (sorted) must hold every key the sum reads: ``out_keys`` (sorted) is
    shifted by a constant per tap, so each tap is one merge walk of two sorted arrays
    (linear, no binary search per point). The output is split into chunks walked in
    parallel, each starting its walk with one binary search.
    """
    half = (taps.size - 1) // 2
    n = out_keys.size
    nchunk = max(1, min(64, n // 65536))
    for c in numba.prange(nchunk):
        lo = n * c // nchunk
        hi = n * (c + 1) // nchunk
        for m in range(lo, hi):
            out[m] = 0.0
        if hi <= lo:
            continue
        for t in range(taps.size):
            shift = (t - half) * step
            p = np.searchsorted(in_keys, out_keys[lo] + shift)
            w = taps[t]
            for m in range(lo, hi):
                target = out_keys[m] + shift
                while in_keys[p] < target:
                    p += 1
                out[m] += w * in_values[p]


@_jit
def _lagrange6(t, w):
    """Weights of the 6-point Lagrange interpolant on nodes -2..3 at ``t`` in [0, 1)."""
    for j in range(6):
        xj = j - 2.0
        v = 1.0
        for k in range(6):
            if k != j:
                v *= (t - (k - 2.0)) / (xj - (k - 2.0))
        w[j] = v


@_pjit
def lattice_lookup(grid, lat0, dlat, lon0, dlon, latitude, longitude, out):
    """6x6-point Lagrange interpolation on a padded latitude/longitude lattice.

    ``grid[i, j]`` holds the value at latitude ``lat0 + i dlat`` and longitude
    ``lon0 + j dlon`` (degrees); the caller pads it so that every point has its 6x6
    neighbourhood inside (reflected across the poles, wrapped in longitude).
    Longitudes are taken modulo 360 into [lon0 + 2 dlon, lon0 + 2 dlon + 360).
    """
    n = latitude.size
    nchunk = max(1, min(64, n // 65536))
    for c in numba.prange(nchunk):
        # weights allocated per chunk, not per point (tens of millions of points)
        w_lat = np.empty(6)
        w_lon = np.empty(6)
        for p in range(n * c // nchunk, n * (c + 1) // nchunk):
            y = (latitude[p] - lat0) / dlat
            i = int(math.floor(y))
            _lagrange6(y - i, w_lat)
            lon = longitude[p] - (lon0 + 2 * dlon)
            lon = lon - 360.0 * math.floor(lon / 360.0)
            x = lon / dlon + 2
            j = int(math.floor(x))
            _lagrange6(x - j, w_lon)
            acc = 0.0
            for a in range(6):
                row = 0.0
                for b in range(6):
                    row += w_lon[b] * grid[i - 2 + a, j - 2 + b]
                acc += w_lat[a] * row
            out[p] = acc


@_pjit
def key_directions(keys, key_offset, key_bits, position_offset, h, latitude, longitude):
    """Geodetic latitude/longitude (degrees) of the directions of lattice points.

    The lattice point of packed key ``k`` (index triple ``a``) sits at
    ``(a + position_offset) h``; its direction is read as ``u = (cos φ cos λ, cos φ sin λ,
    sin φ)``, the mapping of :func:`geoidspline.sphere.coordinates.directions`.
    """
    mask = (1 << key_bits) - 1
    for p in numba.prange(keys.size):
        key = keys[p]
        x = ((key >> (2 * key_bits)) & mask) - key_offset + position_offset
        y = ((key >> key_bits) & mask) - key_offset + position_offset
        z = (key & mask) - key_offset + position_offset
        latitude[p] = math.degrees(math.atan2(z * h, math.hypot(x * h, y * h)))
        longitude[p] = math.degrees(math.atan2(y * h, x * h))
