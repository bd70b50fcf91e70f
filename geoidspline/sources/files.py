"""What every grid reader shares: the file's digest and provenance, axis checks, the
360° duplicate column, the final grid, and atomic writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import InputFileError
from .base import Provenance
from .catalogue import entry_for_file
from .grid import GeoidGrid


def provenance_of(path: Path, sha256: str, **known) -> Provenance:
    """Provenance of a file, completed from the catalogue when the file name is known there."""


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


def drop_repeated_column(path, lon, values):
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


def finish_grid(path, lat, lon, values, provenance, *, complete=False) -> GeoidGrid:
    """Normalise the 360° duplicate column, check the NaNs, build the grid."""
    lon, values = drop_repeated_column(path, lon, values)
    nan = int(np.isnan(values).sum())
    if nan == values.size:
        raise InputFileError(path, f"all {nan} nodes are NaN (no data)")
    if complete and nan:
        raise InputFileError(path, f"{nan} of {values.size} nodes are NaN (no data) in a grid that must be complete")
    try:
        return GeoidGrid(lat, lon, values, provenance)
    except InputFileError as exc:
        raise InputFileError(path, exc.rule) from None


def regular_axis(path, coord, name, period):
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
