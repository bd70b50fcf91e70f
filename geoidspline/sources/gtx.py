"""PROJ's GTX grids: a 40-byte big-endian header and float32 rows from the south."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .._files import atomic_write
from ..errors import InputFileError
from .files import finish_grid, provenance_of
from .grid import GeoidGrid

#: The value PROJ's GTX format uses for a node without data (metres).
GTX_NODATA = -88.8888


_GTX_HEADER_BYTES = 40


# -- PROJ GTX ------------------------------------------------------------------------
def read_gtx(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
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
