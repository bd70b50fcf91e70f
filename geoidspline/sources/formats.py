"""Readers and writers of geoid grid files.

:func:`read_grid` reads PROJ GTX, CF netCDF, NGA ``WW15MGH.DAC``, GeographicLib PGM, ISG,
PROJ GeoTIFF, GSI ASCII and NGS ``.bin`` files into a :class:`~geoidspline.sources.grid.GeoidGrid`
(latitude ascending, longitude ascending, metres). Every check is strict, and a failure raises
:class:`~geoidspline.errors.InputFileError` whose message names the file and the rule
it breaks, e.g. ``"egm.gtx: GTX file is 4152000 bytes, header says 721 x 1440 float32
nodes need 4153000"``.

The format is decided by the content, never by the name: magic bytes (netCDF/HDF5,
TIFF, PGM), then a header (ISG keys, a GSI header line, an NGS header plausible in one
byte order, a GTX header that agrees with the file size), then size (NGA's DAC). The extension only chooses which format's rule to quote when the content matches
none. A spherical-harmonic model given as a grid is named as such.

:func:`write_gtx` and :func:`write_netcdf` write a grid back (tests, fixtures, export).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from .._files import sha256_file
from ..errors import InputFileError
from ..geodesy.limits import MAX_GRID_NODES
from .dac import check_dac_size, looks_like_dac, read_dac
from .files import check_catalogue_copy, reader_faults
from .geotiff import looks_like_geotiff, read_geotiff
from .grid import GeoidGrid
from .gsi import looks_like_gsi, read_gsi
from .gtx import GTX_NODATA, gtx_header, read_gtx, write_gtx
from .isg import looks_like_isg, read_isg
from .ngs import ngs_header, read_ngs
from .netcdf import NETCDF_MAGIC, NETCDF_SUFFIXES, check_netcdf_header, read_netcdf, write_netcdf
from .pgm import check_pgm_header, looks_like_pgm, pgm_header, read_pgm

__all__ = ["read_grid", "write_gtx", "write_netcdf", "pgm_header", "GTX_NODATA", "GridFormat", "GRID_FORMATS",
           "grid_format_of"]

#: Bytes read to recognise a format (an ISG or ICGEM header may follow pages of text).
HEAD_BYTES = 1 << 16

#: Largest file read into memory for a grid: 16 bytes per node covers text formats.
MAX_GRID_FILE_BYTES = 16 * MAX_GRID_NODES


@dataclass(frozen=True)
class GridFormat:
    """One grid file format: how to recognise it, check it early, and read it.

    ``looks_like(head, size)`` tests the first :data:`HEAD_BYTES` bytes and the file size;
    ``check_header(path, head, size)`` raises, before the body is read, when the header
    contradicts the size or declares an absurd grid; ``read`` is
    ``(path, data, sha256, complete)``, or ``(path, sha256, complete)`` when ``by_path``.
    """

    name: str
    label: str
    suffixes: tuple[str, ...]
    looks_like: Callable[[bytes, int], bool]
    read: Callable[..., GeoidGrid]
    check_header: Callable[[Path, bytes, int], object] | None = None
    by_path: bool = False


def _header_accepts(check_header):
    """``looks_like`` of a format recognised by its header alone: the header check passes."""
    def looks_like(head: bytes, size: int) -> bool:
        try:
            check_header("", head, size)
        except InputFileError:
            return False
        return True
    return looks_like


#: The formats, in the order their content is tested: magic bytes first, then a header
#: that must agree with the size, then the size alone.
GRID_FORMATS = (
    GridFormat("netcdf", "CF netCDF", tuple(sorted(NETCDF_SUFFIXES)), lambda head, size: head.startswith(NETCDF_MAGIC),
               read_netcdf, check_netcdf_header, by_path=True),
    GridFormat("geotiff", "PROJ GeoTIFF", (".tif", ".tiff"), lambda head, size: looks_like_geotiff(head),
               read_geotiff, by_path=True),
    GridFormat("pgm", "GeographicLib PGM", (".pgm",), looks_like_pgm, read_pgm, check_pgm_header),
    GridFormat("isg", "ISG", (".isg",), lambda head, size: looks_like_isg(head), read_isg),
    GridFormat("gsi", "GSI ASCII", (".asc",), lambda head, size: looks_like_gsi(head), read_gsi),
    GridFormat("ngs", "NGS .bin", (".bin",), _header_accepts(ngs_header), read_ngs, ngs_header),
    GridFormat("gtx", "PROJ GTX", (".gtx",), _header_accepts(gtx_header), read_gtx, gtx_header),
    GridFormat("dac", "NGA WW15MGH.DAC", (".dac",), looks_like_dac, read_dac, check_dac_size),
)


def grid_format_of(head: bytes, size: int) -> GridFormat | None:
    """The grid format the content matches, or None."""
    return next((fmt for fmt in GRID_FORMATS if fmt.looks_like(head, size)), None)


def _not_a_grid(path: Path) -> InputFileError | None:
    """The error for a model, a correction or a broken gzip given as a grid, else None."""
    from .harmonics.models import model_file_kind

    kind = model_file_kind(path)
    if kind is not None and kind.startswith("corrupt"):
        return InputFileError(path, kind)
    if kind in ("icgem", "nga"):
        label = "an ICGEM .gfc" if kind == "icgem" else "NGA coefficient text (n m C S sigmaC sigmaS)"
        return InputFileError(path, f"is a spherical-harmonic model ({label}), not a grid: give it as a model source")
    if kind == "nga-correction":
        return InputFileError(
            path, "is a zeta-to-N correction (NGA CORRCOEF text: n m C S), not a grid: give it as a model's correction"
        )
    return None


def _unrecognised(path: Path) -> InputFileError:
    formats = "; ".join(f"{fmt.label} ({', '.join(fmt.suffixes)})" for fmt in GRID_FORMATS)
    return InputFileError(
        path, f"unrecognised grid format: the content matches none of {formats} "
        "(recognised by content: netCDF/HDF5, TIFF and PGM magic bytes, an ISG header, a GSI header line, "
        "an NGS .bin header that agrees with the file size in one byte order, "
        "a GTX header that agrees with the file size, the exact size of WW15MGH.DAC)",
    )


def _choice(path, fmt: GridFormat, band, variable) -> dict:
    """The band/variable keyword of ``fmt``'s reader, refusing one the format has not."""
    if band is not None and fmt.name != "geotiff":
        raise InputFileError(path, f"is a {fmt.label} grid, which has one band: --band applies to GeoTIFF files")
    if variable is not None and fmt.name != "netcdf":
        raise InputFileError(path, f"is a {fmt.label} grid, which has no variables: --variable applies to netCDF files")
    if fmt.name == "geotiff":
        return {"band": band}
    if fmt.name == "netcdf":
        return {"variable": variable}
    return {}


