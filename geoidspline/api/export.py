"""A store sampled on a latitude/longitude lattice, written as a grid PROJ, GDAL and xarray read."""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)
from .._files import fault_cause
from ..errors import CoordinateError, ExportError, GeoidSplineError, InputFileError
from ..options import check_number
from ..sphere.region import Region

#: Export formats by file suffix.
EXPORT_FORMATS = {".gtx": "PROJ GTX", ".nc": "CF netCDF-4", ".tif": "GeoTIFF", ".tiff": "GeoTIFF"}


_AXIS_TOL = 1e-9


_MAX_EXPORT_NODES = 200_000_000  # 0.8 GB of float32 in a GTX, 1.6 GB of doubles in memory


def _lattice_count(start, stop, step):
    return int(math.floor((stop - start) / step + _AXIS_TOL)) + 1


def _lattice(start, stop, step):
    """start, start + step, ... up to stop (inclusive within 1e-9°)."""
    return start + step * np.arange(_lattice_count(start, stop, step))


def export_lattice(store, spacing_deg, region=None):
    """The export lattice: (latitude, longitude) axes in degrees and the region used.

    Latitudes from the region's south edge northward and longitudes from its west edge
    eastward in steps of ``spacing_deg``, up to the last node at or before the north/east
    edge. For a region spanning all longitudes the column at west + 360° is left out
    (the grid is periodic). The region defaults to the store's and must lie inside it.
    """
    spacing = check_number("spacing_deg", spacing_deg)
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
    rows, columns = _lattice_count(region.south, region.north, spacing), _lattice_count(west, east, spacing)
    if rows * columns > 2 * _MAX_EXPORT_NODES:  # refused before allocating; the exact count is below
        raise CoordinateError(
            f"spacing {spacing:g} degrees gives about {rows} x {columns} nodes, more than "
            f"{_MAX_EXPORT_NODES:,}: use a coarser spacing or a smaller region"
        )
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


def export_grid(store, path, spacing_deg, region=None, tide_system=None):
    """Evaluate ``store`` on a latitude/longitude lattice and write it to ``path``.

    ``tide_system`` (default: the store's own) converts the values to another tide
    system (:func:`geoidspline.sources.reference.tide_offset_m`); the file then states it.

    The lattice is :func:`export_lattice` (every ``spacing_deg`` degrees from the south
    and west edges of ``region``, default the store's region). The format follows the
    suffix:

    - ``.gtx``: PROJ GTX (float32 metres, :func:`geoidspline.sources.gtx.write_gtx`), usable
      with ``+proj=vgridshift`` (PROJ interpolates it bilinearly);
    - ``.nc``: CF netCDF-4, ``geoid_height(latitude, longitude)`` in metres
      (:func:`geoidspline.sources.netcdf.write_netcdf`);
    - ``.tif``/``.tiff``: PROJ's GeoTIFF grid profile (float32, EPSG:4979, pixel is
      point, one pixel per node, north row first; :func:`geoidspline.sources.geotiff.write_geotiff`),
      usable with ``+proj=vgridshift``; written with ``rasterio``, which must be
      installed (the optional extra ``geotiff``).

    Nodes outside the store's coverage (where its source had no data) are written as
    no data (GTX: -88.8888, netCDF and GeoTIFF: NaN); a lattice with no covered node is
    refused. Returns the :class:`~geoidspline.sources.grid.GeoidGrid` that was written.
    """
    from ..sources.base import Provenance
    from ..sources.grid import GeoidGrid
    from ..sources.gtx import write_gtx
    from ..sources.netcdf import write_netcdf

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
    from ..geodesy.tides import tide_conversion, tide_offset_m

    prov = store.manifest.get("provenance", {})
    conversion = tide_conversion(prov.get("tide_system"), tide_system, store.path)
    latitude, longitude, used = export_lattice(store, spacing_deg, region)
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    values, covered = _covered_values(store, lat2, lon2, used)
    if not covered.any():
        raise CoordinateError(
            f"export region {used.as_tuple()} (S W N E degrees) holds no node inside the store's coverage"
        )
    if not covered.all():
        log.warning("%s: %d of %d nodes lie where the store has no data; written as no data",
                    path, int((~covered).sum()), covered.size)
    notes = (
        f"sampled from geoidspline store {store.path} (version {store.manifest.get('store_version')}) "
        f"every {float(spacing_deg):g} degrees over S W N E {used.as_tuple()}",
    )
    if conversion is not None:
        values = values + tide_offset_m(lat2, *conversion)
        notes += (f"converted from {conversion[0]} to {conversion[1]} (Ekman 1989; IERS 2010 §6.2.2)",)
    grid = GeoidGrid(
        latitude, longitude, values,
        Provenance(
            source=f"geoidspline store {Path(store.path).name}",
            sha256=prov.get("sha256"),
            model=prov.get("model", "unknown"),
            kind="grid",
            ellipsoid=prov.get("ellipsoid", "WGS84"),
            tide_system=conversion[1] if conversion else prov.get("tide_system"),
            zero_degree_term_m=prov.get("zero_degree_term_m"),
            datum=prov.get("datum"),
            quantity=prov.get("quantity") or "geoid",
            notes=notes,
        ),
    )
    if suffix == ".gtx":
        finite = values[np.isfinite(values)]
        if finite.size and np.abs(finite).max() >= 1000.0:
            log.warning("%s: values beyond ±1000 m, which PROJ treats as no data in GTX grids", path)
    writer = {".gtx": write_gtx, ".nc": write_netcdf}.get(suffix, _write_geotiff)
    try:
        writer(path, grid)  # atomic: the partial file is removed on a fault
    except (OSError, RuntimeError) as exc:  # the cause behind it (geoidspline._files.write_fault)
        raise ExportError(f"{path}: cannot write the {EXPORT_FORMATS[suffix]} export: {fault_cause(exc)}; "
                          f"nothing was written there") from None
    return grid


def _covered_values(store, lat2, lon2, region):
    """The store's values at the lattice nodes and where it covers them (NaN elsewhere).

    A node on the region's edge may lie a rounding error (< 1e-9°) outside it: such a
    node is tested, and evaluated, 1e-9° inside instead, so edges are not lost as no data.
    """
    values = np.array(store.undulation(lat2, lon2), dtype=np.float64)
    covered = np.asarray(store.covers(lat2, lon2), dtype=bool) & np.isfinite(values)
    miss = ~covered
    if miss.any():
        centre_lat = 0.5 * (region.south + region.north)
        centre_lon = lon2.flat[0] + 0.5 * region.longitude_span
        lat_in = lat2[miss] + _AXIS_TOL * np.sign(centre_lat - lat2[miss])
        lon_in = lon2[miss] + (_AXIS_TOL * np.sign(centre_lon - lon2[miss]) if region.longitude_span < 360.0 else 0.0)
        inside = np.asarray(store.covers(lat_in, lon_in), dtype=bool)
        if inside.any():
            again = np.array(store.undulation(lat_in[inside], lon_in[inside]), dtype=np.float64).reshape(-1)
            rows, cols = np.nonzero(miss)
            values[rows[inside], cols[inside]] = again
            covered[rows[inside], cols[inside]] = np.isfinite(again)
    values[~covered] = np.nan
    return values, covered


def _write_geotiff(path: Path, grid):
    """PROJ's GeoTIFF grid profile (:func:`geoidspline.sources.geotiff.write_geotiff`)."""
    from ..sources.geotiff import write_geotiff

    write_geotiff(path, grid)
