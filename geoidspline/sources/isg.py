"""ISG: the International Service for the Geoid's text grid format (versions 1.0, 1.01, 2.0).

Most regional and national geoid models are published by the ISG in this format. A file
is free text, then a header between a ``begin_of_head`` and an ``end_of_head`` line of
``key : value`` / ``key = value`` lines, then the grid: ``nrows`` lines of ``ncols``
values, north row first, west to east, in metres. The keys read here:

- ``lat min``, ``lat max``, ``lon min``, ``lon max``, ``delta lat``, ``delta lon``,
  ``nrows``, ``ncols``, ``ISG format`` (always required); ``nodata`` (e.g. -9999.0000);
- 2.0: ``data format`` (``grid``; ``sparse`` is refused), ``coord type`` (``geodetic``;
  ``projected`` is refused), ``coord units`` (``deg``, or ``dms`` as ``39°50'00"``),
  ``data units`` (``meters``; ``feet`` is refused), ``data type`` (``geoid`` or
  ``quasi-geoid``), ``data ordering`` (``N-to-S, W-to-E``), ``ref ellipsoid``,
  ``tide system``, ``model name``, ``EPSG code`` (1.0 spells units and ellipsoid
  ``units`` and ``reference``).

Registration. The bounds either give the outer nodes (node registration: ``lat max -
lat min = (nrows - 1) * delta lat``, the ISG 2.0 convention) or the outer cell edges
with values at the cell centres (cell registration: ``= nrows * delta lat``, the
convention GDAL reads ISG 1.0 with); the header's numbers say which, and a cell-
registered grid's nodes are shifted half a cell inwards. Anything else is refused.

Values equal to ``nodata`` become NaN (no data). Coordinates written with few decimals
(``0.016667`` for 1', ``121.666667``) are read as the lattice they round
(:func:`~geoidspline.sources._common.snap_spacing`).
"""

from __future__ import annotations

import datetime as _dt
import logging
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..errors import InputFileError
from ._common import MAX_TEXT_NODES, decimals_tolerance, parse_values, snap_origin, snap_spacing
from .files import finish_grid, provenance_of
from .grid import GeoidGrid
from .reference import crs_datum

__all__ = ["ISG_NODATA", "looks_like_isg", "isg_header", "read_isg", "write_isg"]

log = logging.getLogger(__name__)

#: The no-data value :func:`write_isg` writes (the one ISG's own files use).
ISG_NODATA = -9999.0

_VERSIONS = {1.0: "1.0", 1.01: "1.01", 2.0: "2.0"}
_TIDE = {"tide-free": "tide_free", "mean-tide": "mean_tide", "zero-tide": "zero_tide"}
_METRES = {"meters", "metres", "meter", "metre", "m"}
_DMS = re.compile(r"^([+-])?\s*(\d+)\s*[°º]\s*(\d+)\s*'\s*(\d+(?:\.\d*)?)\s*\"$")
_UNSET = "---"


def looks_like_isg(head: bytes) -> bool:
    """Whether the first bytes of a file (64 KiB are plenty) are an ISG grid's.

    ``begin_of_head`` alone is not enough: ICGEM ``.gfc`` models use it too; an ISG
    header also has one of its own keys.
    """
    return b"begin_of_head" in head and re.search(
        rb"^[ \t]*(isg format|lat min|north min|nrows)[ \t]*[:=]", head, re.IGNORECASE | re.MULTILINE
    ) is not None


# -- header ------------------------------------------------------------------------
@dataclass(frozen=True)
class _Axis:
    """One axis read from a header: nodes ``origin + spacing * k``, k < count (degrees)."""

    origin: float
    spacing: float
    count: int
    registration: str  # "node" or "cell"


def _split(path, text: str):
    """(header lines with their line numbers, body text, first body line number)."""
    begin = re.search(r"^[ \t]*begin_of_head\b.*$", text, re.MULTILINE)
    if begin is None:
        raise InputFileError(path, "ISG file has no 'begin_of_head' line")
    end = re.compile(r"^[ \t]*end_of_head\b.*$", re.MULTILINE).search(text, begin.end())
    if end is None:
        raise InputFileError(path, "ISG header has no 'end_of_head' line after 'begin_of_head'")
    first = text.count("\n", 0, begin.start()) + 2  # line number of the first header line
    lines = text[begin.end():end.start()].strip("\r\n").splitlines()
    body_line = text.count("\n", 0, end.end()) + 2
    return [(first + i, line) for i, line in enumerate(lines)], text[end.end():], body_line


