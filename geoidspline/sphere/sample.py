"""Undulations on a latitude/longitude lattice: what a source gives and a fit reads.

Here, below both, so that :mod:`geoidspline.sources` (which makes samples) and
:mod:`geoidspline.fitting` (which fits them) import neither each other.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["NodeSample"]


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
