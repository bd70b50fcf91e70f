"""Geoid grids known by name: the catalogue's entries and where their files are.

The entries live in ``grids/catalogue.toml`` (package data ``geoidspline.grids``). Each
names a file, the directories to look for it in (in order), how to get it, what the
values are (model, tide system and the zero-degree term N0, metres, they contain) and
the sha256 of its known copies. Resolving a command's SOURCE to a grid or model is
:mod:`geoidspline.sources.resolve`.

Search order for an entry's file: its ``search`` list, in order, each item one of

1. ``$NAME``: the directories in environment variable NAME (``os.pathsep``-separated),
   e.g. ``$PROJ_DATA``, ``$PROJ_LIB``, ``$GEOIDSPLINE_DATA``;
2. ``pyproj:data_dir`` / ``pyproj:user_data_dir``: pyproj's data directories;
3. an absolute directory (``/usr/share/proj``).

Only absolute directories are searched: a relative one (in the catalogue or in an
environment variable) would depend on the working directory, where anyone can plant a
file of the right name, and is skipped with a warning. The first directory holding the
file wins, and its sha256 must be one of the entry's known copies
(:func:`geoidspline.sources.files.check_catalogue_copy`).
"""

from __future__ import annotations

import functools
import logging
import os
from dataclasses import dataclass
from pathlib import Path

try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib
from ..errors import InputFileError

log = logging.getLogger(__name__)

__all__ = ["CatalogueEntry", "list_catalogue", "get_entry", "entry_for_file", "search_directories", "find_catalogue_file"]


@dataclass(frozen=True)
class CatalogueEntry:
    """One named grid. ``zero_degree_term_m`` (metres) and ``tide_system`` are None when unknown."""

    name: str
    file: str
    format: str
    model: str
    reference: str
    search: tuple[str, ...]
    how_to_get: str
    description: str = ""
    tide_system: str | None = None
    zero_degree_term_m: float | None = None
    sha256: tuple[str, ...] = ()


def _catalogue_text() -> str:
    try:
        from importlib.resources import files

        return files("geoidspline.grids").joinpath("catalogue.toml").read_text(encoding="utf-8")
    except ModuleNotFoundError:
        # Running from a source tree without installing: grids/ sits beside geoidspline/.
        return (Path(__file__).resolve().parent.parent / "grids" / "catalogue.toml").read_text(encoding="utf-8")


@functools.lru_cache(maxsize=1)
def _entries() -> dict[str, CatalogueEntry]:
    raw = tomllib.loads(_catalogue_text())
    entries = {}
    for name, table in raw.items():
        table = dict(table)
        table["search"] = tuple(table.get("search", ()))
        table["sha256"] = tuple(table.get("sha256", ()))
        entries[name] = CatalogueEntry(name=name, **table)
    return entries


def list_catalogue() -> list[CatalogueEntry]:
    """All catalogue entries, sorted by name."""
    return [entry for _, entry in sorted(_entries().items())]


def get_entry(name: str) -> CatalogueEntry:
    """The entry called ``name`` (case-insensitive), or InputFileError listing the known names."""
    entry = _entries().get(str(name).strip().lower())
    if entry is None:
        raise InputFileError(
            name, f"no such file, and not a catalogue name; known names: {', '.join(sorted(_entries()))}"
        )
    return entry


def entry_for_file(file_name: str) -> CatalogueEntry | None:
    """The entry whose file is called ``file_name`` (case-insensitive), else None."""
    lowered = Path(file_name).name.lower()
    for entry in _entries().values():
        if entry.file.lower() == lowered:
            return entry
    return None


def search_directories(entry: CatalogueEntry) -> list[Path]:
    """The absolute directories searched for ``entry.file``, in order, without duplicates
    (relative ones are skipped: see the module documentation)."""
    dirs: list[Path] = []
    for spec in entry.search:
        if spec.startswith("$"):
            value = os.environ.get(spec[1:], "")
            found = [p for p in value.split(os.pathsep) if p]
        elif spec == "pyproj:data_dir":
            found = _pyproj_dirs(user=False)
        elif spec == "pyproj:user_data_dir":
            found = _pyproj_dirs(user=True)
        else:
            found = [spec]
        for item in found:
            path = Path(item).expanduser()
            if not path.is_absolute():
                log.warning("catalogue entry %s: search directory %r (from %s) is relative to the working "
                            "directory; skipped", entry.name, item, spec)
                continue
            if path not in dirs:
                dirs.append(path)
    return dirs


def _pyproj_dirs(user: bool) -> list[str]:
    try:
        import pyproj.datadir as datadir

        if user:
            return [datadir.get_user_data_dir()]
        return [p for p in datadir.get_data_dir().split(os.pathsep) if p]
    except Exception:  # pyproj missing or without a data dir: nothing to search there
        return []


def find_catalogue_file(entry: CatalogueEntry) -> Path:
    """The first existing ``entry.file`` in :func:`search_directories`, or raise.

    The error names the directories searched and how to get the file.
    """
    dirs = search_directories(entry)
    names = dict.fromkeys([entry.file, entry.file.lower(), entry.file.upper()])
    for directory in dirs:
        for name in names:
            candidate = directory / name
            if candidate.is_file():
                return candidate
    searched = ", ".join(str(d) for d in dirs) or "(no directories)"
    raise InputFileError(
        entry.file,
        f"file of catalogue entry '{entry.name}' not found; searched {searched}; to get it: {entry.how_to_get}",
    )
