"""What every reader shares: the file's digest and provenance, the catalogue's known
copies, axis checks, the 360° duplicate column, the plausibility of the values, the
final grid, and faults turned into messages.

Every grid reader ends in :func:`finish_grid`, so its checks hold for every format: no
grid without data, no hole in a grid that must be complete, and no value beyond the
geoid's physical range (:mod:`geoidspline.geodesy.limits`).
"""

from __future__ import annotations

import contextlib
import zlib
from pathlib import Path

import numpy as np

from ..errors import GeoidSplineError, InputFileError
from ..geodesy.limits import GEOID_RANGE_M, MAX_ABS_UNDULATION_M
from .base import Provenance
from .catalogue import entry_for_file
from .grid import GeoidGrid


@contextlib.contextmanager
def reader_faults(path):
    """Turn what the system raises while reading ``path`` into one InputFileError naming it.

    Out of memory, an I/O error (permission, EIO, a directory), a broken gzip or deflate
    stream: never a traceback, never a partial result.
    """
    try:
        yield
    except GeoidSplineError:
        raise
    except MemoryError:
        raise InputFileError(path, "not enough memory to read this file") from None
    except (zlib.error, EOFError) as exc:
        raise InputFileError(path, f"corrupt or truncated compressed data: {exc}") from None
    except OSError as exc:  # includes gzip.BadGzipFile
        raise InputFileError(path, f"cannot read the file: {exc.strerror or exc}") from None


def check_catalogue_copy(path: Path, sha256: str, allow_unknown_copy: bool = False) -> None:
    """Refuse a file named like a catalogue file whose bytes are none of its known copies.

    A bit-flipped ``WW15MGH.DAC`` reads as a plausible grid with values off by up to
    164 m; only its digest tells. ``allow_unknown_copy=True`` reads it anyway (another
    genuine copy of the product): the provenance then notes the unknown digest.
    """
    entry = entry_for_file(Path(path).name)
    if entry is None or not entry.sha256 or sha256 in entry.sha256 or allow_unknown_copy:
        return
    raise InputFileError(
        path,
        f"sha256 {sha256} is none of the known copies of catalogue entry '{entry.name}' "
        f"({', '.join(entry.sha256)}): the file is damaged, or another product under the same "
        "name. Get it again (" + entry.how_to_get + "), or, if you trust this copy, give its "
        "path with allow_unknown_copy=True",
    )


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
            # Reached only when the caller allowed it (check_catalogue_copy): say so.
            notes.append(f"sha256 differs from the catalogue's known copies of {entry.file} (allowed by the caller)")
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
    """Normalise the 360° duplicate column, check the NaNs (no data) and the plausibility
    of the values (:func:`check_plausible`), build the grid."""
    lon, values = drop_repeated_column(path, lon, values)
    nan = int(np.isnan(values).sum())
    if nan == values.size:
        raise InputFileError(path, f"all {nan} nodes are NaN (no data)")
    if complete and nan:
        raise InputFileError(path, f"{nan} of {values.size} nodes are NaN (no data) in a grid that must be complete")
    check_plausible(path, lat, lon, values)
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
    if not (np.isfinite(spacing) and spacing * coord.size <= 2 * period and period / spacing < 1e9):
        raise InputFileError(path, f"{name} spacing {spacing:.6g} degrees is not a usable lattice spacing")
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


def check_plausible(path, lat, lon, values) -> None:
    """Refuse undulations beyond ±MAX_ABS_UNDULATION_M, naming the worst node.

    The message tells a unit mistake (the bulk of the field beyond the range and its
    largest value within 100 or 1000 times the range: centimetres or millimetres) from
    isolated values (a corrupt value, or a no-data marker the file does not declare,
    such as float32's largest number 3.4e38).
    """
    magnitude = np.abs(np.where(np.isnan(values), 0.0, values))
    worst = float(magnitude.max()) if magnitude.size else 0.0
    if worst <= MAX_ABS_UNDULATION_M:
        return
    beyond = magnitude > MAX_ABS_UNDULATION_M
    count = int(beyond.sum())
    finite = int(np.isfinite(values).sum())
    i, j = np.unravel_index(int(np.argmax(magnitude)), magnitude.shape)
    value = float(values[i, j])
    low, high = GEOID_RANGE_M
    if count >= 0.01 * finite and worst <= 100 * MAX_ABS_UNDULATION_M:
        hint = (f"the values look like centimetres ({value:.6g} cm is {value / 100:.4g} m): "
                "check the file's units")
    elif count >= 0.01 * finite and worst <= 1000 * MAX_ABS_UNDULATION_M:
        hint = (f"the values look like millimetres ({value:.6g} mm is {value / 1000:.4g} m): "
                "check the file's units")
    else:
        hint = ("a corrupt value, or a no-data marker the file does not declare "
                "(declare it as the format's no-data value)")
    raise InputFileError(
        path,
        f"{count} of {finite} nodes lie beyond the physical range of geoid undulations, ±{MAX_ABS_UNDULATION_M:g} m "
        f"(the Earth's geoid spans about {low:g} to +{high:g} m); the largest, {value:.6g} m, "
        f"is at latitude {float(lat[i]):.6g}, longitude {float(lon[j]):.6g}: {hint}",
    )
