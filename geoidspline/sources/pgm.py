"""GeographicLib's geoid PGM files: 16-bit pixels with an offset and a scale.

GeographicLib's geoid files are global and complete: the format has no no-data pixel
value, so every pixel is a value (a corrupt one is caught by the plausibility check of
:func:`~.files.finish_grid`).
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import InputFileError
from ..geodesy.limits import MAX_GRID_NODES
from .files import finish_grid, provenance_of, reader_faults
from .grid import GeoidGrid


_MAX_FIELD_DIGITS = 12


def looks_like_pgm(head: bytes, size: int) -> bool:
    """Whether a file starts like a binary PGM (``P5`` and a whitespace byte)."""
    return head[:2] == b"P5" and head[2:3].isspace()


# -- GeographicLib PGM ---------------------------------------------------------------
def pgm_header(path) -> dict:
    """Decode the header of a GeographicLib geoid PGM file.

    Returns ``width``, ``height``, ``maxval``, ``offset`` and ``scale`` (metres),
    ``data_offset`` (bytes), ``comments`` (dict of the ``# Key value`` lines) and
    ``description``.
    """
    path = Path(path)
    with reader_faults(path):
        if not path.is_file():
            raise InputFileError(path, "no such file" if not path.exists() else "not a regular file")
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
            window = data[pos:pos + _MAX_FIELD_DIGITS + 1]  # not data[pos:]: that copies the file
            match = re.match(rb"\d+", window)
            if match is None:
                raise InputFileError(path, f"PGM header has a non-numeric field at byte {pos}")
            if match.end() > _MAX_FIELD_DIGITS:
                raise InputFileError(path, f"PGM header has a field of more than {_MAX_FIELD_DIGITS} digits at byte {pos}")
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
    if width * height > MAX_GRID_NODES:
        raise InputFileError(
            path, f"PGM raster {width} x {height} has more than the {MAX_GRID_NODES:,} nodes geoidspline reads"
        )
    if width != 2 * (height - 1):
        # Same rule as GeographicLib's "Raster size mismatch": equal spacing 180/(height-1) = 360/width.
        raise InputFileError(
            path, f"PGM raster {width} x {height} has unequal spacing; a global geoid grid needs width == 2*(height-1)"
        )
    origin = comments.get("Origin")
    if origin is not None and origin.split() != ["90N", "0E"]:
        raise InputFileError(path, f"PGM '# Origin {origin}' is not supported (only 90N 0E)")
    return header


def check_pgm_header(path, head: bytes, size: int) -> dict:
    """The header of a PGM file of ``size`` bytes starting with ``head``, checked against
    the size before the pixels are read."""
    header = _parse_pgm_header(path, head)
    width, height, start = header["width"], header["height"], header["data_offset"]
    expected = width * height * 2
    if size - start != expected:
        raise InputFileError(
            path,
            f"PGM data is {size - start} bytes after the header (byte {start}), "
            f"but {width} x {height} uint16 pixels need {expected}",
        )
    return header


def read_pgm(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
    head = check_pgm_header(path, data[:1 << 16], len(data))
    width, height, start = head["width"], head["height"], head["data_offset"]
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
    prov = provenance_of(path, sha256, model=model, notes=notes)
    return finish_grid(path, lat, lon, values, prov, complete=complete)
