"""Quantities derived from a store's spline: deflections, heights and error bounds.

Latitudes and longitudes are geodetic degrees (WGS84), heights and undulations metres.
Scalars give scalars, arrays broadcast, NaN gives NaN, a finite latitude beyond ±90°
raises :class:`~geoidspline.errors.CoordinateError`. The functions take a store
(:class:`geoidspline.store.TileStore`, whose methods call them) or, where only the spline
is needed, any object with ``evaluate_points(points (M, 3), nderiv)``.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np

from ..errors import CoordinateError
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


_TILE_OFFSET = 1 << 20

#: Safety factor of :func:`tile_error_bound` on the largest error measured near a point
#: (derivation and measurements: README, "--with-error"; benchmarks/README.md, "Error
#: bound").
ERROR_BOUND_FACTOR = 1.5


def _tile_codes(tiles):
    """One int64 per integer tile triple (M, 3) (|index| < 2**20)."""
    tiles = np.asarray(tiles, dtype=np.int64).reshape(-1, 3)
    shifted = tiles + _TILE_OFFSET
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def _figure(*values):
    """The largest of the per-tile figures that were measured (None: not measured)."""
    known = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return max(known) if known else math.nan


@functools.lru_cache(maxsize=8)
def _tile_table_cached(key):
    tiles, figures, excess = key
    codes = _tile_codes(np.array(tiles, dtype=np.int64).reshape(-1, 3))
    order = np.argsort(codes)
    return codes[order], np.array(figures, dtype=np.float64)[order], np.array(excess, dtype=np.float64)[order]


def _tile_table(manifest):
    """Sorted tile codes; each tile's largest measured error (the maximum of its
    check-point and node errors, NaN for a tile with neither); and by how much its
    check-point maximum exceeds its node maximum (0 when not, NaN when unknown)."""
    tiles = []
    figures = []
    excess = []
    for entry in manifest["tiles"]:
        tiles.extend(int(v) for v in entry["tile"])
        check, node = entry.get("max_error_m"), entry.get("node_max_error_m")
        figures.append(_figure(check, node))
        excess.append(max(0.0, float(check) - float(node)) if check is not None and node is not None else math.nan)
    return _tile_table_cached((tuple(tiles), tuple(figures), tuple(excess)))


def _store_figure(manifest):
    """The store's largest measured error (check points and nodes), metres."""
    acc = manifest.get("accuracy", {})
    return _figure(acc.get("max_error_m"), acc.get("node_max_error_m"))


def _store_excess(manifest):
    acc = manifest.get("accuracy", {})
    check, node = acc.get("max_error_m"), acc.get("node_max_error_m")
    return max(0.0, float(check) - float(node)) if check is not None and node is not None else 0.0


def _nearby(store, latitude, longitude):
    """(largest measured error, largest check-over-node excess) over the tiles within
    reach of each point; flat arrays, NaN for NaN coordinates (see
    :func:`nearby_measured_error`)."""
    lat, lon = check_coordinates(latitude, longitude)
    lat_f, lon_f = lat.ravel(), lon.ravel()
    figure = np.full(lat_f.shape, np.nan)
    excess = np.full(lat_f.shape, np.nan)
    ok = np.isfinite(lat_f) & np.isfinite(lon_f)
    if not ok.any():
        return lat.shape, figure, excess
    manifest = store.manifest
    meta = manifest["spline"]
    size = float(meta["tile_size"])
    coarsest = max([float(meta["h0"])] + [float(lv["h"]) for lv in meta.get("levels", ())])
    reach = int(meta["order"]) * coarsest / 2.0
    codes, figures, excesses = _tile_table(manifest)
    u = directions(lat_f[ok], lon_f[ok])
    lo = np.floor((u - reach) / size - 1e-9).astype(np.int64)
    hi = np.floor((u + reach) / size + 1e-9).astype(np.int64)
    span = int((hi - lo).max()) + 1
    best = np.full(u.shape[0], np.nan)
    most = np.full(u.shape[0], np.nan)
    if codes.size:
        for offset in np.ndindex(span, span, span):
            tile = lo + np.array(offset)
            query = _tile_codes(tile)
            pos = np.minimum(np.searchsorted(codes, query), codes.size - 1)
            found = np.all(tile <= hi, axis=1) & (codes[pos] == query)
            best = np.fmax(best, np.where(found, figures[pos], np.nan))
            most = np.fmax(most, np.where(found, excesses[pos], np.nan))
    best[np.isnan(best)] = _store_figure(manifest)
    most[np.isnan(most)] = _store_excess(manifest)
    figure[ok] = best
    excess[ok] = most
    return lat.shape, figure, excess


def nearby_measured_error(store, latitude, longitude):
    """The largest error measured when the store was written near each point (metres).

    The spline at a point depends only on the B-splines within ``reach = order · h0 / 2``
    of its direction u (per axis, h0 the coarsest spacing), and those were fitted to the
    data of the tiles meeting the cube ``u ± reach``. This is the largest per-tile
    figure (the maximum of the tile's check-point error ``max_error_m`` and node error
    ``node_max_error_m``) over those tiles; where none of them has figures (a tile
    rewritten by an update has node figures only; one holding coefficients only, none),
    the store's overall maximum. NaN for a NaN coordinate. Not restricted to the
    coverage: :func:`tile_error_bound` is.
    """
    shape, figure, _ = _nearby(store, latitude, longitude)
    return _shaped(figure, shape)


def grid_interpolation_uncertainty(store, latitude, longitude):
    """An estimate of how far the field a grid source samples may be from any smooth
    interpolation of its nodes, near each point (metres; 0 for a model source).

    A grid store's check points compare it with the grid's bicubic interpolation at the
    cell centres, the points farthest from the nodes. Where its check-point maximum
    exceeds its node maximum, the excess is how much two interpolants through the same
    nodes (within the fit's misfit) differ between them: the grid itself does not say
    which is right, so the field between the nodes is at least that uncertain. This is
    the largest such excess, ``max(0, max_error_m − node_max_error_m)``, over the tiles
    within reach of the point (as in :func:`nearby_measured_error`).
    """
    shape, _, excess = _nearby(store, latitude, longitude)
    if store.manifest.get("provenance", {}).get("kind") != "grid":
        excess = np.where(np.isnan(excess), np.nan, 0.0)
    return _shaped(excess, shape)


def tile_error_bound(store, latitude, longitude):
    """A bound on the store's error |N − truth| at each point (metres).

    ``ERROR_BOUND_FACTOR`` times the largest error measured near the point when the
    store was written (:func:`nearby_measured_error`: check points and data nodes of
    the tiles whose data fitted the B-splines non-zero at the point), plus for a grid
    source the grid's own interpolation uncertainty there
    (:func:`grid_interpolation_uncertainty`). The truth is the source: the exact
    synthesis of a model; for a grid its nodes and its interpolation between them.
    Measured on real stores, the bound held at more than 99.9 % of random points inside
    the coverage (README, "--with-error", has the derivation; benchmarks/README.md the
    measurements); it is a statistical bound, not a proof.

    NaN for a point outside the store's coverage (nothing was measured there: see
    :meth:`~geoidspline.store.TileStore.covers`) and for a NaN coordinate.
    """
    shape, figure, excess = _nearby(store, latitude, longitude)
    if store.manifest.get("provenance", {}).get("kind") != "grid":
        excess = np.zeros_like(excess)
    covered = np.asarray(store.covers(latitude, longitude), dtype=bool).reshape(-1)
    bound = np.where(covered, ERROR_BOUND_FACTOR * figure + excess, np.nan)
    return _shaped(bound, shape)


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