def _fields(path, lines) -> dict[str, str]:
    """Header ``key : value`` / ``key = value`` pairs, keys lower-case with single spaces."""
    fields: dict[str, str] = {}
    for number, line in lines:
        if not line.strip():
            continue
        match = re.match(r"^([^:=]*)[:=](.*)$", line)
        key = " ".join(match.group(1).split()).lower() if match else ""
        if not key:
            raise InputFileError(path, f"ISG header line {number} {line.strip()[:60]!r} is not 'key : value' or 'key = value'")
        if key in fields:
            raise InputFileError(path, f"ISG header key '{key}' appears twice (again on line {number})")
        fields[key] = match.group(2).strip()
    return fields


def _optional(fields, *keys):
    """The first of ``keys`` present with a value other than '---', else None."""
    for key in keys:
        value = fields.get(key)
        if value is not None and value != _UNSET and value != "":
            return value
    return None


def _required(path, fields, key):
    value = fields.get(key)
    if value is None:
        raise InputFileError(path, f"ISG header has no '{key}' key")
    if value in ("", _UNSET):
        raise InputFileError(path, f"ISG header key '{key}' has no value ('{value}')")
    return value


def _count(path, fields, key) -> int:
    text = _required(path, fields, key)
    if not re.fullmatch(r"\+?\d+", text):
        raise InputFileError(path, f"ISG header '{key} = {text}' is not a whole number")
    value = int(text)
    if value < 1:
        raise InputFileError(path, f"ISG header '{key} = {text}' must be at least 1")
    return value


def _coordinate(path, fields, key, units) -> tuple[float, float]:
    """(degrees, half a unit of the last digit written) of a header coordinate."""
    text = _required(path, fields, key)
    if units == "dms" or (units == "unstated" and re.search("[°º]", text)):
        match = _DMS.match(text)
        if match is None:
            raise InputFileError(
                path, f"ISG header '{key} = {text}' is not degrees°minutes'seconds\" (coord units dms), e.g. 39°50'00\""
            )
        sign, degrees, minutes, seconds = match.groups()
        if int(minutes) >= 60 or float(seconds) >= 60.0:
            raise InputFileError(path, f"ISG header '{key} = {text}': minutes and seconds must be below 60")
        value = int(degrees) + int(minutes) / 60.0 + float(seconds) / 3600.0
        return (-value if sign == "-" else value), 0.0  # whole seconds: exact as written
    if not re.fullmatch(r"[+-]?(\d+\.?\d*|\.\d+)([eE][+-]?\d+)?", text):
        raise InputFileError(path, f"ISG header '{key} = {text}' is not a number of degrees (coord units {units})")
    return float(text), decimals_tolerance(text)


def _axis(path, fields, name, count_key, units, version) -> _Axis:
    """The lattice of one axis (``name`` is 'lat' or 'lon'), registration from the bounds."""
    low, low_tol = _coordinate(path, fields, f"{name} min", units)
    high, high_tol = _coordinate(path, fields, f"{name} max", units)
    step, step_tol = _coordinate(path, fields, f"delta {name}", units)
    count = _count(path, fields, count_key)
    if not step > 0:
        raise InputFileError(path, f"ISG header 'delta {name}' is {step:g}; it must be > 0 degrees")
    spacing = snap_spacing(step, step_tol)
    spacing_tol = step_tol if spacing == step else 0.0
    extent = high - low
    tol = low_tol + high_tol + count * spacing_tol + 1e-9 * max(1.0, abs(high), abs(low))
    node = abs(extent - (count - 1) * spacing) <= tol
    cell = abs(extent - count * spacing) <= tol
    if node and cell:  # only for a spacing within the rounding: take the version's convention
        node = version == "2.0"
    if not (node or cell):
        raise InputFileError(
            path,
            f"ISG header {name} min..{name} max = {low:.10g}..{high:.10g} spans {extent:.10g} degrees, but "
            f"{count_key} = {count} nodes at delta {name} = {spacing:.10g} span {(count - 1) * spacing:.10g} "
            f"(node registration) or {count * spacing:.10g} (cell registration)",
        )
    if node:
        return _Axis(snap_origin(low, spacing, low_tol), spacing, count, "node")
    return _Axis(snap_origin(low, spacing, low_tol) + spacing / 2.0, spacing, count, "cell")


