"""Derived quantities of a tile store: the validated API behind ``geoid-query`` options.

Everything here takes a store (:class:`geoidspline.store.TileStore`) or, where only the
spline is needed, any object with the ambient-spline method
``evaluate_points(points (M, 3), nderiv)`` (an :class:`~geoidspline.spline.AmbientSpline`).
Latitudes and longitudes are geodetic degrees (WGS84), heights and undulations metres.
Scalars give scalars, arrays broadcast, NaN gives NaN, a finite latitude beyond ±90°
raises :class:`~geoidspline.errors.CoordinateError`.

- :func:`deflection`: deflection of the vertical (ξ, η) in arcseconds and the geoid
  gradient in metres per metre, from the analytic gradient of the spline;
- :func:`tile_error_bound`: the largest check-point error of the tile a point is in;
- :func:`to_geodetic`: coordinates in any geographic, geocentric or projected CRS to
  WGS84 latitude, longitude and ellipsoidal height (PROJ, through pyproj);
- :func:`convert_height`: ellipsoidal h ↔ orthometric H with H = h − N;
- :func:`export_grid`: the store sampled on a latitude/longitude lattice as a PROJ GTX,
  CF netCDF or GeoTIFF file;
- :func:`load_synthesis`, :func:`default_preset`, :func:`check_against`: exact
  spherical-harmonic synthesis for ``geoid-query --model`` and ``geoid-info
  --check-against``.
"""

from __future__ import annotations

import functools
import inspect
import logging
import math
import re
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .constants import WGS84
from .errors import CoordinateError, GeoidSplineError, InputFileError
from .region import Region
from .spline import check_coordinates, directions

__all__ = [
    "Deflection",
    "ARCSEC_PER_RADIAN",
    "gaussian_mean_radius",
    "deflection",
    "tile_error_bound",
    "to_geodetic",
    "crs_info",
    "convert_height",
    "HEIGHT_KINDS",
    "export_grid",
    "export_lattice",
    "EXPORT_FORMATS",
    "default_preset",
    "load_synthesis",
    "store_preset",
    "check_against",
    "CHECK_SEED",
]

log = logging.getLogger(__name__)

#: Arcseconds in one radian (648000/π).
ARCSEC_PER_RADIAN = 648000.0 / math.pi


# ------------------------------------------------------------------------ helpers


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


def gaussian_mean_radius(latitude, ellipsoid=WGS84):
    """Gaussian mean radius of curvature √(M N) (metres) at geodetic latitude (degrees).

    M = a(1 − e²)/W³ (meridian) and N = a/W (prime vertical), W = √(1 − e² sin²φ), so
    √(M N) = a √(1 − e²) / W². On WGS84 it runs from 6,356,752 m (= b, at the equator)
    to 6,399,594 m (= a²/b, at the poles).
    """
    phi = np.radians(np.asarray(latitude, dtype=np.float64))
    e2 = ellipsoid.e2
    w2 = 1.0 - e2 * np.sin(phi) ** 2
    return ellipsoid.a * math.sqrt(1.0 - e2) / w2


# ------------------------------------------------------------------------ deflection


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


# ------------------------------------------------------------------------ tile errors

_TILE_OFFSET = 1 << 20


def _tile_codes(tiles):
    """One int64 per integer tile triple (M, 3) (|index| < 2**20)."""
    tiles = np.asarray(tiles, dtype=np.int64).reshape(-1, 3)
    shifted = tiles + _TILE_OFFSET
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


@functools.lru_cache(maxsize=8)
def _tile_table_cached(key):
    tiles, errors = key
    codes = _tile_codes(np.array(tiles, dtype=np.int64).reshape(-1, 3))
    order = np.argsort(codes)
    return codes[order], np.array(errors, dtype=np.float64)[order]


def _tile_table(manifest):
    tiles = []
    errors = []
    for entry in manifest["tiles"]:
        tiles.extend(int(v) for v in entry["tile"])
        value = entry.get("max_error_m")
        errors.append(np.nan if value is None else float(value))
    return _tile_table_cached((tuple(tiles), tuple(errors)))


