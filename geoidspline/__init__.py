"""geoidspline: geoid undulations as C² ambient B-spline tiles (Lehmann 2013).

Fit a geoid grid or spherical-harmonic model once into a tile store
(:func:`geoidspline.fit.fit_source`, ``geoid-fit``), then answer point queries fast
(:func:`open_store`, ``geoid-query``). Latitudes and longitudes are in degrees,
heights and undulations in metres.
"""

from __future__ import annotations

__version__ = "0.1.0"

__all__ = ["open_store", "__version__"]


def open_store(path):
    """Open a tile store read-only; see :class:`geoidspline.store.TileStore`."""
    from .store import TileStore

    return TileStore.open(path)
