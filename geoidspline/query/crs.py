"""Coordinates in any CRS PROJ knows, to WGS84 geodetic latitude, longitude and height."""

from __future__ import annotations

import functools

import numpy as np

from ..errors import CoordinateError
from ..sphere.region import MAX_ABS_POINT_LONGITUDE_DEG


def _shaped(values, shape):
    """Reshape a flat result to the query's shape; a 0-d query gives a NumPy scalar."""
    values = np.asarray(values, dtype=np.float64).reshape(shape)
    return values[()] if shape == () else values


@functools.lru_cache(maxsize=32)
def _transformer(crs_text: str):
    import pyproj
    from pyproj.exceptions import CRSError, ProjError

    try:
        crs = pyproj.CRS.from_user_input(crs_text)
    except CRSError as exc:
        raise CoordinateError(f"unknown CRS {crs_text!r}: {exc}") from None
    kind = _crs_kind(crs)
    if kind is None:
        raise CoordinateError(
            f"CRS {crs_text!r} ({crs.name}, {crs.type_name}) is not supported: give a geographic "
            "(2D or 3D), geocentric or projected CRS; for a compound CRS give its horizontal part "
            "and pass the height with height_in"
        )
    try:
        transformer = pyproj.Transformer.from_crs(crs, "EPSG:4979", always_xy=True)
    except (CRSError, ProjError) as exc:
        raise CoordinateError(f"no transformation from {crs_text!r} to WGS84 (EPSG:4979): {exc}") from None
    return crs, kind, transformer


def _crs_kind(crs):
    if crs.is_compound or crs.is_vertical:
        return None
    if crs.is_geocentric:
        return "geocentric"
    if crs.is_projected:
        return "projected"
    if crs.is_geographic:
        return "geographic"
    return None


def crs_info(crs="EPSG:4326"):
    """(kind, dimension) of a CRS: kind "geographic", "geocentric" or "projected";
    dimension 2 or 3 (3 when its third axis is part of the coordinates, e.g. EPSG:4978
    or EPSG:4979). Raises :class:`CoordinateError` for an unknown or unsupported CRS."""
    crs_obj, kind, _ = _transformer(str(crs))
    return kind, (3 if len(crs_obj.axis_info) >= 3 else 2)


def to_geodetic(x, y, z=None, crs="EPSG:4326"):
    """Coordinates in ``crs`` to WGS84 geodetic (latitude, longitude, h) in degrees/metres.

    Uses a pyproj Transformer from ``crs`` to EPSG:4979 (WGS 84 geographic 3D) with
    ``always_xy=True``: ``x``, ``y`` are easting, northing for a projected CRS,
    **longitude, latitude** for a geographic one (whatever the CRS's own axis order), X, Y
    for a geocentric one. ``z`` is the third coordinate of a 3D CRS (geocentric Z,
    ellipsoidal height of a geographic 3D CRS); it is required for a geocentric CRS.
    Without ``z`` the returned h is NaN (unknown).

    ``crs`` is anything ``pyproj.CRS.from_user_input`` accepts ("EPSG:32633", a WKT or
    PROJ string, ...). Geographic 2D/3D, geocentric and projected CRSs are accepted;
    an unknown CRS or another kind (vertical, compound, engineering) raises
    :class:`CoordinateError`. Points PROJ cannot transform (or a geographic latitude
    beyond ±90°, or a longitude beyond ±1e6° that wrapping would turn into noise) give
    NaN. Longitudes come
    back in [−180, 180]. Scalars give scalars.
    """
    crs_obj, kind, transformer = _transformer(str(crs))
    try:
        xb, yb = np.broadcast_arrays(np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64))
        if z is not None:
            xb, yb, zb = np.broadcast_arrays(xb, yb, np.asarray(z, dtype=np.float64))
    except (TypeError, ValueError) as exc:
        raise CoordinateError(f"coordinates must be numbers of broadcastable shapes: {exc}") from None
    shape = xb.shape
    if kind == "geocentric" and z is None:
        raise CoordinateError(f"CRS {crs!r} is geocentric: x, y and z are all needed")
    xf, yf = xb.ravel(), yb.ravel()
    with np.errstate(invalid="ignore"):
        if z is None:
            lon, lat = transformer.transform(xf, yf)
            h = np.full(xf.shape, np.nan)
        else:
            lon, lat, h = transformer.transform(xf, yf, zb.ravel())
    lon = np.array(lon, dtype=np.float64, copy=True)
    lat = np.array(lat, dtype=np.float64, copy=True)
    h = np.array(h, dtype=np.float64, copy=True)
    with np.errstate(invalid="ignore"):
        # a longitude beyond ±1e6° would wrap to noise that looks like a position
        bad = ~(np.isfinite(lon) & np.isfinite(lat)) | (np.abs(lat) > 90.0)
        bad |= np.abs(lon) > MAX_ABS_POINT_LONGITUDE_DEG
    lon[bad] = np.nan
    lat[bad] = np.nan
    h[bad | ~np.isfinite(h)] = np.nan
    lon = np.where(np.abs(lon) > 180.0, (lon + 180.0) % 360.0 - 180.0, lon)
    return _shaped(lat, shape), _shaped(lon, shape), _shaped(h, shape)
