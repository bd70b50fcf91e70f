"""From a command's SOURCE to a source object: a grid file, a catalogue name or a model.

>>> grid = resolve_source("egm96-15")          # PROJ's egm96_15.gtx, wherever PROJ keeps it
>>> grid = resolve_source("my/grid.nc")        # any file read_grid understands
>>> source = open_source("egm96_to360.ascii.gz", correction="CORRCOEF.gz")   # a model
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path

from ..errors import GeoidSplineError, InputFileError
from .catalogue import find_catalogue_file, get_entry
from .formats import read_grid
from .grid import GeoidGrid
from .harmonics.presets import PRESETS, default_preset, store_preset

__all__ = ["resolve_source", "is_model_file", "open_source", "load_synthesis"]


def resolve_source(name_or_path) -> GeoidGrid:
    """A grid from an existing file path, or else from a catalogue name.

    A catalogue grid must be complete (no NaN nodes) and gets the catalogue's model,
    tide system and zero-degree term in its provenance.
    """
    path = Path(name_or_path).expanduser()
    if path.exists():
        return read_grid(path)
    if isinstance(name_or_path, os.PathLike):
        raise InputFileError(path, "no such file")
    entry = get_entry(str(name_or_path))
    grid = read_grid(find_catalogue_file(entry), complete=True)
    grid.provenance = dataclasses.replace(
        grid.provenance,
        model=entry.model,
        tide_system=entry.tide_system,
        zero_degree_term_m=entry.zero_degree_term_m,
    )
    return grid


def is_model_file(path) -> bool:
    """Whether ``path`` names a spherical-harmonic model rather than a grid.

    ICGEM files end in ``.gfc`` (optionally compressed); NGA's coefficient files have
    no header and are recognised by their standard names (``egm96_to360.ascii``,
    ``EGM2008_to2190_*``), see :data:`geoidspline.sources.harmonics.NGA_CATALOGUE`.
    """
    name = Path(path).name.lower()
    if name.endswith((".gfc", ".gfc.gz")):
        return True
    from .harmonics.models import _nga_lookup

    return _nga_lookup(path) is not None


def open_source(name_or_path, correction=None, preset=None):
    """The source behind a command-line SOURCE: a model (with its optional ζ-to-N
    correction file and NGA preset) or a grid file / catalogue name."""
    if correction is not None or (Path(name_or_path).exists() and is_model_file(name_or_path)):
        
        return load_synthesis(name_or_path, correction, preset)
    if preset is not None:
        raise InputFileError(name_or_path, "a preset applies to spherical-harmonic models only")
    return resolve_source(name_or_path)


def load_synthesis(model_path, correction_path=None, preset=None, like_store=None):
    """Read a model (ICGEM .gfc or NGA ASCII) and optional CORRCOEF-style correction
    and return the :class:`~geoidspline.sources.harmonics.GeoidSynthesis`.

    ``preset`` None means: the preset ``like_store`` was fitted with when that store was
    fitted from this same model file (:func:`store_preset`), else :func:`default_preset`.
    """
    from .harmonics.models import read_model, read_nga_correction
    from .harmonics.synthesis import GeoidSynthesis

    if preset is not None and preset not in PRESETS:
        raise GeoidSplineError(f"unknown preset {preset!r}; expected one of {', '.join(PRESETS)}")
    for label, value in (("model", model_path), ("correction", correction_path)):
        if value is not None and not Path(value).is_file():
            raise InputFileError(value, f"{label} file not found" if not Path(value).exists() else "not a regular file")
    model = read_model(model_path)
    correction = read_nga_correction(correction_path) if correction_path is not None else None
    chosen = preset
    if chosen is None and like_store is not None:
        chosen = store_preset(like_store, model)
    if chosen is None:
        chosen = default_preset(model, correction)
    try:
        return GeoidSynthesis(model, correction, preset=chosen)
    except ValueError as exc:
        raise GeoidSplineError(f"{model_path}: {exc}") from None
