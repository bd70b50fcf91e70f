"""GeographicLib's geoid PGM files: 16-bit pixels with an offset and a scale."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..errors import InputFileError
from .files import finish_grid, provenance_of
from .grid import GeoidGrid


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


def read_pgm(path: Path, data: bytes, sha256: str, complete: bool) -> GeoidGrid:
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
    prov = provenance_of(path, sha256, model=model, notes=notes)
    return finish_grid(path, lat, lon, values, prov, complete=complete)
