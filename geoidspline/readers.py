"""Readers and writers of geoid grid files.

:func:`read_grid` reads PROJ GTX, CF netCDF, NGA ``WW15MGH.DAC`` and GeographicLib PGM
files into a :class:`~geoidspline.grid.GeoidGrid` (latitude ascending, longitude
ascending, metres). Every check is strict, and a failure raises
:class:`~geoidspline.errors.InputFileError` whose message names the file and the rule
it breaks, e.g. ``"egm.gtx: GTX file is 4152000 bytes, header says 721 x 1440 float32
nodes need 4153000"``.

:func:`write_gtx` and :func:`write_netcdf` write a grid back (tests, fixtures, export).
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import tempfile
from pathlib import Path

import numpy as np

from .errors import InputFileError
from .grid import GeoidGrid
from .sources import Provenance

__all__ = ["read_grid", "write_gtx", "write_netcdf", "pgm_header", "GTX_NODATA"]

log = logging.getLogger(__name__)

#: The value PROJ's GTX format uses for a node without data (metres).
GTX_NODATA = -88.8888
_GTX_HEADER_BYTES = 40

# NGA's WW15MGH.DAC: 15' EGM96 grid, 90N->90S by 0E->359.75E, int16 big-endian cm.
_DAC_ROWS, _DAC_COLS, _DAC_STEP = 721, 1440, 0.25

_NETCDF_MAGIC = (b"CDF\x01", b"CDF\x02", b"CDF\x05", b"\x89HDF\r\n\x1a\n")
_NETCDF_SUFFIXES = {".nc", ".nc4", ".cdf", ".netcdf"}

_TIDE_SYSTEMS = {"tide_free", "zero_tide", "mean_tide"}


# -- helpers shared by the readers -------------------------------------------------
def _sha256_file(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _provenance(path: Path, sha256: str, **known) -> Provenance:
    """Provenance of a file, completed from the catalogue when the file name is known there."""
    from .catalogue import entry_for_file  # lazy: catalogue imports this module

    fields = dict(source=path.name, sha256=sha256, kind="grid", ellipsoid="WGS84")
    fields.update({k: v for k, v in known.items() if v is not None})
    notes = list(fields.pop("notes", ()))
    entry = entry_for_file(path.name)
    if entry is not None:
        fields.update(model=entry.model, tide_system=entry.tide_system,
                      zero_degree_term_m=entry.zero_degree_term_m)
        notes.append(f"catalogue entry {entry.name}: {entry.reference}")
        if entry.sha256 and sha256 not in entry.sha256:
            # Same name, other bytes: another copy or another product; say so, don't fail.
            notes.append(f"sha256 differs from the catalogue's known copies of {entry.file}")
    return Provenance(notes=tuple(notes), **fields)


def _drop_repeated_column(path, lon, values):
    """Drop a last column 360° after the first (a global grid that repeats 0°/360°)."""
    if lon.size < 3:
        return lon, values
    spacing = (lon[-1] - lon[0]) / (lon.size - 1)
    if abs((lon.size - 1) * spacing - 360.0) > 1e-9:
        return lon, values
    first, last = values[:, 0], values[:, -1]
    both_nan = np.isnan(first) & np.isnan(last)
    diff = np.where(both_nan, 0.0, np.abs(first - last))
    worst = float(np.nanmax(np.where(np.isnan(diff), np.inf, diff)))
    if worst > 1e-6:
        raise InputFileError(
            path,
            f"the last longitude column ({lon[-1]:g}) is 360 degrees after the first "
            f"({lon[0]:g}) but differs from it by up to {worst:.6g} m",
        )
    return lon[:-1], values[:, :-1]


def _finish(path, lat, lon, values, provenance, *, complete=False) -> GeoidGrid:
    """Normalise the 360° duplicate column, check the NaNs, build the grid."""
    lon, values = _drop_repeated_column(path, lon, values)
    nan = int(np.isnan(values).sum())
    if nan == values.size:
        raise InputFileError(path, f"all {nan} nodes are NaN (no data)")
    if complete and nan:
        raise InputFileError(path, f"{nan} of {values.size} nodes are NaN (no data) in a grid that must be complete")
    try:
        return GeoidGrid(lat, lon, values, provenance)
    except InputFileError as exc:
        raise InputFileError(path, exc.rule) from None


def _regular_axis(path, coord, name, period):
    """An exact equally spaced lattice (degrees) for coordinates read from a file.

    Files often store coordinates as float32 (errors up to ~1e-5°): the spacing is
    snapped to ``period / k`` and the origin to a multiple of half the spacing when
    they are that close, and every coordinate must lie within 0.1% of a spacing of
    the lattice.
    """
    coord = np.asarray(coord, dtype=np.float64)
    if coord.size < 2:
        raise InputFileError(path, f"{name} has {coord.size} value(s); a grid needs at least 2")
    if not np.isfinite(coord).all():
        raise InputFileError(path, f"{name} contains non-finite values")
    spacing = (coord[-1] - coord[0]) / (coord.size - 1)
    if not spacing > 0:
        raise InputFileError(path, f"{name} is not strictly monotonic")
    turns = round(period / spacing)
    if turns > 0 and abs(turns * spacing - period) <= 1e-4:
        spacing = period / turns
    origin = coord[0]
    half = spacing / 2.0
    if abs(origin - round(origin / half) * half) <= 1e-5:
        origin = round(origin / half) * half
    lattice = origin + spacing * np.arange(coord.size)
    worst = float(np.max(np.abs(coord - lattice)))
    if worst > 1e-3 * spacing:
        raise InputFileError(
            path,
            f"{name} is not equally spaced: a value is {worst:.3g} degrees off the "
            f"{spacing:.12g}-degree lattice starting at {origin:.12g}",
        )
    return lattice


# -- PROJ GTX ------------------------------------------------------------------------
def _read_gtx(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    size = len(data)
    if size < _GTX_HEADER_BYTES:
        raise InputFileError(path, f"GTX file is {size} bytes, shorter than its {_GTX_HEADER_BYTES}-byte header")
    lat0, lon0, dlat, dlon = (float(v) for v in np.frombuffer(data, ">f8", count=4))
    rows, cols = (int(v) for v in np.frombuffer(data, ">i4", count=2, offset=32))
    header = f"(lat0={lat0}, lon0={lon0}, dlat={dlat}, dlon={dlon}, rows={rows}, cols={cols})"
    if not all(np.isfinite(v) for v in (lat0, lon0, dlat, dlon)):
        raise InputFileError(path, f"GTX header has non-finite values {header}")
    if not (dlat > 0 and dlon > 0):
        raise InputFileError(path, f"GTX header spacing must be > 0 degrees, got dlat={dlat}, dlon={dlon}")
    if rows <= 0 or cols <= 0:
        raise InputFileError(path, f"GTX header must have rows > 0 and cols > 0, got rows={rows}, cols={cols}")
    expected = _GTX_HEADER_BYTES + rows * cols * 4
    if size != expected:
        raise InputFileError(
            path, f"GTX file is {size} bytes, header says {rows} x {cols} float32 nodes need {expected}"
        )
    lat1 = lat0 + (rows - 1) * dlat
    if lat0 < -90.0 - 1e-9 or lat1 > 90.0 + 1e-9:
        raise InputFileError(path, f"GTX latitudes {lat0}..{lat1} go beyond [-90, 90] degrees {header}")
    raw = np.frombuffer(data, ">f4", offset=_GTX_HEADER_BYTES).reshape(rows, cols)
    bad = int((~np.isfinite(raw)).sum())
    if bad:
        raise InputFileError(
            path, f"{bad} nodes are NaN or infinite; GTX marks no data with {GTX_NODATA}, not NaN"
        )
    values = raw.astype(np.float64)
    values[np.abs(values - GTX_NODATA) < 1e-4] = np.nan  # float32(-88.8888) is not exact
    lat = lat0 + dlat * np.arange(rows)
    lon = lon0 + dlon * np.arange(cols)
    return _finish(path, lat, lon, values, _provenance(path, sha256), complete=complete)


def write_gtx(path, grid: GeoidGrid) -> Path:
    """Write ``grid`` as a PROJ GTX file (big-endian, float32 metres, NaN -> -88.8888)."""
    path = Path(path)
    rows, cols = grid.shape
    header = np.array(
        [grid.latitude[0], grid.longitude[0], grid.latitude_spacing, grid.longitude_spacing], dtype=">f8"
    ).tobytes() + np.array([rows, cols], dtype=">i4").tobytes()
    values = np.where(np.isnan(grid.values), GTX_NODATA, grid.values).astype(">f4")
    _atomic_write(path, header + values.tobytes())
    return path


def _atomic_write(path: Path, payload: bytes):
    # Write beside the target and rename, so a reader never sees half a file.
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(payload)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


# -- NGA WW15MGH.DAC -------------------------------------------------------------------
def _read_dac(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    expected = _DAC_ROWS * _DAC_COLS * 2
    if len(data) != expected:
        raise InputFileError(
            path,
            f"DAC file is {len(data)} bytes, but {_DAC_ROWS} x {_DAC_COLS} int16 nodes "
            f"(NGA WW15MGH.DAC, 15' EGM96) need {expected}",
        )
    cm = np.frombuffer(data, ">i2").reshape(_DAC_ROWS, _DAC_COLS)
    values = cm[::-1].astype(np.float64) / 100.0  # rows 90N->90S, centimetres
    lat = -90.0 + _DAC_STEP * np.arange(_DAC_ROWS)
    lon = _DAC_STEP * np.arange(_DAC_COLS)
    prov = _provenance(path, sha256, notes=("NGA binary grid, int16 centimetres",))
    return _finish(path, lat, lon, values, prov, complete=complete)


# -- GeographicLib PGM ---------------------------------------------------------------
def pgm_header(path) -> dict:
    """Decode the header of a GeographicLib geoid PGM file.

    Returns ``width``, ``height``, ``maxval``, ``offset`` and ``scale`` (metres),
    ``data_offset`` (bytes), ``comments`` (dict of the ``# Key value`` lines) and
    ``description``.
    """
    path = Path(path)
    with open(path, "rb") as fh:
        head = fh.read(1 << 16)
    return _parse_pgm_header(path, head)


def _parse_pgm_header(path: Path, data: bytes) -> dict:
    if data[:2] != b"P5":
        raise InputFileError(path, f"not a binary PGM file: starts with {data[:2]!r}, expected b'P5'")
    pos, tokens, comments = 2, [], {}
    while len(tokens) < 3:
        if pos >= len(data):
            raise InputFileError(path, "PGM header ends before width, height and maxval")
        byte = data[pos:pos + 1]
        if byte.isspace():
            pos += 1
        elif byte == b"#":
            end = data.find(b"\n", pos)
            end = len(data) if end < 0 else end
            line = data[pos + 1:end].decode("latin-1").strip()
            key, _, value = line.partition(" ")
            comments.setdefault(key, value.strip())
            pos = end + 1
        else:
            match = re.match(rb"\d+", data[pos:])
            if match is None:
                raise InputFileError(path, f"PGM header has a non-numeric field at byte {pos}")
            tokens.append(int(match.group()))
            pos += match.end()
    if pos >= len(data) or not data[pos:pos + 1].isspace():
        raise InputFileError(path, "PGM header: maxval must be followed by one whitespace byte")
    width, height, maxval = tokens
    header = dict(width=width, height=height, maxval=maxval, data_offset=pos + 1,
                  comments=comments, description=comments.get("Description"))
    for key in ("Offset", "Scale"):
        if key not in comments:
            raise InputFileError(path, f"PGM header has no '# {key}' comment line (GeographicLib geoid files need one)")
        try:
            header[key.lower()] = float(comments[key])
        except ValueError:
            raise InputFileError(path, f"PGM header '# {key} {comments[key]}' is not a number") from None
    if not (np.isfinite(header["offset"]) and np.isfinite(header["scale"]) and header["scale"] != 0):
        raise InputFileError(path, f"PGM Offset {header['offset']} / Scale {header['scale']} are not usable")
    if maxval != 65535:
        raise InputFileError(path, f"PGM maxval is {maxval}; GeographicLib geoid files use 65535 (16-bit pixels)")
    if width <= 0 or height < 2:
        raise InputFileError(path, f"PGM raster {width} x {height} is too small")
    if width != 2 * (height - 1):
        # Same rule as GeographicLib's "Raster size mismatch": equal spacing 180/(height-1) = 360/width.
        raise InputFileError(
            path, f"PGM raster {width} x {height} has unequal spacing; a global geoid grid needs width == 2*(height-1)"
        )
    origin = comments.get("Origin")
    if origin is not None and origin.split() != ["90N", "0E"]:
        raise InputFileError(path, f"PGM '# Origin {origin}' is not supported (only 90N 0E)")
    return header


def _read_pgm(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    head = _parse_pgm_header(path, data)
    width, height, start = head["width"], head["height"], head["data_offset"]
    expected = width * height * 2
    if len(data) - start != expected:
        raise InputFileError(
            path,
            f"PGM data is {len(data) - start} bytes after the header (byte {start}), "
            f"but {width} x {height} uint16 pixels need {expected}",
        )
    pixels = np.frombuffer(data, ">u2", offset=start).reshape(height, width)
    values = head["offset"] + head["scale"] * pixels[::-1].astype(np.float64)  # rows 90N->90S
    step = 180.0 / (height - 1)
    lat = -90.0 + step * np.arange(height)
    lon = (360.0 / width) * np.arange(width)
    model = None
    if head["description"]:
        found = re.search(r"\bEGM\s*-?\s*(\d{2,4})\b", head["description"], re.IGNORECASE)
        model = f"EGM{found.group(1)}" if found else head["description"]
    notes = (f"GeographicLib PGM: Offset {head['offset']:g} m, Scale {head['scale']:g} m",)
    if head["description"]:
        notes += (f"Description: {head['description']}",)
    prov = _provenance(path, sha256, model=model, notes=notes)
    return _finish(path, lat, lon, values, prov, complete=complete)


# -- CF netCDF -----------------------------------------------------------------------
_LAT_UNITS = {"degrees_north", "degree_north", "degrees_n", "degree_n", "degreesn", "degreen"}
_LON_UNITS = {"degrees_east", "degree_east", "degrees_e", "degree_e", "degreese", "degreee"}
_PLAIN_DEGREES = {"degrees", "degree", "deg"}
_DATA_NAMES = ("geoid", "undulation", "n", "geoid_height", "z", "geoid_undulation", "geoidheight", "geoid_undulations")
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


def _netcdf_variable(path, ds, lat_dim, lon_dim, coord_names):
    """Name of the single undulation variable on (lat_dim, lon_dim), or raise."""
    wanted = {lat_dim, lon_dim}
    cands = []
    for name, var in ds.data_vars.items():
        dims = {d for d, n in zip(var.dims, var.shape) if n != 1 or d in wanted}
        if dims == wanted and str(name) not in coord_names:
            cands.append(str(name))
    if not cands:
        raise InputFileError(path, f"no 2-D data variable on dimensions ({lat_dim}, {lon_dim})")
    if len(cands) == 1:
        return cands[0]
    named = [c for c in cands if c.lower() in _DATA_NAMES]
    if len(named) == 1:
        return named[0]
    raise InputFileError(
        path,
        f"cannot tell which variable holds the undulations: candidates {', '.join(sorted(cands))} "
        f"(name one of them {'/'.join(_DATA_NAMES[:5])}, or keep only one)",
    )


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


def _read_netcdf(path: Path, sha256: str, complete: bool) -> GeoidGrid:
    import xarray as xr

    try:
        ds = xr.open_dataset(path, engine="netcdf4", decode_times=False, mask_and_scale=True)
    except Exception as exc:  # the netCDF library's own message says what is wrong
        raise InputFileError(path, f"cannot be read as netCDF: {exc}") from None
    with ds:
        lat_name, lat_dim, lon_name, lon_dim = _netcdf_axes(path, ds)
        var_name = _netcdf_variable(path, ds, lat_dim, lon_dim, {lat_name, lon_name})
        var = ds[var_name]
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
        data = var.isel({d: 0 for d in extra}) if extra else var  # size-1 dims (time, band)
        values = np.asarray(data.transpose(lat_dim, lon_dim).values, dtype=np.float64) * factor
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
    lat = _regular_axis(path, lat, f"latitude '{lat_name}'", 180.0)
    lon = _regular_axis(path, lon, f"longitude '{lon_name}'", 360.0)
    tide = str(attrs.get("tide_system", "")).strip().lower() or None
    try:
        zero = float(attrs["zero_degree_term_m"]) if "zero_degree_term_m" in attrs else None
    except (TypeError, ValueError):
        zero = None
    notes = [f"netCDF variable '{var_name}' in {units or 'm (assumed)'}"]
    prov = _provenance(
        path, sha256,
        model=str(attrs["model"]) if "model" in attrs else None,
        ellipsoid=str(attrs["ellipsoid"]) if "ellipsoid" in attrs else None,
        tide_system=tide if tide in _TIDE_SYSTEMS else None,
        zero_degree_term_m=zero,
        notes=tuple(notes),
    )
    return _finish(path, lat, lon, values, prov, complete=complete)


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
    for key in ("model", "ellipsoid", "tide_system", "zero_degree_term_m", "sha256"):
        value = getattr(prov, key)
        if value is not None:
            ds.attrs["source_sha256" if key == "sha256" else key] = value
    encoding = {"latitude": {"_FillValue": None}, "longitude": {"_FillValue": None},
                "geoid_height": {"_FillValue": np.nan}}
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        ds.to_netcdf(tmp, engine="netcdf4", format="NETCDF4", encoding=encoding)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


# -- dispatch ------------------------------------------------------------------------
def read_grid(path, *, complete: bool = False) -> GeoidGrid:
    """Read a geoid grid file (PROJ .gtx, CF netCDF, NGA .DAC, GeographicLib .pgm).

    The format is taken from the magic bytes (netCDF, PGM) or else the extension.
    ``complete=True`` rejects any node without data. Errors are
    :class:`InputFileError` naming the file and the rule broken.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "no such file" if not path.exists() else "not a regular file")
    suffix = path.suffix.lower()
    with open(path, "rb") as fh:
        magic = fh.read(8)
    if magic.startswith(_NETCDF_MAGIC) or suffix in _NETCDF_SUFFIXES:
        if not magic.startswith(_NETCDF_MAGIC):
            raise InputFileError(path, f"not a netCDF file: starts with {magic[:4]!r}, not CDF or HDF5 magic bytes")
        return _read_netcdf(path, _sha256_file(path), complete)
    readers = {".gtx": _read_gtx, ".dac": _read_dac, ".pgm": _read_pgm}
    reader = _read_pgm if magic.startswith(b"P5") else readers.get(suffix)
    if reader is None:
        raise InputFileError(
            path,
            f"unrecognised grid format (extension '{path.suffix}'); supported: .gtx (PROJ GTX), "
            ".nc/.nc4/.cdf (CF netCDF), .dac (NGA WW15MGH.DAC), .pgm (GeographicLib)",
        )
    data = path.read_bytes()
    return reader(path, data, hashlib.sha256(data).hexdigest(), complete)