@dataclass(frozen=True)
class _Header:
    version: str
    latitude: _Axis
    longitude: _Axis
    nodata: float | None
    fields: dict


def _header(path, fields) -> _Header:
    version_text = _required(path, fields, "isg format")
    try:
        version = _VERSIONS[float(version_text)]
    except (ValueError, KeyError):
        raise InputFileError(path, f"ISG format '{version_text}' is not one of 1.0, 1.01, 2.0") from None
    if version == "2.0":
        for key in ("data format", "coord type", "coord units"):
            _required(path, fields, key)
    data_format = (_optional(fields, "data format") or "grid").lower()
    if data_format != "grid":
        raise InputFileError(
            path, f"ISG data format '{data_format}' is not supported: geoidspline reads gridded ISG files ('grid')"
        )
    coord_type = (_optional(fields, "coord type") or "geodetic").lower()
    if coord_type != "geodetic":
        projection = _optional(fields, "map projection") or "not named"
        epsg = _optional(fields, "epsg code") or "none"
        raise InputFileError(
            path,
            f"ISG coord type '{coord_type}' (map projection {projection}, EPSG code {epsg}) is not supported: "
            "geoidspline needs a grid in geodetic latitude/longitude; reproject the grid first",
        )
    units = (_optional(fields, "coord units") or "unstated").lower()  # 1.0: either, value by value
    if units not in ("deg", "dms", "unstated"):
        raise InputFileError(
            path, f"ISG coord units '{units}' do not fit geodetic coordinates: expected 'deg' or 'dms'"
        )
    data_units = _optional(fields, "data units", "units")
    if data_units is not None and data_units.lower() not in _METRES:
        raise InputFileError(path, f"ISG data units '{data_units}' are not metres ('meters'); convert the grid to metres")
    data_type = (_optional(fields, "data type") or "geoid").lower()
    if data_type not in ("geoid", "quasi-geoid"):
        raise InputFileError(path, f"ISG data type '{data_type}' is neither 'geoid' nor 'quasi-geoid'")
    ordering = _optional(fields, "data ordering")
    if ordering is not None and " ".join(ordering.lower().replace(",", " ").split()) != "n-to-s w-to-e":
        raise InputFileError(path, f"ISG data ordering '{ordering}' is not supported; gridded files are 'N-to-S, W-to-E'")
    tide = _optional(fields, "tide system")
    if tide is not None and tide.lower().replace("_", "-").replace(" ", "-") not in _TIDE:
        raise InputFileError(path, f"ISG tide system '{tide}' is not one of tide-free, mean-tide, zero-tide")
    latitude = _axis(path, fields, "lat", "nrows", units, version)
    longitude = _axis(path, fields, "lon", "ncols", units, version)
    if latitude.registration != longitude.registration:
        raise InputFileError(
            path,
            f"ISG header bounds give {latitude.registration} registration in latitude but "
            f"{longitude.registration} registration in longitude",
        )
    if latitude.count * longitude.count > MAX_TEXT_NODES:
        raise InputFileError(
            path, f"ISG header declares {latitude.count} x {longitude.count} nodes, more than {MAX_TEXT_NODES:,}"
        )
    nodata_text = _optional(fields, "nodata")
    nodata = None
    if nodata_text is not None:
        try:
            nodata = float(nodata_text)
        except ValueError:
            raise InputFileError(path, f"ISG header 'nodata = {nodata_text}' is not a number") from None
    return _Header(version, latitude, longitude, nodata, fields)


def isg_header(path) -> dict:
    """The header of an ISG file: its ``key: value`` fields (keys lower-case) plus the
    decoded ``version``, ``registration``, ``latitude``/``longitude`` (first node,
    spacing, count in degrees) and ``nodata``."""
    path = Path(path)
    header = _header(path, _fields(path, _split(path, _decode(path, path.read_bytes()))[0]))
    return dict(
        header.fields,
        version=header.version,
        registration=header.latitude.registration,
        latitude=(header.latitude.origin, header.latitude.spacing, header.latitude.count),
        longitude=(header.longitude.origin, header.longitude.spacing, header.longitude.count),
        nodata=header.nodata,
    )


def _decode(path, data: bytes) -> str:
    if b"\x00" in data[:65536]:
        raise InputFileError(path, "ISG file is not text (contains NUL bytes)")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return data.decode("latin-1")  # a degree sign written as byte 0xB0


