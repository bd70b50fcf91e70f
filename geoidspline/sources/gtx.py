"""PROJ's GTX grids: a 40-byte big-endian header and float32 rows from the south.

No data: PROJ marks a node without data with -88.8888 (``GTXVerticalShiftGrid::isNodata``
compares the float32 value with ``-88.88880f``); such nodes become NaN here. Writers
that print the marker with other precisions (-88.888, -88.88888, ...) are read the same
way: a float32 equal to ``-88.`` followed by three to eight 8s. PROJ also reads any
value beyond ±1000 m as no data; geoidspline refuses such a file instead (the
plausibility check in :func:`~.files.finish_grid` names the node), because a value
the file does not declare as no data may as well be a corrupt one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..errors import InputFileError
from ..geodesy.limits import MAX_GRID_NODES
from .files import finish_grid, provenance_of
from .grid import GeoidGrid

#: The value PROJ's GTX format uses for a node without data (metres).
GTX_NODATA = -88.8888

#: The float32 values read as no data: -88.888 ... -88.88888888 (PROJ writes -88.8888).
GTX_NODATA_PATTERNS = np.array([float("-88." + "8" * k) for k in range(3, 9)], dtype=np.float32)

GTX_HEADER_BYTES = 40


@dataclass(frozen=True)
class GtxHeader:
    """A GTX header: first node (degrees), spacings (degrees), rows and columns."""

    lat0: float
    lon0: float
    dlat: float
    dlon: float
    rows: int
    cols: int

    def __str__(self):
        return (f"(lat0={self.lat0}, lon0={self.lon0}, dlat={self.dlat}, dlon={self.dlon}, "
                f"rows={self.rows}, cols={self.cols})")


def gtx_header(path, head: bytes, size: int) -> GtxHeader:
    """The header of a GTX file of ``size`` bytes whose first bytes are ``head``, checked
    (finite values, positive spacings and counts, latitudes within ±90°, at most
    :data:`~geoidspline.geodesy.limits.MAX_GRID_NODES` nodes, and a file size equal to
    40 + rows × cols × 4) before anything else is read."""
    if size < GTX_HEADER_BYTES or len(head) < GTX_HEADER_BYTES:
        raise InputFileError(path, f"GTX file is {size} bytes, shorter than its {GTX_HEADER_BYTES}-byte header")
    lat0, lon0, dlat, dlon = (float(v) for v in np.frombuffer(head, ">f8", count=4))
    rows, cols = (int(v) for v in np.frombuffer(head, ">i4", count=2, offset=32))
    header = GtxHeader(lat0, lon0, dlat, dlon, rows, cols)
    if not all(np.isfinite(v) for v in (lat0, lon0, dlat, dlon)):
        raise InputFileError(path, f"GTX header has non-finite values {header}")
    if not (dlat > 0 and dlon > 0):
        raise InputFileError(path, f"GTX header spacing must be > 0 degrees, got dlat={dlat}, dlon={dlon}")
    if rows <= 0 or cols <= 0:
        raise InputFileError(path, f"GTX header must have rows > 0 and cols > 0, got rows={rows}, cols={cols}")
    if rows * cols > MAX_GRID_NODES:
        raise InputFileError(
            path, f"GTX header declares {rows} x {cols} = {rows * cols:,} nodes, more than the "
            f"{MAX_GRID_NODES:,} geoidspline reads (a global 1' grid has 233 million) {header}"
        )
    expected = GTX_HEADER_BYTES + rows * cols * 4
    if size != expected:
        raise InputFileError(
            path, f"GTX file is {size} bytes, header says {rows} x {cols} float32 nodes need {expected}"
        )
    lat1 = lat0 + (rows - 1) * dlat
    if lat0 < -90.0 - 1e-9 or lat1 > 90.0 + 1e-9:
        raise InputFileError(path, f"GTX latitudes {lat0}..{lat1} go beyond [-90, 90] degrees {header}")
    return header


# -- PROJ GTX ------------------------------------------------------------------------
def read_gtx(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    h = gtx_header(path, data[:GTX_HEADER_BYTES], len(data))
    raw = np.frombuffer(data, ">f4", offset=GTX_HEADER_BYTES).reshape(h.rows, h.cols)
    bad = int((~np.isfinite(raw)).sum())
    if bad:
        raise InputFileError(
            path, f"{bad} nodes are NaN or infinite; GTX marks no data with {GTX_NODATA}, not NaN"
        )
    values = raw.astype(np.float64)
    values[np.isin(raw, GTX_NODATA_PATTERNS)] = np.nan
    lat = h.lat0 + h.dlat * np.arange(h.rows)
    lon = h.lon0 + h.dlon * np.arange(h.cols)
    return finish_grid(path, lat, lon, values, provenance_of(path, sha256), complete=complete)


def write_gtx(path, grid: GeoidGrid) -> Path:
    """Write ``grid`` as a PROJ GTX file (big-endian, float32 metres, NaN -> -88.8888)."""
    path = Path(path)
    rows, cols = grid.shape
    header = np.array(
        [grid.latitude[0], grid.longitude[0], grid.latitude_spacing, grid.longitude_spacing], dtype=">f8"
    ).tobytes() + np.array([rows, cols], dtype=">i4").tobytes()
    values = np.where(np.isnan(grid.values), GTX_NODATA, grid.values).astype(">f4")
    atomic_write(path, header + values.tobytes())
    return path