# -- dispatch ------------------------------------------------------------------------
def read_grid(path, *, complete: bool = False, allow_unknown_copy: bool = False, band: int | None = None,
              variable: str | None = None) -> GeoidGrid:
    """Read a geoid grid file (PROJ .gtx, CF netCDF, NGA .DAC, GeographicLib .pgm, ISG,
    PROJ GeoTIFF, GSI ASCII, NGS .bin).

    ``band`` (1-based) picks the band of a GeoTIFF with several, ``variable`` the
    variable of a netCDF file with several candidates; either is refused for a format
    that has no such choice, and a file with several is refused without it, the
    message listing the choices.

    The format is taken from the content (see the module documentation); the extension
    only picks the rule quoted when the content matches no format. Nodes without data
    (the format's no-data value, netCDF fill values, NaN) become NaN;
    ``complete=True`` rejects any such node. Values beyond the geoid's physical range are
    refused (:func:`~.files.check_plausible`). A file named like a catalogue file
    (``egm96_15.gtx``, ``WW15MGH.DAC``, ...) must be one of the catalogue's known copies
    (sha256) unless ``allow_unknown_copy=True``. Every failure, including out of memory
    and I/O errors, is an :class:`InputFileError` naming the file and the rule broken.
    """
    path = Path(path)
    with reader_faults(path):
        if not path.is_file():
            raise InputFileError(path, "no such file" if not path.exists() else "not a regular file")
        size = path.stat().st_size
        with open(path, "rb") as fh:
            head = fh.read(HEAD_BYTES)
        fmt = grid_format_of(head, size)
        if fmt is None:
            not_a_grid = _not_a_grid(path)
            if not_a_grid is not None:
                raise not_a_grid
            # the name only picks the format whose rule the error quotes
            suffix = path.suffix.lower()
            fmt = next((f for f in GRID_FORMATS if suffix in f.suffixes), None)
            if fmt is None:
                raise _unrecognised(path)
        if fmt.check_header is not None:
            fmt.check_header(path, head, size)  # raises before the body is read
        choice = _choice(path, fmt, band, variable)
        if fmt.by_path:
            sha256 = sha256_file(path)
            check_catalogue_copy(path, sha256, allow_unknown_copy)
            return fmt.read(path, sha256, complete, **choice)
        if size > MAX_GRID_FILE_BYTES:
            raise InputFileError(path, f"{fmt.label} file is {size:,} bytes, more than the {MAX_GRID_FILE_BYTES:,} "
                                 "geoidspline reads for a grid")
        data = path.read_bytes()
        sha256 = hashlib.sha256(data).hexdigest()
        check_catalogue_copy(path, sha256, allow_unknown_copy)
        return fmt.read(path, data, sha256, complete)
