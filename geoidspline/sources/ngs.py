"""NGS ``.bin`` geoid grids (US National Geodetic Survey: GEOID18, GEOID12B, USGG, xGEOID).

Layout (NGS's ``intg``/``geoid`` programs; GDAL's NGSGEOID driver and OSSIM read the
same), a 44-byte header then the values:

- ``slat, wlon, dlat, dlon``: float64, the south-west node and the spacings (degrees);
  ``wlon`` is often given east of Greenwich (GEOID18 CONUS starts at 230.0, i.e. 130°W);
- ``nlat, nlon, ikind``: int32, the numbers of rows and columns, and the value kind
  (1: float32, the only kind NGS publishes);
- ``nlat`` rows of ``nlon`` float32 values in metres, the south row first, each west to
  east.

NGS publishes the files in both byte orders (little-endian for PCs, big-endian for
workstations: ``g2012bu0.bin`` and its ``_be`` twin). The order is detected from the
header itself, never from the file name: exactly one order must give a plausible header
(ikind 1, counts of at least 2, finite positive spacings, latitudes within ±90°, at most
360° of longitude, and a file size of 44 + 4 · nlat · nlon bytes).

The format carries no datum or tide system: NGS's hybrid geoids (GEOID18, GEOID12B) are
on NAD83(2011), its gravimetric ones (USGG, xGEOID) on IGS08/ITRF, and the reader says so
in the provenance (:mod:`geoidspline.sources.reference` then applies the one datum rule).
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

__all__ = ["NGS_HEADER_BYTES", "NgsHeader", "ngs_header", "read_ngs", "write_ngs"]

NGS_HEADER_BYTES = 44
_ORDERS = {"<": "little-endian", ">": "big-endian"}


@dataclass(frozen=True)
class NgsHeader:
    """A decoded NGS header: south-west node and spacings (degrees), counts, kind, byte order."""

    slat: float
    wlon: float
    dlat: float
    dlon: float
    nlat: int
    nlon: int
    ikind: int
    byte_order: str  # "<" or ">"


def _decode(head: bytes, order: str) -> NgsHeader:
    slat, wlon, dlat, dlon = (float(v) for v in np.frombuffer(head, order + "f8", count=4))
    nlat, nlon, ikind = (int(v) for v in np.frombuffer(head, order + "i4", count=3, offset=32))
    return NgsHeader(slat, wlon, dlat, dlon, nlat, nlon, ikind, order)


def _implausible(h: NgsHeader, size: int) -> str | None:
    """Why ``h`` cannot be the header of an NGS grid of ``size`` bytes, or None."""
    if h.ikind != 1:
        return f"ikind {h.ikind} (NGS grids are ikind 1, float32)"
    if not all(np.isfinite(v) for v in (h.slat, h.wlon, h.dlat, h.dlon)):
        return "non-finite coordinates"
    if not (0.0 < h.dlat <= 180.0 and 0.0 < h.dlon <= 360.0):
        return f"spacings dlat={h.dlat:g}, dlon={h.dlon:g} degrees"
    if h.nlat < 2 or h.nlon < 2:
        return f"nlat={h.nlat}, nlon={h.nlon} (a grid needs at least 2 x 2 nodes)"
    if h.nlat * h.nlon > MAX_GRID_NODES:
        return f"{h.nlat} x {h.nlon} nodes, more than {MAX_GRID_NODES:,}"
    north = h.slat + (h.nlat - 1) * h.dlat
    if h.slat < -90.0 - 1e-9 or north > 90.0 + 1e-9:
        return f"latitudes {h.slat:g}..{north:g}"
    if not -360.0 <= h.wlon <= 360.0 or (h.nlon - 1) * h.dlon > 360.0 + 1e-9:
        return f"longitudes from {h.wlon:g} over {(h.nlon - 1) * h.dlon:g} degrees"
    expected = NGS_HEADER_BYTES + 4 * h.nlat * h.nlon
    if size != expected:
        return f"file size {size} bytes where {h.nlat} x {h.nlon} float32 nodes need {expected}"
    return None


def ngs_header(path, head: bytes, size: int) -> NgsHeader:
    """The header of an NGS ``.bin`` file, in the one byte order that makes it plausible."""
    if size < NGS_HEADER_BYTES or len(head) < NGS_HEADER_BYTES:
        raise InputFileError(path, f"NGS .bin file is {size} bytes, shorter than its {NGS_HEADER_BYTES}-byte header")
    found, reasons = [], []
    for order, label in _ORDERS.items():
        header = _decode(head[:NGS_HEADER_BYTES], order)
        reason = _implausible(header, size)
        if reason is None:
            found.append(header)
        else:
            reasons.append(f"{label}: {reason}")
    if len(found) == 1:
        return found[0]
    if not found:
        raise InputFileError(path, "not an NGS .bin geoid grid in either byte order (" + "; ".join(reasons) + ")")
    raise InputFileError(path, "NGS .bin header is plausible in both byte orders; cannot tell which one the file uses")


def read_ngs(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    """Read an NGS ``.bin`` grid's bytes ``data`` into a :class:`GeoidGrid` (metres).

    Longitudes east of 180° (``wlon`` = 230 for 130°W) are brought to -180..180 when the
    whole grid lies east of 180°. NaN values are nodes without data.
    """
    h = ngs_header(path, data[:NGS_HEADER_BYTES], len(data))
    raw = np.frombuffer(data, h.byte_order + "f4", offset=NGS_HEADER_BYTES).reshape(h.nlat, h.nlon)
    if np.isinf(raw).any():
        raise InputFileError(path, f"NGS .bin grid has {int(np.isinf(raw).sum())} infinite values")
    values = raw.astype(np.float64)
    west = h.wlon - 360.0 if h.wlon >= 180.0 else h.wlon
    lat = h.slat + h.dlat * np.arange(h.nlat)
    lon = west + h.dlon * np.arange(h.nlon)
    prov = provenance_of(
        path, sha256, datum=None,
        notes=(f"NGS .bin geoid grid, {_ORDERS[h.byte_order]}, ikind {h.ikind}, west longitude {h.wlon:g} in the file",
               "NGS .bin states no datum: NGS's hybrid geoids (GEOID18, GEOID12B) are on NAD83(2011), "
               "its gravimetric ones (USGG, xGEOID) on IGS08/ITRF"),
    )
    return finish_grid(path, lat, lon, values, prov, complete=complete)


def write_ngs(path, grid: GeoidGrid, *, byte_order: str = "<", east_longitudes: bool = False) -> Path:
    """Write ``grid`` in NGS's ``.bin`` layout (``byte_order`` ``"<"`` or ``">"``); with
    ``east_longitudes`` the west longitude is written in 0..360 as NGS does. NaN is kept."""
    path = Path(path)
    if byte_order not in _ORDERS:
        raise ValueError(f"byte_order must be '<' or '>', got {byte_order!r}")
    nlat, nlon = grid.shape
    west = float(grid.longitude[0])
    if east_longitudes and west < 0.0:
        west += 360.0
    header = np.array([grid.latitude[0], west, grid.latitude_spacing, grid.longitude_spacing],
                      dtype=byte_order + "f8").tobytes()
    header += np.array([nlat, nlon, 1], dtype=byte_order + "i4").tobytes()
    atomic_write(path, header + np.asarray(grid.values, dtype=byte_order + "f4").tobytes())
    return path
