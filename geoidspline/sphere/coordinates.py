"""Geodetic positions and directions on the reference manifold, the unit sphere.

A geodetic position (latitude φ, longitude λ, degrees, WGS84) maps to the direction
``u = (cos φ cos λ, cos φ sin λ, sin φ)`` (METHOD.md §1); :func:`latlon_of` is the
inverse of the radial projection ``x / |x|``, so the radially constant extension of a
function on the sphere is ``G(x) = g(latlon_of(x))``.
"""

from __future__ import annotations

import numpy as np

from ..errors import CoordinateError
from .region import MAX_ABS_POINT_LONGITUDE_DEG

#: Batches from this size on use compiled code (worth loading the kernel library and a
#: thread fan-out); smaller ones are evaluated with numpy, so a one-point query stays fast.
COMPILED_FROM_POINTS = 2048


def _within(values, bound) -> bool:
    """Whether every non-NaN value is within [-bound, bound] (False when all are NaN)."""
    return bool(np.fmin.reduce(values, axis=None) >= -bound and np.fmax.reduce(values, axis=None) <= bound)


def check_coordinates(latitude, longitude):
    """Broadcast latitude/longitude (degrees) to float arrays and check their range.

    NaN is allowed (it yields NaN); a finite latitude outside [-90, 90], an infinite
    value or a longitude beyond ±:data:`~geoidspline.sphere.region.MAX_ABS_POINT_LONGITUDE_DEG`
    (no real coordinate; wrapping 1e308 would give a plausible number) is a
    :class:`CoordinateError`. Other longitudes are wrapped.
    """
    latitude, longitude = np.broadcast_arrays(
        np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float)
    )
    if latitude.size and _within(latitude, 90.0) and _within(longitude, MAX_ABS_POINT_LONGITUDE_DEG):
        return latitude, longitude  # the common case: four reductions, no temporary arrays
    with np.errstate(invalid="ignore"):
        bad_lat = np.abs(latitude) > 90.0
    if np.any(bad_lat):
        first = float(latitude[bad_lat].ravel()[0])
        raise CoordinateError(
            f"latitude must be within [-90, 90] degrees; got {first!r} "
            f"({int(np.count_nonzero(bad_lat))} value(s) out of range)"
        )
    if np.any(np.isinf(longitude)):
        raise CoordinateError("longitude must be finite (degrees)")
    with np.errstate(invalid="ignore"):
        far = np.abs(longitude) > MAX_ABS_POINT_LONGITUDE_DEG
    if np.any(far):
        raise CoordinateError(
            f"longitude must be within ±{MAX_ABS_POINT_LONGITUDE_DEG:g} degrees; got {float(longitude[far].ravel()[0])!r}")
    return latitude, longitude


def directions(latitude, longitude):
    """Unit vectors (..., 3) for latitude/longitude in degrees (no range check)."""
    latitude, longitude = np.broadcast_arrays(np.asarray(latitude, dtype=np.float64),
                                              np.asarray(longitude, dtype=np.float64))
    shape = latitude.shape
    lat = np.ascontiguousarray(latitude).ravel()
    lon = np.ascontiguousarray(longitude).ravel()
    if lat.size < COMPILED_FROM_POINTS:
        return unit_vectors(lat, lon).reshape(shape + (3,))
    from .._kernels.query import unit_vectors as compiled_unit_vectors

    out = np.empty((lat.size, 3))
    # one compiled, threaded pass instead of numpy's temporaries (a third of a query)
    compiled_unit_vectors(lat, lon, out)
    return out.reshape(shape + (3,))


def unit_vectors(latitude, longitude):
    """Directions (M, 3) (cos φ cos λ, cos φ sin λ, sin φ) of 1-D latitude/longitude (degrees)."""
    phi = np.radians(latitude)
    lam = np.radians(longitude)
    out = np.empty((phi.size, 3))
    cos_phi = np.cos(phi)
    np.multiply(cos_phi, np.cos(lam), out=out[:, 0])
    np.multiply(cos_phi, np.sin(lam), out=out[:, 1])
    np.sin(phi, out=out[:, 2])
    return out


def latlon_of(points):
    """Latitude and longitude (degrees) of the directions of ambient points (M, 3):
    the inverse of :func:`directions` for the radial projection ``x / |x|``."""
    points = np.asarray(points, dtype=np.float64)
    norm = np.linalg.norm(points, axis=-1)
    with np.errstate(invalid="ignore", divide="ignore"):
        latitude = np.degrees(np.arcsin(np.clip(points[..., 2] / norm, -1.0, 1.0)))
    longitude = np.degrees(np.arctan2(points[..., 1], points[..., 0]))
    return latitude, longitude