# -- reader --------------------------------------------------------------------------
def read_isg(path, data: bytes, sha256: str, complete: bool = False) -> GeoidGrid:
    """Read an ISG grid file's bytes ``data`` into a :class:`GeoidGrid` (metres).

    Raises :class:`InputFileError` naming ``path`` and the rule broken.
    """
    path = Path(path)
    lines, body, body_line = _split(path, _decode(path, data))
    header = _header(path, _fields(path, lines))
    lat, lon = header.latitude, header.longitude
    values = parse_values(path, body, body_line, "ISG data")
    expected = lat.count * lon.count
    if values.size != expected:
        rows = sum(1 for line in body.splitlines() if line.strip())
        raise InputFileError(
            path,
            f"ISG data has {values.size} values on {rows} lines, but nrows x ncols = {lat.count} x {lon.count} "
            f"needs {expected}",
        )
    expected_registration = "node" if header.version == "2.0" else "cell"  # GDAL's reading of the versions
    if lat.registration != expected_registration:
        log.warning("%s: ISG %s file with %s-registered bounds (GDAL would refuse it); read as %s-registered",
                    path, header.version, lat.registration, lat.registration)
    grid = values.reshape(lat.count, lon.count)[::-1].copy()  # file rows run north to south
    if header.nodata is not None:
        grid[grid == header.nodata] = np.nan
    fields = header.fields
    tide = _optional(fields, "tide system")
    notes = [f"ISG format {header.version}, {lat.registration}-registered"
             + (" (values at cell centres)" if lat.registration == "cell" else "")]
    quantity = (_optional(fields, "data type") or "geoid").lower()
    if quantity == "quasi-geoid":
        notes.append("ISG data type quasi-geoid: the values are height anomalies (zeta), not geoid undulations N")
    for key in ("model type", "model year", "ref frame", "height datum", "epsg code", "creation date"):
        value = _optional(fields, key)
        if value is not None:
            notes.append(f"ISG {key.replace('epsg', 'EPSG')}: {value}")
    if _optional(fields, "data units", "units") is None:
        notes.append("ISG data units not stated; read as metres")
    epsg = _optional(fields, "epsg code")
    datum = None
    if epsg is not None and re.fullmatch(r"\d+", epsg.strip()):
        try:
            datum, _ = crs_datum(f"EPSG:{epsg.strip()}")
        except ValueError:
            raise InputFileError(path, f"ISG EPSG code {epsg} is not a CRS PROJ knows") from None
    prov = provenance_of(
        path, sha256,
        model=_optional(fields, "model name"),
        ellipsoid=_optional(fields, "ref ellipsoid", "reference") or "unknown",
        datum=datum,
        quantity=quantity,
        tide_system=_TIDE[tide.lower().replace("_", "-").replace(" ", "-")] if tide else None,
        notes=tuple(notes),
    )
    latitude = lat.origin + lat.spacing * np.arange(lat.count)
    longitude = lon.origin + lon.spacing * np.arange(lon.count)
    return finish_grid(path, latitude, longitude, grid, prov, complete=complete)


# -- writer --------------------------------------------------------------------------
def _whole_seconds(value: float) -> bool:
    return abs(value * 3600.0 - round(value * 3600.0)) <= 1e-6  # then _exact_lattice decides


def _dms(value: float) -> str:
    seconds = round(abs(value) * 3600.0)
    degrees, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{'-' if value < 0 else ''}{degrees}°{minutes:02d}'{secs:02d}\""


def _coordinate_texts(grid: GeoidGrid):
    """Candidate (coord units, {key: text}) pairs, the conventional ones first."""
    lat, lon = grid.latitude, grid.longitude
    numbers = {
        "lat min": lat[0], "lat max": lat[-1], "lon min": lon[0], "lon max": lon[-1],
        "delta lat": grid.latitude_spacing, "delta lon": grid.longitude_spacing,
    }
    if all(_whole_seconds(v) for v in numbers.values()):
        yield "dms", {k: _dms(v) for k, v in numbers.items()}
    yield "deg", {k: f"{v:.6f}" for k, v in numbers.items()}
    yield "deg", {k: repr(float(v)) for k, v in numbers.items()}
    yield "deg", {k: f"{v:.25f}" for k, v in numbers.items()}  # exact, never snapped


