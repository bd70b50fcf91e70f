"""From a command's SOURCE to a source object: a grid file, a catalogue name or a model.

>>> grid = resolve_source("egm96-15")          # PROJ's egm96_15.gtx, wherever PROJ keeps it
>>> grid = resolve_source("my/grid.nc")        # any file read_grid understands
>>> source = open_source("egm96_to360.ascii.gz", correction="CORRCOEF.gz")   # a model

Whether a file is a grid or a model is decided by its content (:func:`is_model_file`),
never by its name: PROJ's ``egm96_15.gtx`` is a grid although its name starts like NGA's
``egm96_to360``.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from ..errors import GeoidSplineError, InputFileError
from .catalogue import find_catalogue_file, get_entry
from .files import reader_faults
from .formats import HEAD_BYTES, grid_format_of, read_grid
from .grid import GeoidGrid
from .harmonics.presets import PRESETS, default_preset, store_preset

__all__ = ["resolve_source", "is_model_file", "open_source", "load_synthesis"]


def resolve_source(name_or_path, *, allow_unknown_copy: bool = False, band: int | None = None,
                   variable: str | None = None) -> GeoidGrid:
    """A grid from an existing file path, or else from a catalogue name.

    A catalogue grid must be complete (no NaN nodes), must be one of the catalogue's
    known copies (sha256; ``allow_unknown_copy=True`` accepts another) and gets the
    catalogue's model, tide system and zero-degree term in its provenance.
    """
    path = Path(name_or_path).expanduser()
    if path.exists():
        return read_grid(path, allow_unknown_copy=allow_unknown_copy, band=band, variable=variable)
    if isinstance(name_or_path, os.PathLike):
        raise InputFileError(path, "no such file")
    entry = get_entry(str(name_or_path))
    grid = read_grid(find_catalogue_file(entry), complete=True, allow_unknown_copy=allow_unknown_copy, band=band,
                     variable=variable)
    grid.provenance = dataclasses.replace(
        grid.provenance,
        model=entry.model,
        tide_system=entry.tide_system,
        zero_degree_term_m=entry.zero_degree_term_m,
    )
    return grid


def is_model_file(path) -> bool:
    """Whether ``path`` holds a spherical-harmonic model rather than a grid, by content:
    an ICGEM header with ``gfc`` lines, or NGA's ``n m C S sigmaC sigmaS`` lines (plain
    or gzip-compressed). A missing file is not a model."""
    from .harmonics.models import model_file_kind

    return Path(path).is_file() and model_file_kind(path) in ("icgem", "nga")


def open_source(name_or_path, correction=None, preset=None, *, allow_unknown_copy: bool = False, max_degree=None,
                band: int | None = None, variable: str | None = None, progress=None):
    """The source behind a command-line SOURCE: a model (with its optional ζ-to-N
    correction file and NGA preset) or a grid file / catalogue name (``band``/``variable``:
    the GeoTIFF band or netCDF variable of a file with several). ``progress``: told of
    the reading of model files (see :func:`load_synthesis`)."""
    if correction is not None or max_degree is not None or is_model_file(name_or_path):
        if band is not None or variable is not None:
            raise InputFileError(name_or_path, "--band and --variable apply to grid files, not to models")
        return load_synthesis(name_or_path, correction, preset, max_degree=max_degree, progress=progress)
    if preset is not None:
        raise InputFileError(name_or_path, "a preset applies to spherical-harmonic models only")
    return resolve_source(name_or_path, allow_unknown_copy=allow_unknown_copy, band=band, variable=variable)


def _check_is_model(path, label: str) -> None:
    """Refuse, by content, a grid or a correction given as a model (or a model as a correction)."""
    from .harmonics.models import model_file_kind

    with reader_faults(path):
        kind = model_file_kind(path)
        if kind is not None and kind.startswith("corrupt"):
            raise InputFileError(path, kind)
        wanted = ("nga-correction",) if label == "correction" else ("icgem", "nga")
        if kind in wanted or kind is None and not _is_grid(path):
            return  # the reader gives the precise rule for anything else
        if kind is None:
            raise InputFileError(path, f"is a geoid grid, not a {label} file: a grid is a SOURCE of its own")
        what = "a zeta-to-N correction (n m C S)" if kind == "nga-correction" else "a spherical-harmonic model"
        raise InputFileError(path, f"is {what}, not a {label} file")


def _is_grid(path) -> bool:
    with open(path, "rb") as fh:
        head = fh.read(HEAD_BYTES)
    return grid_format_of(head, Path(path).stat().st_size) is not None


def _read_reporting(reader, path, progress, **kwargs):
    """``reader(path)`` reported to ``progress`` (an object with ``stage(name, total,
    unit)``, as geoidspline.fitting.progress's) as the stage "read NAME" in bytes of
    the file; without progress, just read."""
    if progress is None:
        return reader(path, **kwargs)
    with progress.stage(f"read {Path(path).name}", Path(path).stat().st_size, "byte") as advance:
        return reader(path, progress=advance, **kwargs)


def load_synthesis(model_path, correction_path=None, preset=None, like_store=None, *, max_degree=None,
                   progress=None):
    """Read a model (ICGEM .gfc or NGA ASCII) and optional NGA ζ-to-N correction (EGM96's
    CORRCOEF in cm, EGM2008's Zeta-to-N_to2160_egm2008 in m: :func:`correction_unit`)
    and return the :class:`~geoidspline.sources.harmonics.GeoidSynthesis`.

    ``preset`` None means: the preset ``like_store`` was fitted with when that store was
    fitted from this same model file (:func:`store_preset`), else :func:`default_preset`.
    ``max_degree`` truncates the model and the correction on purpose; without it a
    correction that stops below the model's degree is refused. ``progress``: each file's
    reading is a stage "read NAME" counted in bytes of the file (with its ETA).
    """
    from .harmonics.models import correction_unit, read_model, read_nga_correction
    from .harmonics.synthesis import GeoidSynthesis

    if preset is not None and preset not in PRESETS:
        raise GeoidSplineError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
    for label, value in (("model", model_path), ("correction", correction_path)):
        if value is not None and not Path(value).is_file():
            raise InputFileError(value, f"{label} file not found" if not Path(value).exists() else "not a regular file")
        if value is not None:
            _check_is_model(value, label)
    model = _read_reporting(read_model, model_path, progress)
    correction = None
    if correction_path is not None:
        correction = _read_reporting(read_nga_correction, correction_path, progress,
                                     unit=correction_unit(correction_path, model.name))
    chosen = preset
    if chosen is None and like_store is not None:
        chosen = store_preset(like_store, model)
    if chosen is None:
        chosen = default_preset(model, correction)
    try:
        return GeoidSynthesis(model, correction, preset=chosen, max_degree=max_degree)
    except InputFileError:
        raise
    except ValueError as exc:
        raise GeoidSplineError(f"{model_path}: {exc}") from None
    except MemoryError:
        raise InputFileError(model_path, f"not enough memory for a degree-{model.max_degree} synthesis") from None
