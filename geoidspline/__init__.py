"""geoidspline: geoid undulations as C² ambient B-spline tiles (Lehmann 2013).

Fit a geoid grid or spherical-harmonic model once into a tile store (:func:`fit`,
``geoid-fit``), then answer point queries fast (:func:`open_store`, ``geoid-query``).
Latitudes and longitudes are in degrees, heights and undulations in metres.

The packages are layers, bottom to top (tests/test_architecture.py checks every import):
:mod:`._kernels` (compiled loops), :mod:`.geodesy` (ellipsoids, heights), :mod:`.sphere`
(the reference manifold), :mod:`.bspline` (one level, the brick index), :mod:`.hierarchy`
(levels summed); side by side above them :mod:`.sources` (grids and harmonic models),
:mod:`.fitting` (one engine, the regional update a strategy of it), :mod:`.store` (tiles
on disk) and :mod:`.query` (batches, derived quantities); :mod:`.api` is the front door
composing them, and the commands call only it.
"""

from __future__ import annotations

import importlib.util as _importlib_util
import sys as _sys
import pathlib as _pathlib

from ._version import __version__
from .errors import (CoordinateError, FitError, GeoidSplineError, InputFileError, ParameterError, StoreCorruptError,
                     StoreError)
from .sphere.region import GLOBAL, Region

__all__ = ["open_store", "fit", "update", "Region", "GLOBAL", "__version__", "GeoidSplineError",
           "InputFileError", "CoordinateError", "StoreError", "StoreCorruptError", "FitError", "ParameterError"]


def open_store(path, *, lazy: bool = True, verify: bool = True, key=None, cache_bytes: int | None = None):
    """Open a tile store read-only (:func:`geoidspline.api.open_store`).

    ``lazy`` (default) reads a tile when a query first needs it; ``lazy=False`` reads and
    checks every tile now. ``verify`` checks each tile's sha256 as it is read (sizes are
    always checked). ``key``: the Ed25519 public key (PEM file) that must have signed
    the store (docs/signing.md). ``cache_bytes``: the bound of what the store keeps
    between queries short of reading it whole. Imports neither the compiled kernels nor
    scipy: a one-point query stays fast.
    """
    from .api import open_store as _open_store

    return _open_store(path, verify=verify, lazy=lazy, key=key, cache_bytes=cache_bytes)


def fit(source, store, **options):
    """Fit a source into a new store and open it (:func:`geoidspline.api.fit`)."""
    from .api import fit as _fit

    return _fit(source, store, **options)


def update(store, source, region, **options):
    """A regional update of a store (:func:`geoidspline.api.update`)."""
    from .api import update as _update

    return _update(store, source, region, **options)


class _CheckoutPackages:
    """Finds ``geoidspline.cli`` and ``geoidspline.grids`` in a source checkout.

    They live at the repository's top level (``cli/``, ``grids/``) and join the package
    through the install's package-dir mapping; a program run from the checkout root imports
    this source tree instead, where the mapping does not exist. Appended last to
    ``sys.meta_path``, so an install's own finders always win.
    """

    _root = _pathlib.Path(__file__).resolve().parent.parent

    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name not in ("geoidspline.cli", "geoidspline.grids"):
            return None
        folder = cls._root / name.rpartition(".")[2]
        if not (folder / "__init__.py").is_file():
            return None
        return _importlib_util.spec_from_file_location(name, folder / "__init__.py",
                                                       submodule_search_locations=[str(folder)])


if not any(finder is _CheckoutPackages for finder in _sys.meta_path):
    _sys.meta_path.append(_CheckoutPackages)
