"""CF netCDF grids: read (axes and the geoid variable found by CF attributes) and write.

No data: a node is NaN when its stored value is NaN, the variable's ``_FillValue`` or
one of its ``missing_value`` values, outside its ``valid_range`` / ``valid_min`` /
``valid_max`` (compared in the stored, packed values, as the NetCDF User Guide and CF §2.5.1
say), or, when the variable declares no ``_FillValue``, netCDF's default fill value for
its type (what the library writes where nothing was written, 9.96921e36 for floats).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .._files import atomic_path
from ..errors import InputFileError
from ..geodesy.ellipsoids import TIDE_SYSTEMS
from ..geodesy.limits import MAX_GRID_NODES
from .files import finish_grid, provenance_of, regular_axis
from .grid import GeoidGrid

log = logging.getLogger(__name__)


NETCDF_MAGIC = (b"CDF\x01", b"CDF\x02", b"CDF\x05", b"\x89HDF\r\n\x1a\n")

#: netCDF-C's own limits (netcdf.h): NC_MAX_DIMS, NC_MAX_ATTRS, NC_MAX_VARS, NC_MAX_NAME,
#: NC_MAX_VAR_DIMS.
_NC_MAX = dict(dims=1024, attrs=8192, vars=8192, name=256, var_dims=1024)

#: Bytes per value of each nc_type (classic 1..6, CDF-5 adds 7..11).
_NC_TYPE_BYTES = {1: 1, 2: 1, 3: 2, 4: 4, 5: 4, 6: 8, 7: 1, 8: 2, 9: 4, 10: 8, 11: 8}

_NC_DIMENSION, _NC_VARIABLE, _NC_ATTRIBUTE = 10, 11, 12

#: Largest classic header read for the check (bytes); a grid's header is a few kB.
_MAX_CLASSIC_HEADER = 16 << 20


NETCDF_SUFFIXES = {".nc", ".nc4", ".cdf", ".netcdf"}




class _ClassicHeader:
    """A bounds-checked walk through a classic (CDF-1/2/5) netCDF header.

    netCDF-C trusts the counts and sizes of a classic header: a mutated count (say
    2.3e9 dimensions) makes it crash, hang or exhaust memory. This walk follows the
    format specification (NetCDF Users Guide, "File Format Specifications") and raises
    InputFileError at the first count, name, type, id or offset that the file cannot
    hold, before the library opens it.
    """

    def __init__(self, path, data: bytes, size: int):
        self.path, self.data, self.size, self.pos = path, data, size, 4
        version = data[3]
        self.count_bytes = 8 if version == 5 else 4  # NON_NEG
        self.offset_bytes = 4 if version == 1 else 8  # OFFSET (begin)
        self.types = 11 if version == 5 else 6

    def fail(self, rule: str):
        raise InputFileError(self.path, f"netCDF classic header: {rule} (at byte {self.pos})")

    def uint(self, nbytes: int) -> int:
        if self.pos + nbytes > len(self.data):
            self.fail("ends before its end (truncated or corrupt header)")
        value = int.from_bytes(self.data[self.pos:self.pos + nbytes], "big")
        self.pos += nbytes
        return value

    def count(self, what: str, limit: int, min_bytes: int) -> int:
        value = self.uint(self.count_bytes)
        room = (len(self.data) - self.pos) // max(min_bytes, 1)
        if value > limit or value > room:
            self.fail(f"{value} {what}, more than the file can hold")
        return value

    def skip(self, nbytes: int):
        padded = (nbytes + 3) // 4 * 4
        if self.pos + padded > len(self.data):
            self.fail("ends before its end (truncated or corrupt header)")
        self.pos += padded

    def name(self):
        length = self.count("name bytes", _NC_MAX["name"], 1)
        self.skip(length)

    def tagged_list(self, tag: int, what: str, limit: int, min_bytes: int) -> int:
        found = self.uint(4)
        if found not in (0, tag):
            self.fail(f"expected the {what} list tag {tag} or 0, found {found}")
        n = self.count(what, limit, min_bytes)
        if found == 0 and n:
            self.fail(f"an absent {what} list with {n} elements")
        return n

    def nc_type(self) -> int:
        value = self.uint(4)
        if not 1 <= value <= self.types:
            self.fail(f"unknown nc_type {value}")
        return value

    def attributes(self):
        for _ in range(self.tagged_list(_NC_ATTRIBUTE, "attributes", _NC_MAX["attrs"], 12)):
            self.name()
            nbytes = _NC_TYPE_BYTES[self.nc_type()]
            self.skip(self.count("attribute values", 1 << 40, nbytes) * nbytes)

    def check(self):
        numrecs = self.uint(self.count_bytes)
        streaming = numrecs == (1 << 8 * self.count_bytes) - 1
        dims = []
        for _ in range(self.tagged_list(_NC_DIMENSION, "dimensions", _NC_MAX["dims"], 8)):
            self.name()
            dims.append(self.uint(self.count_bytes))
        self.attributes()
        record_bytes = 0
        record_vars = []
        for _ in range(self.tagged_list(_NC_VARIABLE, "variables", _NC_MAX["vars"], 16)):
            self.name()
            ids = [self.uint(self.count_bytes) for _ in range(self.count("dimension ids", _NC_MAX["var_dims"], 4))]
            if any(i >= len(dims) for i in ids):
                self.fail(f"a variable uses dimension id {max(ids)} of {len(dims)} dimensions")
            self.attributes()
            nbytes = _NC_TYPE_BYTES[self.nc_type()]
            self.uint(self.count_bytes)  # vsize: redundant (and wrong for large variables)
            begin = self.uint(self.offset_bytes)
            record = bool(ids) and dims[ids[0]] == 0
            shape = [dims[i] for i in (ids[1:] if record else ids)]
            if any(d == 0 for d in shape):
                self.fail("a variable uses the record dimension other than first")
            nvalues = 1
            for d in shape:
                nvalues *= d
            if begin > self.size or (not record and begin + nvalues * nbytes > self.size):
                self.fail(f"a variable's data ({nvalues:,} values from byte {begin:,}) lie beyond the "
                          f"{self.size:,}-byte file")
            if record:
                record_bytes += nvalues * nbytes
                record_vars.append(begin)
        if record_vars and not streaming and min(record_vars) + numrecs * record_bytes > self.size:
            self.fail(f"{numrecs:,} records of {record_bytes:,} bytes lie beyond the {self.size:,}-byte file")


def check_netcdf_header(path, head: bytes, size: int) -> None:
    """Refuse, before netCDF-C opens it, a file that is not netCDF or whose classic
    header contradicts itself or the file size (see :class:`_ClassicHeader`). HDF5-based
    netCDF-4 files are checked by the HDF5 library itself."""
    if not head.startswith(NETCDF_MAGIC):
        raise InputFileError(path, f"not a netCDF file: starts with {head[:4]!r}, not CDF or HDF5 magic bytes")
    if head.startswith(b"CDF"):
        data = head
        if len(head) < size:
            with open(path, "rb") as fh:
                data = fh.read(min(size, _MAX_CLASSIC_HEADER))
        _ClassicHeader(path, data, size).check()


# -- CF netCDF -----------------------------------------------------------------------
_LAT_UNITS = {"degrees_north", "degree_north", "degrees_n", "degree_n", "degreesn", "degreen"}


_LON_UNITS = {"degrees_east", "degree_east", "degrees_e", "degree_e", "degreese", "degreee"}


_PLAIN_DEGREES = {"degrees", "degree", "deg"}




_UNIT_FACTORS = {
    "m": 1.0, "metre": 1.0, "metres": 1.0, "meter": 1.0, "meters": 1.0,
    "cm": 0.01, "centimetre": 0.01, "centimetres": 0.01, "centimeter": 0.01, "centimeters": 0.01,
    "mm": 0.001, "millimetre": 0.001, "millimetres": 0.001, "millimeter": 0.001, "millimeters": 0.001,
}


def _axis_kind(name: str, var):
    """'lat', 'lon' or None for a 1-D netCDF variable, from its name and CF attributes."""
    attrs = var.attrs
    standard = str(attrs.get("standard_name", "")).strip().lower()
    units = str(attrs.get("units", "")).strip().lower()
    axis = str(attrs.get("axis", "")).strip().upper()
    lname = name.lower()
    degrees = units in _PLAIN_DEGREES
    if standard == "latitude" or units in _LAT_UNITS or lname in ("lat", "latitude") or (axis == "Y" and degrees):
        return "lat"
    if standard == "longitude" or units in _LON_UNITS or lname in ("lon", "long", "longitude") or (axis == "X" and degrees):
        return "lon"
    return None


def _netcdf_axes(path, ds):
    """(lat name, lat dim, lon name, lon dim) of the dataset, or raise."""
    found = {"lat": [], "lon": []}
    for name, var in ds.variables.items():
        if var.ndim == 1:
            kind = _axis_kind(str(name), var)
            if kind:
                found[kind].append((str(name), var.dims[0]))
    picked = []
    for kind, label, good_units in (("lat", "latitude", _LAT_UNITS), ("lon", "longitude", _LON_UNITS)):
        cands = found[kind]
        if len(cands) > 1:
            # Prefer dimension coordinates (variable named like its dimension).
            cands = [c for c in cands if c[0] == c[1]] or cands
        if not cands:
            raise InputFileError(
                path, f"no {label} coordinate found (looked for names lat/lon/latitude/longitude, "
                "standard_name, units degrees_north/degrees_east, axis Y/X)"
            )
        if len({c[1] for c in cands}) > 1:
            raise InputFileError(path, f"several {label} coordinates: {', '.join(c[0] for c in cands)}")
        name, dim = cands[0]
        units = str(ds[name].attrs.get("units", "")).strip()
        if units and units.lower() not in good_units | _PLAIN_DEGREES:
            raise InputFileError(path, f"{label} coordinate '{name}' has units '{units}', need degrees")
        picked += [name, dim]
    if picked[1] == picked[3]:
        raise InputFileError(path, f"latitude '{picked[0]}' and longitude '{picked[2]}' share dimension '{picked[1]}'")
    return tuple(picked)


def _netcdf_variable(path, ds, lat_dim, lon_dim, coord_names, variable=None):
    """Name of the undulation variable on (lat_dim, lon_dim): the only candidate, or
    ``variable``; several candidates without ``variable`` are refused, listed (a file
    with N and its error, or N and ζ, must not be read by guessing from names)."""
    wanted = {lat_dim, lon_dim}
    cands = []
    for name, var in ds.data_vars.items():
        dims = {d for d, n in zip(var.dims, var.shape) if n != 1 or d in wanted}
        if dims == wanted and str(name) not in coord_names and "grid_mapping_name" not in var.attrs:
            cands.append(str(name))
    if variable is not None:
        if variable not in cands:
            raise InputFileError(path, f"--variable {variable!r} is not a 2-D data variable on ({lat_dim}, {lon_dim}); "
                                 f"the candidates are {', '.join(sorted(cands)) or 'none'}")
        return variable
    if not cands:
        raise InputFileError(path, f"no 2-D data variable on dimensions ({lat_dim}, {lon_dim})")
    if len(cands) == 1:
        return cands[0]
    raise InputFileError(
        path,
        f"cannot tell which variable holds the undulations: candidates {', '.join(sorted(cands))}; "
        "name one with --variable NAME (variable=NAME)",
    )


#: standard_name / long_name words that mean height anomalies (a quasi-geoid).
_QUASI = ("height_anomaly", "height anomaly", "quasi-geoid", "quasi_geoid", "quasigeoid", "zeta")


def _netcdf_reference(path, ds, var) -> tuple[str | None, str | None, str]:
    """(datum, ellipsoid, quantity) from CF: the variable's ``grid_mapping`` (``crs_wkt``,
    ``spatial_ref``, EPSG code, or its ellipsoid parameters) and the variable's
    ``standard_name``/``long_name``/``quantity``; the global ``ellipsoid`` attribute
    (geoidspline's own) when there is no grid mapping."""
    from .reference import canonical_ellipsoid, crs_datum

    datum = ellipsoid = None
    mapping = str(var.attrs.get("grid_mapping", "")).split(":")[0].strip()
    if mapping and mapping in ds.variables:
        attrs = ds[mapping].attrs
        text = attrs.get("crs_wkt") or attrs.get("spatial_ref")
        if not text and attrs.get("epsg_code"):
            text = str(attrs["epsg_code"])
        if not text and "semi_major_axis" in attrs and "inverse_flattening" in attrs:
            text = (f"+proj=longlat +a={float(attrs['semi_major_axis'])!r} +rf={float(attrs['inverse_flattening'])!r}"
                    " +no_defs")
        try:
            datum, ellipsoid = crs_datum(text) if text else (None, None)
        except ValueError as exc:
            raise InputFileError(path, f"grid_mapping variable '{mapping}': {exc}") from None
        if datum is not None and datum.startswith("+proj") or (datum is not None and "unknown" in datum.lower()):
            datum = None  # an ellipsoid alone: no datum
        if ellipsoid is None and attrs.get("reference_ellipsoid_name"):
            ellipsoid = canonical_ellipsoid(attrs["reference_ellipsoid_name"])
    if ellipsoid is None and "ellipsoid" in ds.attrs:
        ellipsoid = str(ds.attrs["ellipsoid"])
    said = [str(var.attrs.get(k, "")).strip().lower() for k in ("standard_name", "quantity", "data_type")]
    said.append(str(ds.attrs.get("data_type", "")).strip().lower())
    quantity = "quasi-geoid" if any(s in _QUASI for s in said) else "geoid"
    return datum, ellipsoid, quantity


def _sorted_longitudes(path, lon, values):
    """Longitudes ascending (columns reordered), unwrapping a 0..360/-180..180 seam if needed."""
    order = np.argsort(lon, kind="stable")
    lon, values = lon[order], values[:, order]
    step = np.diff(lon)
    if lon.size > 2 and step.max() > 1.5 * np.median(step):
        # A regional grid across the seam stored as e.g. -180..-170, 170..180: start after the gap.
        cut = int(np.argmax(step)) + 1
        lon = np.concatenate([lon[cut:], lon[:cut] + 360.0])
        values = np.concatenate([values[:, cut:], values[:, :cut]], axis=1)
    return lon, values


def _undeclared_nodata(raw_var) -> np.ndarray:
    """Mask of the stored values that mean no data but that xarray's CF decoding keeps:
    outside valid_range/valid_min/valid_max, and netCDF's default fill value when the
    variable declares no _FillValue."""
    import netCDF4

    raw = np.asarray(raw_var.values)
    attrs = raw_var.attrs
    mask = np.zeros(raw.shape, dtype=bool)
    if "valid_range" in attrs:
        low, high = np.ravel(attrs["valid_range"])[:2]
        mask |= (raw < low) | (raw > high)
    if "valid_min" in attrs:
        mask |= raw < np.ravel(attrs["valid_min"])[0]
    if "valid_max" in attrs:
        mask |= raw > np.ravel(attrs["valid_max"])[0]
    if "_FillValue" not in attrs and raw.dtype.kind in "iuf":
        default = netCDF4.default_fillvals.get(raw.dtype.str[1:])
        if default is not None:
            mask |= raw == np.array(default).astype(raw.dtype)
    return mask


def read_netcdf(path: Path, sha256: str, complete: bool, variable: str | None = None) -> GeoidGrid:
    import xarray as xr

    try:
        ds = xr.open_dataset(path, engine="netcdf4", decode_times=False, mask_and_scale=True)
        raw_ds = xr.open_dataset(path, engine="netcdf4", decode_times=False, mask_and_scale=False)
    except Exception as exc:  # the netCDF library's own message says what is wrong
        raise InputFileError(path, f"cannot be read as netCDF: {exc}") from None
    with ds, raw_ds:
        lat_name, lat_dim, lon_name, lon_dim = _netcdf_axes(path, ds)
        var_name = _netcdf_variable(path, ds, lat_dim, lon_dim, {lat_name, lon_name}, variable)
        var = ds[var_name]
        datum, ellipsoid, quantity = _netcdf_reference(path, ds, var)
        nodes = ds.sizes[lat_dim] * ds.sizes[lon_dim]
        if nodes > MAX_GRID_NODES:
            raise InputFileError(
                path, f"'{var_name}' has {ds.sizes[lat_dim]} x {ds.sizes[lon_dim]} = {nodes:,} nodes, more than "
                f"the {MAX_GRID_NODES:,} geoidspline reads (a global 1' grid has 233 million)",
            )
        units = str(var.attrs.get("units", "")).strip()
        if not units:
            log.warning("%s: variable '%s' has no units attribute; assuming metres", path, var_name)
            factor = 1.0
        elif units.lower() in _UNIT_FACTORS:
            factor = _UNIT_FACTORS[units.lower()]
        else:
            raise InputFileError(
                path, f"variable '{var_name}' has units '{units}'; known units are m, cm, mm (and spelled-out forms)"
            )
        extra = [d for d in var.dims if d not in (lat_dim, lon_dim)]
        first = {d: 0 for d in extra}  # size-1 dims (time, band)
        values = np.asarray(var.isel(first).transpose(lat_dim, lon_dim).values, dtype=np.float64) * factor
        values[_undeclared_nodata(raw_ds[var_name].isel(first).transpose(lat_dim, lon_dim))] = np.nan
        lat = np.asarray(ds[lat_name].values, dtype=np.float64)
        lon = np.asarray(ds[lon_name].values, dtype=np.float64)
        attrs = dict(ds.attrs)
    if lat.size != values.shape[0] or lon.size != values.shape[1]:
        raise InputFileError(path, f"coordinates ({lat.size}, {lon.size}) do not match '{var_name}' {values.shape}")
    if np.isinf(values).any():
        raise InputFileError(path, f"'{var_name}' has {int(np.isinf(values).sum())} infinite values")
    order = np.argsort(lat, kind="stable")  # either orientation -> ascending
    lat, values = lat[order], values[order]
    lon, values = _sorted_longitudes(path, lon, values)
    lat = regular_axis(path, lat, f"latitude '{lat_name}'", 180.0)
    lon = regular_axis(path, lon, f"longitude '{lon_name}'", 360.0)
    tide = str(attrs.get("tide_system", "")).strip().lower() or None
    try:
        zero = float(attrs["zero_degree_term_m"]) if "zero_degree_term_m" in attrs else None
    except (TypeError, ValueError):
        zero = None
    notes = [f"netCDF variable '{var_name}' in {units or 'm (assumed)'}"]
    prov = provenance_of(
        path, sha256,
        model=str(attrs["model"]) if "model" in attrs else None,
        ellipsoid=ellipsoid,
        datum=datum,
        quantity=quantity,
        tide_system=tide if tide in TIDE_SYSTEMS else None,
        zero_degree_term_m=zero,
        notes=tuple(notes),
    )
    return finish_grid(path, lat, lon, values, prov, complete=complete)


def write_netcdf(path, grid: GeoidGrid) -> Path:
    """Write ``grid`` as CF netCDF-4: ``geoid_height(latitude, longitude)`` in metres."""
    import xarray as xr

    path = Path(path)
    prov = grid.provenance
    ds = xr.Dataset(
        {
            "geoid_height": (
                ("latitude", "longitude"),
                np.asarray(grid.values, dtype=np.float64),
                {
                    "units": "m",
                    "long_name": "geoid undulation N above the reference ellipsoid",
                    "standard_name": "geoid_height_above_reference_ellipsoid",
                },
            )
        },
        coords={
            "latitude": ("latitude", np.asarray(grid.latitude), {
                "units": "degrees_north", "standard_name": "latitude", "long_name": "latitude", "axis": "Y"}),
            "longitude": ("longitude", np.asarray(grid.longitude), {
                "units": "degrees_east", "standard_name": "longitude", "long_name": "longitude", "axis": "X"}),
        },
    )
    ds.attrs["Conventions"] = "CF-1.8"
    ds.attrs["source"] = prov.source
    if prov.quantity == "quasi-geoid":
        ds["geoid_height"].attrs.update(standard_name="height_anomaly", quantity="quasi-geoid",
                                        long_name="height anomaly zeta above the reference ellipsoid")
    if prov.datum is not None:
        from pyproj import CRS

        ds["crs"] = ((), 0, {"grid_mapping_name": "latitude_longitude",
                             "crs_wkt": CRS.from_user_input(prov.datum).to_wkt()})
        ds["geoid_height"].attrs["grid_mapping"] = "crs"
    for key in ("model", "ellipsoid", "tide_system", "zero_degree_term_m", "sha256"):
        value = getattr(prov, key)
        if value is not None:
            ds.attrs["source_sha256" if key == "sha256" else key] = value
    encoding = {"latitude": {"_FillValue": None}, "longitude": {"_FillValue": None},
                "geoid_height": {"_FillValue": np.nan}}
    with atomic_path(path) as tmp:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
    return path