def tile_error_bound(store, latitude, longitude):
    """The ``max_error_m`` of the tile each point falls in (metres).

    A sphere point u belongs to the tile cube floor(u / tile_size) (the grouping the
    store used for its check points). The value is the largest |store − truth| at the
    check points of that tile when the store was written: an empirical bound, not a
    guaranteed one. NaN for a point in no tile of the store, in a tile without check
    points, outside the region the store was fitted for (the tile statistics say nothing
    there), or for a NaN coordinate.
    """
    lat, lon = check_coordinates(latitude, longitude)
    shape = lat.shape
    lat_f, lon_f = lat.ravel(), lon.ravel()
    result = np.full(lat_f.shape, np.nan)
    ok = np.isfinite(lat_f) & np.isfinite(lon_f)
    if ok.any():
        size = float(store.manifest["spline"]["tile_size"])
        codes, errors = _tile_table(store.manifest)
        tiles = np.floor(directions(lat_f[ok], lon_f[ok]) / size).astype(np.int64)
        query = _tile_codes(tiles)
        pos = np.searchsorted(codes, query)
        pos_c = np.minimum(pos, max(codes.size - 1, 0))
        found = (pos < codes.size) & (codes[pos_c] == query) if codes.size else np.zeros(query.shape, bool)
        values = np.where(found, errors[pos_c] if codes.size else np.nan, np.nan)
        inside = Region(*store.manifest["region"]).contains(lat_f[ok], lon_f[ok])
        result[ok] = np.where(inside, values, np.nan)
    return _shaped(result, shape)


# ------------------------------------------------------------------------ CRS


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
            "and pass the height with --height-in"
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
    beyond ±90°) give NaN. Longitudes come
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
        bad = ~(np.isfinite(lon) & np.isfinite(lat)) | (np.abs(lat) > 90.0)
    lon[bad] = np.nan
    lat[bad] = np.nan
    h[bad | ~np.isfinite(h)] = np.nan
    lon = np.where(np.abs(lon) > 180.0, (lon + 180.0) % 360.0 - 180.0, lon)
    return _shaped(lat, shape), _shaped(lon, shape), _shaped(h, shape)


# ------------------------------------------------------------------------ heights

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


# ------------------------------------------------------------------------ export

#: Export formats by file suffix.
EXPORT_FORMATS = {".gtx": "PROJ GTX", ".nc": "CF netCDF-4", ".tif": "GeoTIFF", ".tiff": "GeoTIFF"}
_AXIS_TOL = 1e-9
_MAX_EXPORT_NODES = 200_000_000  # 0.8 GB of float32 in a GTX, 1.6 GB of doubles in memory


def _lattice(start, stop, step):
    """start, start + step, ... up to stop (inclusive within 1e-9°)."""
    count = int(math.floor((stop - start) / step + _AXIS_TOL)) + 1
    return start + step * np.arange(count)


def export_lattice(store, spacing_deg, region=None):
    """The export lattice: (latitude, longitude) axes in degrees and the region used.

    Latitudes from the region's south edge northward and longitudes from its west edge
    eastward in steps of ``spacing_deg``, up to the last node at or before the north/east
    edge. For a region spanning all longitudes the column at west + 360° is left out
    (the grid is periodic). The region defaults to the store's and must lie inside it.
    """
    spacing = float(spacing_deg)
    if not (math.isfinite(spacing) and spacing > 0):
        raise CoordinateError(f"spacing must be a positive number of degrees, got {spacing_deg}")
    store_region = Region(*store.manifest["region"])
    if region is None:
        region = store_region
    elif not isinstance(region, Region):
        region = Region.from_bounds(*region)
    if region.south < store_region.south - _AXIS_TOL or region.north > store_region.north + _AXIS_TOL:
        raise CoordinateError(
            f"export region {region.as_tuple()} is not inside the store's region "
            f"{store_region.as_tuple()} (S W N E degrees): outside it the store has no meaningful values"
        )
    west = region.west
    if store_region.longitude_span < 360.0:
        # the requested region on the store's longitude branch, then inside its band
        offset = (region.west - store_region.west) % 360.0
        if offset > 360.0 - _AXIS_TOL:
            offset -= 360.0
        west = store_region.west + offset
        if west + region.longitude_span > store_region.east + _AXIS_TOL:
            raise CoordinateError(
                f"export region {region.as_tuple()} is not inside the store's region "
                f"{store_region.as_tuple()} (S W N E degrees): outside it the store has no meaningful values"
            )
    east = west + region.longitude_span
    latitude = _lattice(region.south, region.north, spacing)
    longitude = _lattice(west, east, spacing)
    if region.longitude_span >= 360.0:
        longitude = longitude[longitude < west + 360.0 - _AXIS_TOL]
        if abs(spacing * longitude.size - 360.0) > 1e-9:
            raise CoordinateError(
                f"a grid all around the globe needs a spacing that divides 360 degrees, got {spacing:g}"
            )
    latitude = np.clip(latitude, -90.0, 90.0)
    if latitude.size * longitude.size > _MAX_EXPORT_NODES:
        raise CoordinateError(
            f"spacing {spacing:g} degrees gives {latitude.size} x {longitude.size} nodes, more than "
            f"{_MAX_EXPORT_NODES:,}: use a coarser spacing or a smaller region"
        )
    if latitude.size < 2 or longitude.size < 2:
        raise CoordinateError(
            f"spacing {spacing:g} degrees gives {latitude.size} x {longitude.size} nodes over "
            f"{region.as_tuple()}: a grid needs at least 2 x 2"
        )
    return latitude, longitude, region


