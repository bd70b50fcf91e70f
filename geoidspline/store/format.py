"""The tile store format: names, the manifest and its checks, tile files.

Layout of a store directory::

    STORE/manifest.json                      the commit point: lists the live tile files
    STORE/tiles/t+0001-0002+0000.v1.gst      one file per tile and store version

A tile file holds every coefficient, of every level, whose B-spline support centre
lies in the tile's cube. Format 2 (``.gst``, written now): runs of keys and quantised
values, see :mod:`geoidspline.store.codec`. Format 1 (``.nc``, still read, and written
by :func:`write_tile_file` with ``format_version=1``): netCDF4 variables ``index``
(coefficient, axis: the B-spline's integer position on its level's grid), ``level``
and ``value`` (metres). Readers tell them apart by the file's first bytes.
"""

from __future__ import annotations

import datetime as _dt
import json
from pathlib import Path

import numpy as np

from .._files import atomic_path, atomic_write
from .._version import __version__  # noqa: F401 (recorded in manifests)
from ..bspline.keys import pack_keys, unpack_keys
from ..errors import StoreCorruptError, StoreError
from .codec import decode_tile, encode_tile, is_tile_v2

FORMAT_NAME = "geoidspline-tile-store"


FORMAT_VERSION = 2
"""The format written; every version from 1 up to it is read."""


MANIFEST = "manifest.json"


TILE_DIR = "tiles"


LOCK = ".lock"


def tile_name(tile, version, format_version=FORMAT_VERSION):
    i, j, k = (int(v) for v in tile)
    return f"t{i:+05d}{j:+05d}{k:+05d}.v{version}.{'nc' if format_version == 1 else 'gst'}"


def utc_now():
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def error_stats(errors):
    errors = np.asarray(errors, dtype=float)
    if errors.size == 0:
        return {"count": 0, "max_error_m": None, "rms_error_m": None, "p99_error_m": None}
    absolute = np.abs(errors)
    return {
        "count": int(errors.size),
        "max_error_m": float(absolute.max()),
        "rms_error_m": float(np.sqrt(np.mean(errors**2))),
        "p99_error_m": float(np.percentile(absolute, 99)),
    }


def write_tile_file(path, tile, levels, indices, values, attrs, format_version=FORMAT_VERSION):
    """Write one tile file; format 2 quantises with ``attrs["value_step_m"]``."""
    if format_version >= 2:
        atomic_write(path, encode_tile(tile, levels, indices, values, attrs["value_step_m"]))
        return
    import netCDF4

    with atomic_path(path) as tmp, netCDF4.Dataset(tmp, "w", format="NETCDF4") as ds:
        ds.setncattr("Conventions", "CF-1.8")
        ds.setncattr("title", "geoidspline ambient B-spline tile")
        ds.setncattr("format", FORMAT_NAME)
        ds.setncattr("format_version", 1)
        ds.setncattr("tile", np.asarray(tile, dtype=np.int32))
        for key, value in attrs.items():
            if value is not None and key != "value_step_m":
                ds.setncattr(key, value)
        ds.createDimension("coefficient", len(values))
        ds.createDimension("axis", 3)
        var = ds.createVariable("index", "i4", ("coefficient", "axis"), zlib=True, complevel=4)
        var.long_name = "integer position (i, j, k) of the B-spline on its level's grid: support [k h, (k + order) h) per axis"
        var.units = "1"
        var[:] = indices.astype(np.int32)
        var = ds.createVariable("level", "i1", ("coefficient",), zlib=True, complevel=4)
        var.long_name = "overlay level; grid spacing h = h0 / 2**level on the unit sphere"
        var.units = "1"
        var[:] = levels.astype(np.int8)
        var = ds.createVariable("value", "f8", ("coefficient",), zlib=True, complevel=4)
        var.long_name = "B-spline coefficient of the geoid undulation"
        var.units = "m"
        var[:] = values


def read_tile_levels(path, entry, data):
    """{level: (sorted packed keys, values in metres)} of a tile file's bytes ``data``
    (either format; format 2 decodes straight to keys, without index triples)."""
    if not is_tile_v2(data):
        indices, levels, values = read_tile_file(path, entry, data)
        out = {}
        for level in np.unique(levels):
            sel = levels == level
            keys = pack_keys(indices[sel])
            order = np.argsort(keys)
            out[int(level)] = (keys[order], values[sel][order])
        return out
    try:
        _, out = decode_tile(data)
    except ValueError as exc:
        raise StoreCorruptError(f"{path}: tile {entry['tile']} {exc}") from None
    count = sum(v[0].size for v in out.values())
    if count != entry["coefficients"]:
        raise StoreCorruptError(
            f"{path}: tile {entry['tile']} holds {count} coefficients, the manifest says {entry['coefficients']}")
    return out


def read_tile_file(path, entry, data=None):
    """(indices (M, 3), levels (M,), values (M,)) of a tile file, or of its bytes ``data``."""
    if data is None:
        data = Path(path).read_bytes()
    if is_tile_v2(data):
        out = read_tile_levels(path, entry, data)
        if not out:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0)
        indices = np.concatenate([unpack_keys(k) for k, _ in out.values()])
        levels = np.concatenate([np.full(k.size, lv, np.int64) for lv, (k, _) in out.items()])
        values = np.concatenate([v for _, v in out.values()])
        return indices, levels, values
    import netCDF4

    try:
        with netCDF4.Dataset(str(path), "r", memory=data) as ds:
            ds.set_auto_mask(False)
            indices = np.asarray(ds["index"][:], dtype=np.int64)
            levels = np.asarray(ds["level"][:], dtype=np.int64)
            values = np.asarray(ds["value"][:], dtype=np.float64)
    except (OSError, KeyError, IndexError, RuntimeError) as exc:
        raise StoreCorruptError(f"{path}: tile {entry['tile']} cannot be read as a tile file ({exc})") from None
    if values.size != entry["coefficients"]:
        raise StoreCorruptError(
            f"{path}: tile {entry['tile']} holds {values.size} coefficients, the manifest says {entry['coefficients']}"
        )
    return indices.reshape(-1, 3), levels, values


def load_manifest(root: Path) -> dict:
    path = root / MANIFEST
    if not root.exists():
        raise StoreError(f"{root}: no such store")
    if not path.exists():
        raise StoreError(
            f"{root}: not a geoidspline store (no {MANIFEST}; a store whose first write did not finish has none)"
        )
    try:
        with open(path, encoding="utf-8") as fh:
            manifest = json.load(fh)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise StoreCorruptError(f"{path}: manifest is not valid JSON ({exc})") from None
    if not isinstance(manifest, dict):
        raise StoreCorruptError(f"{path}: manifest is not a JSON object")
    if manifest.get("format") != FORMAT_NAME:
        raise StoreError(f"{path}: not a geoidspline manifest (format {manifest.get('format')!r})")
    if manifest.get("format_version", 0) > FORMAT_VERSION:
        raise StoreError(
            f"{path}: store format {manifest['format_version']} is newer than this geoidspline reads ({FORMAT_VERSION})"
        )
    missing = [key for key in MANIFEST_KEYS if key not in manifest]
    if missing:
        raise StoreCorruptError(f"{path}: manifest lacks {', '.join(missing)}")
    return manifest


MANIFEST_KEYS = ("format_version", "store_version", "spline", "fit", "accuracy", "tiles", "region", "provenance")
