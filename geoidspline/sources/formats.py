"""Readers and writers of geoid grid files.

:func:`read_grid` reads PROJ GTX, CF netCDF, NGA ``WW15MGH.DAC``, GeographicLib PGM,
ISG, PROJ GeoTIFF and GSI ASCII files into a :class:`~geoidspline.sources.grid.GeoidGrid` (latitude ascending, longitude
ascending, metres). Every check is strict, and a failure raises
:class:`~geoidspline.errors.InputFileError` whose message names the file and the rule
it breaks, e.g. ``"egm.gtx: GTX file is 4152000 bytes, header says 721 x 1440 float32
nodes need 4153000"``.

:func:`write_gtx` and :func:`write_netcdf` write a grid back (tests, fixtures, export).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from .._files import sha256_file
from ..errors import InputFileError
from .dac import read_dac
from .geotiff import looks_like_geotiff, read_geotiff
from .grid import GeoidGrid
from .gsi import looks_like_gsi, read_gsi
from .gtx import GTX_NODATA, read_gtx, write_gtx
from .isg import looks_like_isg, read_isg
from .netcdf import NETCDF_MAGIC, NETCDF_SUFFIXES, read_netcdf, write_netcdf
from .pgm import pgm_header, read_pgm

__all__ = ["read_grid", "write_gtx", "write_netcdf", "pgm_header", "GTX_NODATA"]


# -- dispatch ------------------------------------------------------------------------
def read_grid(path, *, complete: bool = False) -> GeoidGrid:
    """Read a geoid grid file (PROJ .gtx, CF netCDF, NGA .DAC, GeographicLib .pgm, ISG,
    PROJ GeoTIFF, GSI ASCII).

    The format is taken from the content (netCDF, TIFF and PGM magic bytes, an ISG
    header, a GSI header line) or else the extension.
    ``complete=True`` rejects any node without data. Errors are
    :class:`InputFileError` naming the file and the rule broken.
    """
    path = Path(path)
    if not path.is_file():
        raise InputFileError(path, "no such file" if not path.exists() else "not a regular file")
    suffix = path.suffix.lower()
    with open(path, "rb") as fh:
        magic = fh.read(1 << 16)  # an ISG header may follow pages of free text
    if magic.startswith(NETCDF_MAGIC) or suffix in NETCDF_SUFFIXES:
        if not magic.startswith(NETCDF_MAGIC):
            raise InputFileError(path, f"not a netCDF file: starts with {magic[:4]!r}, not CDF or HDF5 magic bytes")
        return read_netcdf(path, sha256_file(path), complete)
    if looks_like_geotiff(magic) or suffix in (".tif", ".tiff"):
        return read_geotiff(path, sha256_file(path), complete)
    readers = {".gtx": read_gtx, ".dac": read_dac, ".pgm": read_pgm, ".isg": read_isg, ".asc": read_gsi}
    by_content = [(magic.startswith(b"P5"), read_pgm), (looks_like_isg(magic), read_isg),
                  (looks_like_gsi(magic), read_gsi)]
    reader = next((r for found, r in by_content if found), readers.get(suffix))
    if reader is None:
        raise InputFileError(
            path,
            f"unrecognised grid format (extension '{path.suffix}'); supported: .gtx (PROJ GTX), "
            ".nc/.nc4/.cdf (CF netCDF), .dac (NGA WW15MGH.DAC), .pgm (GeographicLib), .isg (ISG), "
            ".tif (PROJ GeoTIFF), .asc (GSI ASCII)",
        )
    data = path.read_bytes()
    return reader(path, data, hashlib.sha256(data).hexdigest(), complete)
