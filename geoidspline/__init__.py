"""geoidspline: geoid undulations as C² ambient B-spline tiles (Lehmann 2013).

Fit a geoid grid or spherical-harmonic model once into a tile store (:func:`fit`,
``geoid-fit``), then answer point queries fast (:func:`open_store`, ``geoid-query``).
Latitudes and longitudes are in degrees, heights and undulations in metres.

The packages follow the method: :mod:`.sphere` (the reference manifold), :mod:`.bspline`
(one level), :mod:`.hierarchy` (levels summed), :mod:`.fitting`, :mod:`.sources` (grids
and harmonic models), :mod:`.store` (tiles on disk), :mod:`.query` (the query index and
derived quantities), :mod:`.geodesy` (ellipsoids); see README's "Architecture".
"""

from __future__ import annotations

from ._version import __version__
from .errors import CoordinateError, FitError, GeoidSplineError, InputFileError, StoreCorruptError, StoreError
from .sphere.region import GLOBAL, Region

__all__ = ["open_store", "fit", "update", "Region", "GLOBAL", "__version__", "GeoidSplineError",
           "InputFileError", "CoordinateError", "StoreError", "StoreCorruptError", "FitError"]


def open_store(path, *, lazy: bool = True, verify: bool = True):
    """Open a tile store read-only (:func:`geoidspline.api.open_store`).

    ``lazy`` (default) reads a tile when a query first needs it; ``lazy=False`` reads and
    checks every tile now. ``verify`` checks each tile's sha256 as it is read (sizes are
    always checked). Imports neither numba nor scipy: a one-point query stays fast.
    """
    from .store.reader import TileStore

    return TileStore.open(path, verify=verify, lazy=lazy)


def fit(source, store, **options):
    """Fit a source into a new store and open it (:func:`geoidspline.api.fit`)."""
    from .api import fit as _fit

    return _fit(source, store, **options)


def update(store, source, region, **options):
    """A regional update of a store (:func:`geoidspline.api.update`)."""
    from .api import update as _update

    return _update(store, source, region, **options)
