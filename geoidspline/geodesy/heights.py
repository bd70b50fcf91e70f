"""Orthometric and ellipsoidal heights from the geoid undulation (all metres)."""

from __future__ import annotations

import numpy as np

from ..errors import CoordinateError


#: The height kinds :func:`convert_height` takes, and what each is converted to.
HEIGHT_KINDS = {"ellipsoidal": "orthometric", "orthometric": "ellipsoidal"}


def convert_height(undulation, height, height_in):
    """Convert a height with the geoid undulation N (all metres).

    ``height_in="ellipsoidal"``: h above the ellipsoid → orthometric H = h − N;
    ``height_in="orthometric"``: H above the geoid → ellipsoidal h = H + N.
    Arrays broadcast; NaN propagates.
    """
    if height_in not in HEIGHT_KINDS:
        raise CoordinateError(f"height_in must be 'ellipsoidal' or 'orthometric', got {height_in!r}")
    n = np.asarray(undulation, dtype=np.float64)
    h = np.asarray(height, dtype=np.float64)
    out = h - n if height_in == "ellipsoidal" else h + n
    return out[()] if out.ndim == 0 else out
