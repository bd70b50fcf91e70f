"""GSI's ASCII geoid grids (Geospatial Information Authority of Japan, e.g. ``gsigeo2011_ver2_2.asc``).

Layout (as GSI distributes GSIGEO2011, and as the MIT-licensed ``japan-geoid`` package
parses it):

- line 1: ``lat0 lon0 dlat dlon nlat nlon ikind version``, e.g.
  ``20.00000 120.00000 0.016667 0.025000 1801 1201 1 ver2.2``: the south-west node, the
  spacings (degrees, rounded to 6 decimals: 0.016667 is 1'), the numbers of latitude
  rows and longitude columns, a kind code and a version label;
- then the values in metres with 4 decimals, row by row from the south row (lat0)
  northward, each row west to east; GSI writes 28 values per line and starts every row
  on a new line, but any whitespace layout is read;
- ``999.0000`` marks a node without data (GSIGEO2011 has no data over the sea).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..errors import InputFileError
from ._common import MAX_TEXT_NODES, decimals_tolerance, parse_values, snap_origin, snap_spacing
from .files import finish_grid, provenance_of
from .grid import GeoidGrid

__all__ = ["GSI_NODATA", "looks_like_gsi", "read_gsi", "write_gsi"]

#: GSI's no-data value (metres).
GSI_NODATA = 999.0
#: The datum of GSI's geoid grids (GSIGEO2011 is on JGD2011, GRS80): EPSG's JGD2011.
JGD2011 = "EPSG:6668"
#: Values per line in GSI's files.
GSI_VALUES_PER_LINE = 28

_NUMBER = r"[+-]?(?:\d+\.?\d*|\.\d+)"
_HEADER = re.compile(
    rf"^\s*({_NUMBER})\s+({_NUMBER})\s+({_NUMBER})\s+({_NUMBER})\s+(\d+)\s+(\d+)\s+([+-]?\d+)\s+(\S+)\s*$"
)


def _first_line(head: bytes) -> str | None:
    line = head.split(b"\n", 1)[0].rstrip(b"\r")
    try:
        return line.decode("ascii")
    except UnicodeDecodeError:
        return None


def looks_like_gsi(head: bytes) -> bool:
    """Whether a file's first bytes start with a GSI ASCII header line
    (``lat0 lon0 dlat dlon nlat nlon ikind version``: six numbers, an integer, a label)."""
    line = _first_line(head)
    return line is not None and _HEADER.match(line) is not None


def _header(path, line: str) -> dict:
    match = _HEADER.match(line)
    if match is None:
        tokens = line.split()
        raise InputFileError(
            path,
            f"GSI header line {line.strip()[:80]!r} has {len(tokens)} fields; expected 8: "
            "lat0 lon0 dlat dlon nlat nlon ikind version (nlat, nlon, ikind whole numbers)",
        )
    lat0_t, lon0_t, dlat_t, dlon_t, nlat_t, nlon_t, ikind_t, version = match.groups()
    nlat, nlon = int(nlat_t), int(nlon_t)
    dlat, dlon = float(dlat_t), float(dlon_t)
    if not (dlat > 0 and dlon > 0):
        raise InputFileError(path, f"GSI header spacings dlat={dlat_t}, dlon={dlon_t} must be > 0 degrees")
    if nlat < 2 or nlon < 2:
        raise InputFileError(path, f"GSI header nlat={nlat}, nlon={nlon}: a grid needs at least 2 x 2 nodes")
    if nlat * nlon > MAX_TEXT_NODES:
        raise InputFileError(path, f"GSI header declares {nlat} x {nlon} nodes, more than {MAX_TEXT_NODES:,}")
    dlat = snap_spacing(dlat, decimals_tolerance(dlat_t))
    dlon = snap_spacing(dlon, decimals_tolerance(dlon_t))
    lat0 = snap_origin(float(lat0_t), dlat, decimals_tolerance(lat0_t))
    lon0 = snap_origin(float(lon0_t), dlon, decimals_tolerance(lon0_t))
    return dict(lat0=lat0, lon0=lon0, dlat=dlat, dlon=dlon, nlat=nlat, nlon=nlon, ikind=int(ikind_t), version=version)


def read_gsi(path, data: bytes, sha256: str, complete: bool = False) -> GeoidGrid:
    """Read a GSI ASCII geoid file's bytes ``data`` into a :class:`GeoidGrid` (metres).

    Raises :class:`InputFileError` naming ``path`` and the rule broken.
    """
    path = Path(path)
    try:
        text = data.decode("ascii")
    except UnicodeDecodeError as exc:
        raise InputFileError(path, f"GSI ASCII geoid file has a non-ASCII byte at offset {exc.start}") from None
    first, _, body = text.partition("\n")
    head = _header(path, first)
    nlat, nlon = head["nlat"], head["nlon"]
    values = parse_values(path, body, 2, "GSI data")
    if values.size != nlat * nlon:
        raise InputFileError(
            path, f"GSI data has {values.size} values, but the header's nlat x nlon = {nlat} x {nlon} needs {nlat * nlon}"
        )
    grid = values.reshape(nlat, nlon)  # south row first: latitude ascending already
    grid[grid == GSI_NODATA] = np.nan
    label = head["version"]
    name_hint = re.match(r"(gsigeo\d{4}|jpgeo\d{4})", path.name, re.IGNORECASE)  # only a label, never the format
    model = f"{name_hint.group(1).upper()} {label}" if name_hint and name_hint.group(1).upper() not in label.upper() else label
    prov = provenance_of(
        path, sha256, model=model, ellipsoid="GRS80", datum=JGD2011,
        notes=(f"GSI ASCII geoid grid, version label {label}, ikind {head['ikind']}",),
    )
    latitude = head["lat0"] + head["dlat"] * np.arange(nlat)
    longitude = head["lon0"] + head["dlon"] * np.arange(nlon)
    return finish_grid(path, latitude, longitude, grid, prov, complete=complete)


def write_gsi(path, grid: GeoidGrid, *, version: str = "ver2.2", ikind: int = 1) -> Path:
    """Write ``grid`` in GSI's ASCII layout (values rounded to 0.1 mm; NaN -> 999.0000).

    The header is GSI's ``%.5f %.5f %.6f %.6f nlat nlon ikind version`` when those
    digits read back as the grid's lattice, else every digit needed; 28 values per
    line, each row starting a new line, south row first. ``version`` is one word.
    """
    path = Path(path)
    if not re.fullmatch(r"\S+", version):
        raise ValueError(f"version must be one word, got {version!r}")
    nlat, nlon = grid.shape
    numbers = (grid.latitude[0], grid.longitude[0], grid.latitude_spacing, grid.longitude_spacing)
    header = "{:.5f} {:.5f} {:.6f} {:.6f}".format(*numbers) + f" {nlat} {nlon} {int(ikind)} {version}"
    back = _header(path, header)
    worst = max(
        float(np.max(np.abs(back["lat0"] + back["dlat"] * np.arange(nlat) - grid.latitude))),
        float(np.max(np.abs(back["lon0"] + back["dlon"] * np.arange(nlon) - grid.longitude))),
    )
    if worst > 1e-11:  # GSI's digits would move the nodes: write them all
        header = " ".join(f"{v:.20f}" for v in numbers) + f" {nlat} {nlon} {int(ikind)} {version}"
    values = np.where(np.isnan(grid.values), GSI_NODATA, np.round(grid.values, 4))
    lines = [header]
    for row in values.tolist():
        for start in range(0, nlon, GSI_VALUES_PER_LINE):
            # " %8.4f" is GSI's 9 columns, and keeps a blank before a 9-character -100.0000
            lines.append("".join(f" {v:8.4f}" for v in row[start:start + GSI_VALUES_PER_LINE]))
    atomic_write(path, ("\n".join(lines) + "\n").encode("ascii"))
    return path
