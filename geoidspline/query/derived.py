"""Quantities derived from a spline: deflections and heights.

Latitudes and longitudes are geodetic degrees (WGS84), heights and undulations metres.
Scalars give scalars, arrays broadcast, NaN gives NaN, a finite latitude beyond ±90°
raises :class:`~geoidspline.errors.CoordinateError`. They live below the layers that use
them (a store's methods call them too): :func:`deflection` beside the spline it
differentiates (:mod:`geoidspline.hierarchy.derived`), :func:`convert_height` in
:mod:`geoidspline.geodesy.heights`; a store's measured error bound is the store's own
(:func:`geoidspline.store.error_bound.tile_error_bound`).
"""

from __future__ import annotations

from ..geodesy.heights import HEIGHT_KINDS, convert_height
from ..hierarchy.derived import ARCSEC_PER_RADIAN, Deflection, deflection

__all__ = ["ARCSEC_PER_RADIAN", "Deflection", "deflection", "HEIGHT_KINDS", "convert_height"]
