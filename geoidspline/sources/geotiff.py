"""PROJ's GeoTIFF grids (the Geodetic TIFF Grid profile, GTG), read and written with rasterio.

PROJ distributes its geoid models in this profile (e.g. ``us_nga_egm96_15.tif``): one
float32 band of geoid undulations in metres, ``TYPE=VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL``
and band description ``geoid_undulation`` in the GDAL metadata, a geographic CRS in the
GeoKeys (EPSG:4326, or EPSG:4979 written as GeoTIFF 1.1), a ``GDAL_NODATA`` value,
deflate compression with the floating-point predictor, 256 x 256 tiles (one strip for a
small grid), north row first.

*Pixel is point or area.* PROJ takes a PixelIsPoint file's tie point as a node, and a
PixelIsArea file's nodes at the pixel centres, half a pixel inside. GDAL (and so
rasterio) reports both as the same area-based transform, so a node is always the centre
of its pixel here; the reader notes which convention the file declared.

rasterio ships GDAL in its wheels; it is the optional extra ``geotiff``
(``pip install 'geoidspline[geotiff]'``). Without it, reading or writing a GeoTIFF is an
:class:`~geoidspline.errors.InputFileError` saying so.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._files import atomic_path
from ..errors import GeoidSplineError, InputFileError
from .files import finish_grid, provenance_of
from .reference import crs_datum
from .grid import GeoidGrid

__all__ = ["GEOTIFF_NODATA", "GTG_TYPE", "looks_like_geotiff", "read_geotiff", "write_geotiff"]

#: The no-data value :func:`write_geotiff` writes: finite, as GTG asks, and exact in float32.
GEOTIFF_NODATA = -32768.0
#: GTG's grid type of a geoid model (geographic CRS to vertical CRS).
GTG_TYPE = "VERTICAL_OFFSET_GEOGRAPHIC_TO_VERTICAL"

_MAGIC = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")  # TIFF and BigTIFF, both byte orders
_METRE_UNITS = {"", "metre", "metres", "meter", "meters", "m"}
_INSTALL = "pip install 'geoidspline[geotiff]' (or: pip install rasterio)"
# Vertical CRS of the global models, for GTG's target_crs_epsg_code.
_VERTICAL_EPSG = {"EGM84": 5798, "EGM96": 5773, "EGM2008": 3855}
_PROVENANCE_TAGS = ("model", "tide_system", "zero_degree_term_m")
#: Band descriptions and tags that say the values are height anomalies.
_QUASI = ("quasi-geoid", "quasi_geoid", "quasigeoid", "height_anomaly", "height anomaly", "zeta")
#: Largest raster read (2.5e8 nodes, 2 GB as float64; a global 1' grid has 2.3e8),
#: checked before allocating.
MAX_RASTER_NODES = 250_000_000


def looks_like_geotiff(head: bytes) -> bool:
    """Whether a file's first bytes are a TIFF's (``II*\\0``/``MM\\0*``, BigTIFF ``+``)."""
    return head[:4] in _MAGIC


def _rasterio(path, doing: str):
    try:
        import rasterio
    except ImportError:
        raise InputFileError(path, f"{doing} a GeoTIFF needs the rasterio package, which is not installed: {_INSTALL}") from None
    return rasterio


# -- reader --------------------------------------------------------------------------
def _axis(start: float, step: float, count: int, period: float) -> np.ndarray:
    """Nodes ``start + step * k``, with the round-off of GDAL's half-pixel shifts removed
    (spacing snapped to period/k, first node to a multiple of half the spacing, each only
    when within 1e-12 relative / 1e-11 degrees: a few units in the last place)."""
    turns = round(period / step)
    if turns > 0 and abs(period / turns - step) <= 1e-12 * step:
        step = period / turns
    half = step / 2.0
    snapped = round(start / half) * half
    if abs(snapped - start) <= 1e-11:
        start = snapped
    return start + step * np.arange(count)


def read_geotiff(path, sha256: str, complete: bool = False, band: int | None = None) -> GeoidGrid:
    """Read a GeoTIFF geoid grid (one band, metres) into a :class:`GeoidGrid`.

    A file of one band needs no ``band``; a file of several is refused unless ``band``
    (1-based) names one, the message listing the bands with their descriptions. The
    file's CRS (GeoKeys/WKT) becomes the provenance's ``datum`` and ``ellipsoid``.

    Checks: a plain GeoTIFF (not several subgrids), a geographic CRS in degrees, no
    rotation, a GTG ``TYPE`` (when present) of a geoid model, units metres (or none),
    a supported data type (float or 16/32-bit integers with scale/offset). Nodes equal
    to the nodata value, or NaN, become NaN. Errors are :class:`InputFileError`
    naming ``path`` and the rule broken.
    """
    try:
        return _read_geotiff(Path(path), sha256, complete, band)
    except (GeoidSplineError, MemoryError, OSError):
        raise
    except Exception as exc:  # rasterio/GDAL on a damaged file, e.g. UnicodeDecodeError in a tag
        raise InputFileError(path, f"cannot be read as GeoTIFF: {type(exc).__name__}: {exc}") from None


def _pick_band(path, ds, band: int | None) -> int:
    """The 1-based band to read: the only one, or the one asked for."""
    count = ds.count
    listing = ", ".join(f"{i}" + (f" '{d}'" if d else "") for i, d in enumerate(ds.descriptions, start=1))
    if band is None:
        if count == 1:
            return 1
        raise InputFileError(path, f"GeoTIFF has {count} bands ({listing}): name the one holding the undulations "
                             "with --band N (band=N)")
    if not 1 <= band <= count:
        raise InputFileError(path, f"--band {band} is not a band of this GeoTIFF; its bands are {listing}")
    return band


def _read_geotiff(path: Path, sha256: str, complete: bool, band: int | None = None) -> GeoidGrid:
    rasterio = _rasterio(path, "reading")
    from rasterio.errors import RasterioError

    try:
        ds = rasterio.open(path)
    except RasterioError as exc:
        raise InputFileError(path, f"cannot be read as GeoTIFF: {exc}") from None
    with ds:
        if ds.driver != "GTiff":
            raise InputFileError(path, f"not a GeoTIFF (GDAL opened it as {ds.driver})")
        if ds.subdatasets:
            raise InputFileError(
                path, f"GeoTIFF holds {len(ds.subdatasets) + 1} grids (subgrids); geoidspline reads single-grid files"
            )
        if ds.crs is None:
            raise InputFileError(path, "GeoTIFF has no coordinate reference system (GeoKeys); cannot place its nodes")
        if not ds.crs.is_geographic:
            raise InputFileError(
                path, f"GeoTIFF CRS {ds.crs.to_string()} is projected; a geoid grid must be in geographic "
                "latitude/longitude (GTG uses EPSG:4326 or EPSG:4979)"
            )
        unit_name, _ = ds.crs.units_factor
        if unit_name.lower() not in ("degree", "degrees"):
            raise InputFileError(path, f"GeoTIFF CRS angles are in '{unit_name}', need degrees")
        transform = ds.transform
        if transform.b != 0.0 or transform.d != 0.0:
            raise InputFileError(path, f"GeoTIFF is rotated or sheared (transform {tuple(transform)[:6]})")
        if not (transform.a > 0 and transform.e != 0):
            raise InputFileError(path, f"GeoTIFF pixel size ({transform.a}, {transform.e}) is not usable")
        tags = ds.tags()
        grid_type = tags.get("TYPE")
        if grid_type is not None and grid_type != GTG_TYPE:
            raise InputFileError(
                path, f"GeoTIFF grid TYPE is {grid_type}; a geoid model is {GTG_TYPE} (geoid undulations)"
            )
        index = _pick_band(path, ds, band)
        b = index - 1
        unit = (ds.units[b] or "").strip()
        if unit.lower() not in _METRE_UNITS:
            raise InputFileError(path, f"GeoTIFF band {index} unit is '{unit}'; geoid undulations must be in metres "
                                 "(metre)")
        dtype = np.dtype(ds.dtypes[b])
        if dtype.kind not in "fiu" or dtype.itemsize > 8:
            raise InputFileError(path, f"GeoTIFF band {index} has data type {dtype}; expected float32/64 or integers")
        if ds.width * ds.height > MAX_RASTER_NODES:
            raise InputFileError(
                path, f"GeoTIFF declares {ds.height} x {ds.width} nodes, more than {MAX_RASTER_NODES:,}"
            )
        raw = ds.read(index)
        nodata = ds.nodatavals[b]
        scale, offset = ds.scales[b], ds.offsets[b]
        pixel_is = tags.get("AREA_OR_POINT", "Area")
        description = ds.descriptions[b]
        band_tags = ds.tags(index)
        crs_wkt = ds.crs.to_wkt()
        rows, cols = ds.height, ds.width
    values = raw.astype(np.float64)
    missing = np.isnan(values)
    if nodata is not None:
        missing |= np.isnan(values) if np.isnan(nodata) else (raw == np.asarray(nodata).astype(raw.dtype))
    if np.isinf(values).any():
        raise InputFileError(path, f"GeoTIFF band {index} has {int(np.isinf(values).sum())} infinite values")
    values = offset + scale * values
    values[missing] = np.nan
    # GDAL's transform is area-based for both conventions: node (i, j) is the centre of pixel (i, j).
    lon = _axis(transform.c + transform.a / 2.0, transform.a, cols, 360.0)
    if transform.e > 0:  # south row first
        lat = _axis(transform.f + transform.e / 2.0, transform.e, rows, 180.0)
    else:  # north row first (GTG): flip to ascending latitude
        lat = _axis(transform.f + transform.e * (rows - 0.5), -transform.e, rows, 180.0)
        values = values[::-1]
    notes = [f"GeoTIFF, pixel is {pixel_is.lower()} (nodes at pixel centres), band {index}"
             + (f" '{description}'" if description else "")]
    if grid_type is None:
        notes.append(f"no GTG TYPE in the metadata: band {index} read as geoid undulations")
    if dtype.kind != "f" or scale != 1.0 or offset != 0.0:
        notes.append(f"{dtype} values with scale {scale:g}, offset {offset:g}")
    known = {key: tags[key] for key in _PROVENANCE_TAGS if tags.get(key)}
    datum, ellipsoid_name = crs_datum(crs_wkt)
    quantity = _quantity(tags, band_tags, description)
    try:
        zero = float(known["zero_degree_term_m"]) if "zero_degree_term_m" in known else None
    except ValueError:
        zero = None
    tide = known.get("tide_system")
    prov = provenance_of(
        path, sha256,
        model=known.get("model"),
        ellipsoid=ellipsoid_name,
        datum=datum,
        quantity=quantity,
        tide_system=tide if tide in ("tide_free", "zero_tide", "mean_tide") else None,
        zero_degree_term_m=zero,
        notes=tuple(notes),
    )
    return finish_grid(path, lat, lon, values, prov, complete=complete)


def _quantity(tags: dict, band_tags: dict, description) -> str:
    """"quasi-geoid" when the metadata (a ``quantity``/``data_type`` tag, the band
    description) says height anomalies, else "geoid"."""
    said = [str(t.get(k, "")) for t in (tags, band_tags) for k in ("quantity", "data_type")] + [str(description or "")]
    return "quasi-geoid" if any(s.strip().lower() in _QUASI for s in said) else "geoid"


# -- writer --------------------------------------------------------------------------
def write_geotiff(path, grid: GeoidGrid, *, crs_epsg: int | str | None = None, pixel_is: str = "point",
                  nodata: float = GEOTIFF_NODATA, block_size: int = 256) -> Path:
    """Write ``grid`` as a PROJ GeoTIFF grid (GTG): float32 metres, deflate + predictor 3.

    ``crs_epsg`` is the geographic CRS of the nodes (an EPSG code or CRS text; default
    the grid's ``datum``, else 4979, WGS 84 3D, as GTG geoid models); ``pixel_is`` ``"point"`` (GTG's convention: the tie point is the
    north-west node) or ``"area"`` (the tie point is that node's cell corner). Grids of
    at least ``block_size`` nodes in a direction are tiled, smaller ones are one strip.
    NaN (no data) is written as ``nodata``. PROJ's ``vgridshift`` reads the file, e.g.
    ``+proj=vgridshift +grids=/abs/path.tif +multiplier=1``.
    """
    path = Path(path)
    if pixel_is not in ("point", "area"):
        raise ValueError(f"pixel_is must be 'point' or 'area', got {pixel_is!r}")
    rasterio = _rasterio(path, "writing")
    if crs_epsg is None:
        crs_epsg = grid.provenance.datum or 4979
    from rasterio.crs import CRS
    from rasterio.errors import RasterioError
    from rasterio.transform import Affine

    rows, cols = grid.shape
    dlat, dlon = grid.latitude_spacing, grid.longitude_spacing
    data = np.where(np.isnan(grid.values), nodata, grid.values)[::-1].astype(np.float32)  # north row first
    # The area-based transform GDAL expects: the outer corner of the north-west node's pixel.
    transform = Affine(dlon, 0.0, grid.longitude[0] - dlon / 2.0, 0.0, -dlat, grid.latitude[-1] + dlat / 2.0)
    profile = dict(
        driver="GTiff", width=cols, height=rows, count=1, dtype="float32",
        crs=CRS.from_epsg(crs_epsg) if isinstance(crs_epsg, int) else CRS.from_user_input(crs_epsg),
        # the file states the nodes' datum: the grid's own when it has one, else WGS 84 3D (GTG's)
        transform=transform, nodata=nodata, compress="deflate", predictor=3, interleave="band",
        photometric="minisblack", geotiff_version="1.1",
    )
    if rows >= block_size or cols >= block_size:
        profile.update(tiled=True, blockxsize=block_size, blockysize=block_size)
    else:
        profile.update(blockysize=rows)  # one strip
    prov = grid.provenance
    tags = dict(TYPE=GTG_TYPE, AREA_OR_POINT="Point" if pixel_is == "point" else "Area",
                source=prov.source, TIFFTAG_IMAGEDESCRIPTION=(
                    f"Geoid undulation N (metres) of {prov.model}, written by geoidspline from {prov.source}"))
    for key in _PROVENANCE_TAGS + ("quantity",):
        value = getattr(prov, key)
        if value is not None:
            tags[key] = str(value)
    if prov.sha256:
        tags["source_sha256"] = prov.sha256
    vertical = _VERTICAL_EPSG.get(str(prov.model).upper().replace(" ", ""))
    if vertical is not None:
        tags["target_crs_epsg_code"] = str(vertical)
    try:
        with atomic_path(path, suffix=".tmp.tif") as tmp:
            with rasterio.open(tmp, "w", **profile) as ds:
                ds.update_tags(**tags)  # before the data: GDAL writes the GeoKeys (PixelIsPoint) at close
                ds.set_band_description(1, "geoid_undulation")
                ds.set_band_unit(1, "metre")
                ds.write(data, 1)
            # GDAL reports a failed write at close (a full disk) on stderr only, and
            # returns: read the file back, so that an incomplete one is never renamed
            # into place as if it were the grid
            with rasterio.open(tmp) as written:
                complete = np.array_equal(written.read(1), data)
            if not complete:
                raise RuntimeError("GDAL wrote an incomplete file")
    except RasterioError as exc:
        if isinstance(exc, OSError):
            raise
        raise InputFileError(path, f"cannot write GeoTIFF: {exc}") from None
    return path