def export_grid(store, path, spacing_deg, region=None):
    """Evaluate ``store`` on a latitude/longitude lattice and write it to ``path``.

    The lattice is :func:`export_lattice` (every ``spacing_deg`` degrees from the south
    and west edges of ``region``, default the store's region). The format follows the
    suffix:

    - ``.gtx``: PROJ GTX (float32 metres, :func:`geoidspline.readers.write_gtx`), usable
      with ``+proj=vgridshift`` (PROJ interpolates it bilinearly);
    - ``.nc``: CF netCDF-4, ``geoid_height(latitude, longitude)`` in metres
      (:func:`geoidspline.readers.write_netcdf`);
    - ``.tif``/``.tiff``: a float32 GeoTIFF in EPSG:4326 with pixel-is-point
      georeferencing (one pixel per node, north row first), written with ``rasterio``,
      which must be installed (it is not a dependency of geoidspline).

    Returns the :class:`~geoidspline.grid.GeoidGrid` that was written.
    """
    from .grid import GeoidGrid
    from .readers import write_gtx, write_netcdf
    from .sources import Provenance

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise InputFileError(
            path, f"unknown export format '{path.suffix}': use .gtx (PROJ GTX), .nc (netCDF) or .tif (GeoTIFF)"
        )
    if suffix in (".tif", ".tiff"):
        try:
            import rasterio  # noqa: F401
        except ImportError:
            raise GeoidSplineError(
                "writing GeoTIFF needs the rasterio package, which is not installed: "
                "pip install rasterio (or export .gtx or .nc instead)"
            ) from None
    if not path.parent.is_dir():
        raise InputFileError(path, "the output directory does not exist")
    latitude, longitude, used = export_lattice(store, spacing_deg, region)
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    values = store.undulation(lat2, lon2)
    prov = store.manifest.get("provenance", {})
    notes = (
        f"sampled from geoidspline store {store.path} (version {store.manifest.get('store_version')}) "
        f"every {float(spacing_deg):g} degrees over S W N E {used.as_tuple()}",
    )
    grid = GeoidGrid(
        latitude, longitude, values,
        Provenance(
            source=f"geoidspline store {Path(store.path).name}",
            sha256=prov.get("sha256"),
            model=prov.get("model", "unknown"),
            kind="grid",
            ellipsoid=prov.get("ellipsoid", "WGS84"),
            tide_system=prov.get("tide_system"),
            zero_degree_term_m=prov.get("zero_degree_term_m"),
            notes=notes,
        ),
    )
    if suffix == ".gtx":
        finite = values[np.isfinite(values)]
        if finite.size and np.abs(finite).max() >= 1000.0:
            log.warning("%s: values beyond ±1000 m, which PROJ treats as no data in GTX grids", path)
        write_gtx(path, grid)
    elif suffix == ".nc":
        write_netcdf(path, grid)
    else:
        _write_geotiff(path, grid)
    return grid


def _write_geotiff(path: Path, grid):
    import os
    import tempfile

    import rasterio
    from rasterio.transform import from_origin

    lat, lon = grid.latitude, grid.longitude
    dlat, dlon = grid.latitude_spacing, grid.longitude_spacing
    data = np.asarray(grid.values[::-1], dtype=np.float32)  # north row first
    # Pixel-is-point: node (row 0, col 0) at (west, north); the affine transform gives the
    # outer corner of that pixel, half a cell beyond the node, as GDAL expects.
    transform = from_origin(lon[0] - dlon / 2.0, lat[-1] + dlat / 2.0, dlon, dlat)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp.tif")
    os.close(fd)
    try:
        with rasterio.open(
            tmp, "w", driver="GTiff", width=data.shape[1], height=data.shape[0], count=1,
            dtype="float32", crs="EPSG:4326", transform=transform, nodata=float("nan"),
            compress="deflate",
        ) as ds:
            ds.write(data, 1)
            ds.update_tags(AREA_OR_POINT="Point")
            ds.update_tags(1, units="m", long_name="geoid undulation N above the WGS84 ellipsoid")
            ds.set_band_description(1, "geoid_undulation")
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# ------------------------------------------------------------------------ models

#: Seed of the random check points of :func:`check_against` (the fit's own check
#: points use seed 0, see :func:`geoidspline.build.check_points`).
CHECK_SEED = 1


