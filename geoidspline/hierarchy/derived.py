"""Deflection of the vertical from the analytic gradient of any ambient spline.

Latitudes and longitudes are geodetic degrees (WGS84). Scalars give scalars, arrays
broadcast, NaN gives NaN, a finite latitude beyond ±90° raises
:class:`~geoidspline.errors.CoordinateError`. :func:`deflection` takes any object with
``evaluate_points(points (M, 3), nderiv)`` or one holding such a spline as ``.spline``
(a store): here, beside the spline it differentiates, so that a store and the query
layer both reach it going down (:mod:`geoidspline.query.derived` re-exports it).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from ..geodesy.ellipsoids import gaussian_mean_radius
from ..sphere.coordinates import check_coordinates, directions

#: Arcseconds in one radian (648000/π).
ARCSEC_PER_RADIAN = 648000.0 / math.pi


def _spline_of(store_or_spline):
    """The ambient spline of a store, or the argument itself when it is a spline."""
    spline = getattr(store_or_spline, "spline", None)
    if spline is not None and hasattr(spline, "evaluate_points"):
        return spline
    if hasattr(store_or_spline, "evaluate_points"):
        return store_or_spline
    raise TypeError(
        f"expected a TileStore or an ambient spline (with evaluate_points), got {type(store_or_spline).__name__}"
    )


def _shaped(values, shape):
    """Reshape a flat result to the query's shape; a 0-d query gives a NumPy scalar."""
    values = np.asarray(values, dtype=np.float64).reshape(shape)
    return values[()] if shape == () else values


class Deflection(NamedTuple):
    """Deflection of the vertical from the geoid slope, and that slope.

    ``xi_arcsec`` (ξ, north-south component) and ``eta_arcsec`` (η, east-west
    component) in arcseconds; ``dn_dnorth``/``dn_deast`` the geoid gradient
    ∂N/∂(distance north) and ∂N/∂(distance east) in metres per metre.
    ξ = −dN/dnorth and η = −dN/deast (in radians).
    """

    xi_arcsec: object
    eta_arcsec: object
    dn_dnorth: object
    dn_deast: object


def deflection(store_or_spline, latitude, longitude) -> Deflection:
    """Geoidal deflection of the vertical (ξ, η) and the geoid gradient at points.

    Computed from the analytic gradient g = ∇S of the ambient spline at the sphere point
    u = (cos φ cos λ, cos φ sin λ, sin φ) (no finite differences). Its tangent
    components along ê_north = (−sin φ cos λ, −sin φ sin λ, cos φ) = ∂u/∂φ and
    ê_east = (−sin λ, cos λ, 0) = (1/cos φ) ∂u/∂λ are the surface derivatives

        ∂N/∂φ = g·ê_north,   (1/cos φ) ∂N/∂λ = g·ê_east   (metres per radian);

    any radial component of g (the spline is only approximately constant along rays)
    is ignored, as the geoid is the restriction of S to the sphere.

    Distances use the WGS84 Gaussian mean radius of curvature R = √(M N) at φ
    (:func:`gaussian_mean_radius`), the usual spherical approximation: metres per metre
    are dN/dnorth = (∂N/∂φ)/R and dN/deast = (∂N/∂λ)/(R cos φ). (The strict ellipsoidal
    distances M dφ and N cos φ dλ would change these by at most 0.34 %.)

    Sign convention (Heiskanen & Moritz 1967, Physical Geodesy, ch. 2; Torge, Geodesy):

        ξ = −(1/R) ∂N/∂φ,   η = −(1/(R cos φ)) ∂N/∂λ,

    converted from radians to arcseconds. These are ξ = Φ − φ and η = (Λ − λ) cos φ
    (astronomic minus geodetic), positive when the astronomic zenith (the plumb line)
    lies north, respectively east, of the ellipsoidal one; a geoid rising to the north
    gives ξ < 0, one rising to the east η < 0.

    At the poles the tangent basis above stays finite: ê_north points along the meridian
    of the *given* longitude (over the pole) and ê_east 90° east of it, so ξ and η there
    are relative to the meridian of that longitude.

    Returns a :class:`Deflection` ``(xi_arcsec, eta_arcsec, dn_dnorth, dn_deast)``;
    scalars for scalar input, arrays of the broadcast shape otherwise; NaN in gives NaN.
    """
    spline = _spline_of(store_or_spline)
    lat, lon = check_coordinates(latitude, longitude)
    shape = lat.shape
    lat_f = lat.ravel()
    lon_f = lon.ravel()
    phi = np.radians(lat_f)
    lam = np.radians(lon_f)
    sin_phi, cos_phi = np.sin(phi), np.cos(phi)
    sin_lam, cos_lam = np.sin(lam), np.cos(lam)
    if lat_f.size:
        values = np.asarray(spline.evaluate_points(directions(lat_f, lon_f), nderiv=1), dtype=np.float64)
        g = values.reshape(-1, 4)[:, 1:4]
    else:
        g = np.zeros((0, 3))
    dn_dphi = g[:, 0] * (-sin_phi * cos_lam) + g[:, 1] * (-sin_phi * sin_lam) + g[:, 2] * cos_phi
    dn_dlam_cos = g[:, 0] * (-sin_lam) + g[:, 1] * cos_lam
    radius = gaussian_mean_radius(lat_f)
    dn_dnorth = dn_dphi / radius
    dn_deast = dn_dlam_cos / radius
    return Deflection(
        _shaped(-dn_dnorth * ARCSEC_PER_RADIAN, shape),
        _shaped(-dn_deast * ARCSEC_PER_RADIAN, shape),
        _shaped(dn_dnorth, shape),
        _shaped(dn_deast, shape),
    )