def _exact_lattice(units, texts, grid) -> bool:
    """Whether a header with these coordinate texts reads back as ``grid``'s nodes."""
    fields = dict(texts, nrows=str(grid.shape[0]), ncols=str(grid.shape[1]))
    try:
        lat = _axis("?", fields, "lat", "nrows", units, "2.0")
        lon = _axis("?", fields, "lon", "ncols", units, "2.0")
    except InputFileError:
        return False
    if not lat.registration == lon.registration == "node":
        return False
    # GeoidGrid's spacing is (last - first) / (n - 1), a few ulps off 1/3 or 1/60: the
    # header is exact when it gives every node to within a micrometre (1e-11 degrees).
    return all(
        float(np.max(np.abs(axis.origin + axis.spacing * np.arange(axis.count) - nodes))) <= 1e-11
        for axis, nodes in ((lat, grid.latitude), (lon, grid.longitude))
    )


def write_isg(path, grid: GeoidGrid, *, decimals: int | None = None, data_type: str | None = None,
              created: _dt.date | None = None) -> Path:
    """Write ``grid`` as an ISG 2.0 file (node-registered, north row first, metres).

    Coordinates are written in ``dms`` when every bound and spacing is a whole number
    of arc-seconds, else in ``deg`` with six decimals, or with every digit needed when
    six decimals would not read back as the same lattice. Values are written with
    ``decimals`` decimals (ISG's files use 4), or by default with the shortest text that
    reads back bit for bit. NaN (no data) is written as :data:`ISG_NODATA`.
    ``data_type`` is ``"geoid"`` or ``"quasi-geoid"`` (default: the grid's quantity).
    """
    path = Path(path)
    data_type = data_type or grid.provenance.quantity or "geoid"
    if data_type not in ("geoid", "quasi-geoid"):
        raise ValueError(f"data_type must be 'geoid' or 'quasi-geoid', got {data_type!r}")
    units, texts = next((c for c in _coordinate_texts(grid) if _exact_lattice(*c, grid)), (None, None))
    if units is None:  # not expected: the last candidate is exact
        raise InputFileError(path, f"cannot write the lattice of {grid!r} exactly in an ISG header")
    prov = grid.provenance
    tide = {v: k for k, v in _TIDE.items()}.get(prov.tide_system, _UNSET)
    created = created or _dt.date.today()
    head = [
        ("model name", ":", prov.model or _UNSET), ("model year", ":", _UNSET), ("model type", ":", _UNSET),
        ("data type", ":", data_type), ("data units", ":", "meters"), ("data format", ":", "grid"),
        ("data ordering", ":", "N-to-S, W-to-E"), ("ref ellipsoid", ":", prov.ellipsoid or _UNSET),
        ("ref frame", ":", _UNSET), ("height datum", ":", _UNSET), ("tide system", ":", tide),
        ("coord type", ":", "geodetic"), ("coord units", ":", units), ("map projection", ":", _UNSET),
        ("EPSG code", ":", _UNSET),
        *[(key, "=", texts[key]) for key in ("lat min", "lat max", "lon min", "lon max", "delta lat", "delta lon")],
        ("nrows", "=", str(grid.shape[0])), ("ncols", "=", str(grid.shape[1])),
        ("nodata", "=", f"{ISG_NODATA:.4f}"), ("creation date", "=", created.strftime("%d/%m/%Y")),
        ("ISG format", "=", "2.0"),
    ]
    comment = [f"Written by geoidspline from {prov.source}" + (f" (sha256 {prov.sha256})" if prov.sha256 else "")]
    comment += list(prov.notes)
    lines = comment + [""] + ["begin_of_head " + "=" * 48]
    lines += [f"{key:<15}{sep} {value:>11}" if sep == "=" else f"{key:<15}{sep} {value}" for key, sep, value in head]
    lines.append("end_of_head " + "=" * 50)
    rows = np.asarray(grid.values, dtype=np.float64)[::-1]
    nodata = f"{ISG_NODATA:.4f}"
    if decimals is None:
        cells = [[nodata if v != v else repr(v) for v in row] for row in rows.tolist()]
    else:
        cells = [[nodata if v != v else f"{v:.{decimals}f}" for v in row] for row in rows.tolist()]
    width = max(len(nodata), max(len(c) for row in cells for c in row))
    lines += [" ".join(c.rjust(width) for c in row) for row in cells]
    atomic_write(path, ("\n".join(lines) + "\n").encode("utf-8"))
    return path
