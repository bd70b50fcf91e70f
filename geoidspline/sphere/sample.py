"""Undulations on a latitude/longitude lattice: what a source gives and a fit reads.

Here, below both, so that :mod:`geoidspline.sources` (which makes samples) and
:mod:`geoidspline.fitting` (which fits them) import neither each other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NodeSample", "catmull_rom_weights", "lattice_interpolation", "interval_distance"]


@dataclass(frozen=True)
class NodeSample:
    """Undulations on a latitude/longitude lattice.

    ``latitude`` (degrees, ascending, shape (nlat,)), ``longitude`` (degrees, ascending,
    shape (nlon,), possibly beyond ±180 for a region crossing the antimeridian) and
    ``undulation`` (metres, shape (nlat, nlon)). NaN marks a node without data.
    ``first_row``: the index of the first row on a larger lattice the sample is a band of
    (a fit thins nodes by rows of that lattice, so a band thins as the whole would).
    """

    latitude: np.ndarray
    longitude: np.ndarray
    undulation: np.ndarray
    first_row: int = 0


def catmull_rom_weights(t):
    """Catmull-Rom (cubic convolution, a = -0.5) weights of nodes -1, 0, 1, 2 at t in [0, 1].

    Returns an array of shape (4,) + t.shape. The weights sum to 1 and reproduce
    polynomials up to degree 2 exactly on a uniform lattice.
    """
    t2 = t * t
    t3 = t2 * t
    return np.stack(
        [
            0.5 * (-t3 + 2.0 * t2 - t),
            0.5 * (3.0 * t3 - 5.0 * t2 + 2.0),
            0.5 * (-3.0 * t3 + 4.0 * t2 + t),
            0.5 * (t3 - t2),
        ]
    )


def lattice_interpolation(values, row, row_fraction, col, col_fraction, method: str, periodic: bool):
    """Bilinear or bicubic (Catmull-Rom) interpolation of ``values`` (nlat, nlon) in the
    cell whose south-west node is (``row``, ``col``), at the fractions ``row_fraction``,
    ``col_fraction`` (in [0, 1]) of its sides: what a grid's ``undulation`` gives between
    its nodes and what a fit's cell centres are valued at, one computation for both.

    ``row`` in [0, nlat - 2]; ``col`` in [0, nlon - 1] when ``periodic`` (columns wrap),
    else in [0, nlon - 2]. The bicubic stencil's rows beyond the first/last are clamped to
    the edge row (no crossing of the poles), its columns wrapped or clamped likewise.
    """
    nlat, nlon = values.shape
    i, j, fy, fx, v = row, col, row_fraction, col_fraction, values
    if method == "bilinear":
        j1 = (j + 1) % nlon if periodic else j + 1
        # Same expression order as GeographicLib's Geoid (bilinear branch).
        a = (1.0 - fx) * v[i, j] + fx * v[i, j1]
        b = (1.0 - fx) * v[i + 1, j] + fx * v[i + 1, j1]
        return (1.0 - fy) * a + fy * b
    wy = catmull_rom_weights(fy)
    wx = catmull_rom_weights(fx)
    inside = np.zeros(np.shape(i))
    # 16 gathers of one value per point keep memory at O(points).
    for a in range(4):
        rows = np.clip(i + (a - 1), 0, nlat - 1)  # clamp at the edge rows
        row_sum = np.zeros(np.shape(i))
        for b in range(4):
            cols = j + (b - 1)
            cols = cols % nlon if periodic else np.clip(cols, 0, nlon - 1)
            row_sum += wx[b] * v[rows, cols]
        inside += wy[a] * row_sum
    return inside


def interval_distance(values, low, high) -> np.ndarray:
    """How far ``values`` lie outside the intervals [``low``, ``high``] (0 inside), metres:
    a grid's figure between its nodes, the interval spanned there by its bilinear and
    bicubic interpolants (its truth is unknown but lies near them)."""
    return np.maximum(np.maximum(low - values, values - high), 0.0)
