"""Coverage lookups of large batches: is each point's source cell free of no-data nodes.

The same rule, step for step, as :meth:`geoidspline.sphere.coverage.NodataLattice.cells_have_data`
(numpy, used for small batches): one threaded pass instead of a dozen numpy passes and
a gather, which made a store with a no-data mask answer a batch 1.4-2 times slower.
C: ``src/coverage.c``.
"""

from __future__ import annotations

import numpy as np

from ._clib import F64, I64, PTR, c_in, c_out, function, ptr, threads

_cells_have_data = function("gs_cells_have_data", PTR, PTR, I64, F64, F64, F64, F64, F64, F64, F64, F64, I64, I64,
                            I64, PTR, F64, PTR, I64)


def cells_have_data(latitude, longitude, south, north, west, span, lat0, dlat, lon0, dlon, nlat, nlon, periodic,
                    cell_ok, edge_tol, out):
    """``out[p]``: point p lies in the region (``south <= lat <= north``, and
    ``(lon - west) mod 360 <= span`` unless span >= 360: :meth:`Region.contains`) and the
    lattice cell holding it has data at all four nodes (False beyond the lattice and for
    NaN). ``cell_ok`` is the flat row-major cell mask over ``nlat - 1`` rows and ``nlon``
    (periodic) or ``nlon - 1`` columns; nlat, nlon >= 2."""
    lat = c_in(latitude, np.float64)
    lon = c_in(longitude, np.float64)
    ok = c_in(cell_ok, np.bool_)
    c_out(out, np.bool_)
    _cells_have_data(ptr(lat), ptr(lon), lat.size, south, north, west, span, lat0, dlat, lon0, dlon, nlat, nlon,
                     int(periodic), ptr(ok), edge_tol, ptr(out), threads())