def _library_default_preset():
    from .harmonics import GeoidSynthesis

    return inspect.signature(GeoidSynthesis).parameters["preset"].default


def default_preset(model, correction=None) -> str:
    """The preset used when none is given.

    NGA's EGM2008 (model name starting with "EGM2008") gets ``nga-hsynth`` (NGA's
    hsynth_WGS84, N0 = −0.41 m); everything else, in particular EGM96 and any model
    given with a ζ-to-N correction, gets geoidspline.harmonics' default, ``nga-f477``
    (NGA's F477, N0 = −0.53 m). A non-NGA model is better run with an explicit
    ``preset="generic"``.
    """
    name = (getattr(model, "name", "") or "").upper()
    if correction is None and name.startswith("EGM2008"):
        return "nga-hsynth"
    return _library_default_preset()


def store_preset(store, model=None):
    """The synthesis preset a store was fitted with, from its provenance notes, or None.

    With ``model`` given, only when the store was fitted from that very model file
    (same sha256); a store fitted from a grid has none.
    """
    prov = store.manifest.get("provenance", {}) or {}
    if prov.get("kind") != "harmonic":
        return None
    if model is not None and (not prov.get("sha256") or prov.get("sha256") != getattr(model, "sha256", None)):
        return None
    from .harmonics import PRESETS

    for note in prov.get("notes", ()) or ():
        match = re.match(r"preset ([\w-]+):", str(note))
        if match and match.group(1) in PRESETS:
            return match.group(1)
    return None


def load_synthesis(model_path, correction_path=None, preset=None, like_store=None):
    """Read a model (ICGEM .gfc or NGA ASCII) and optional CORRCOEF-style correction
    and return the :class:`~geoidspline.harmonics.GeoidSynthesis`.

    ``preset`` None means: the preset ``like_store`` was fitted with when that store was
    fitted from this same model file (:func:`store_preset`), else :func:`default_preset`.
    """
    from .harmonics import PRESETS, GeoidSynthesis, read_model, read_nga_correction

    if preset is not None and preset not in PRESETS:
        raise GeoidSplineError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
    for label, value in (("model", model_path), ("correction", correction_path)):
        if value is not None and not Path(value).is_file():
            raise InputFileError(value, f"{label} file not found" if not Path(value).exists() else "not a regular file")
    model = read_model(model_path)
    correction = read_nga_correction(correction_path) if correction_path is not None else None
    chosen = preset
    if chosen is None and like_store is not None:
        chosen = store_preset(like_store, model)
    if chosen is None:
        chosen = default_preset(model, correction)
    try:
        return GeoidSynthesis(model, correction, preset=chosen)
    except ValueError as exc:
        raise GeoidSplineError(f"{model_path}: {exc}") from None


def check_against(store, synthesis, points=20_000, seed=CHECK_SEED) -> dict:
    """|store − exact synthesis| at ``points`` random points of the store's region.

    The points are uniform in area over the store's region
    (:func:`geoidspline.build.check_points`, seed ``seed``); they are random, so not the
    fit's lattice nodes, and a different seed from the store's own check points.
    Returns a dict with ``points``, ``seed``, ``max_error_m``, ``rms_error_m``,
    ``p99_error_m``, ``mean_error_m`` (store − model), the point of the largest error and
    what was compared.
    """
    from .build import check_points

    points = int(points)
    if points < 1:
        raise GeoidSplineError(f"--points must be at least 1, got {points}")
    region = Region(*store.manifest["region"])
    check = check_points(synthesis, region, count=points, seed=seed)
    errors = store.undulation(check.latitude, check.longitude) - check.truth
    absolute = np.abs(errors)
    worst = int(np.argmax(absolute))
    prov = store.manifest.get("provenance", {})
    model = synthesis.model
    correction = synthesis.correction
    same_source = bool(prov.get("sha256")) and prov.get("sha256") == model.sha256
    return {
        "model": str(model.source_path or model.name),
        "model_name": model.name,
        "model_sha256": model.sha256,
        "correction": None if correction is None else str(correction.source_path or correction.name),
        "preset": synthesis.preset,
        "max_degree": synthesis.max_degree,
        "zero_degree_term_m": synthesis.zero_degree_term_m,
        "store_source_sha256": prov.get("sha256"),
        "same_source": same_source,
        "region": list(region.as_tuple()),
        "points": points,
        "seed": seed,
        "sampling": check.description,
        "max_error_m": float(absolute.max()),
        "rms_error_m": float(np.sqrt(np.mean(errors**2))),
        "p99_error_m": float(np.percentile(absolute, 99)),
        "mean_error_m": float(np.mean(errors)),
        "worst_point": [float(check.latitude[worst]), float(check.longitude[worst])],
        "units": "m",
    }
