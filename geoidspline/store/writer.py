"""Writing a store: the writer lock, tile files under new names, one atomic commit.

Writing is atomic: tile files are written under new names (they are never changed
once written), then ``manifest.json`` is replaced with :func:`os.replace`, so a crash
leaves either the old manifest with its old files or the new one with all of its own.
Files no manifest names are removed afterwards. A directory without
``manifest.json`` is not a store (a first write that crashed), and opening it says so.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._files import fsync_dir, sha256_file
from .._version import __version__
from ..bspline import keys as _keys
from ..bspline.level import cube_of_support_centres
from ..errors import StoreCorruptError, StoreError
from ..sphere.coordinates import directions
from .codec import quantised_spline, value_error_bound, value_step
from .format import (
    FORMAT_NAME,
    FORMAT_VERSION,
    LOCK,
    MANIFEST,
    TILE_DIR,
    error_stats,
    load_manifest,
    tile_name,
    utc_now,
    write_tile_file,
)

if TYPE_CHECKING:  # annotations only
    from ..fitting.check_points import CheckPoints
    from ..hierarchy.ambient import AmbientSpline


def group_by_tile(dirs, tile_size):
    tiles = np.floor(dirs / tile_size).astype(np.int64)
    keys = _keys.pack_keys(tiles)
    return keys


def crash_point(name):
    """Test hook: die here, like SIGKILL (no clean-up), when GEOIDSPLINE_CRASH_AT=name."""
    if os.environ.get("GEOIDSPLINE_CRASH_AT") == name:
        os._exit(77)


class StoreLock:
    """Exclusive writer lock of a store: ``STORE/.lock`` holding the writer's pid.

    Created with O_EXCL, so two writers cannot both take it; a lock whose process is
    gone (a killed writer) is taken over with a warning.
    """

    def __init__(self, root: Path):
        self.path = Path(root) / LOCK

    def __enter__(self):
        for _ in range(2):
            try:
                fd = os.open(self.path, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o644)
            except FileExistsError:
                try:
                    pid = int(self.path.read_text().strip() or 0)
                except (OSError, ValueError):
                    pid = 0
                if pid and _process_alive(pid):
                    raise StoreError(
                        f"{self.path.parent}: another writer (pid {pid}) is updating this store; "
                        f"try again when it has finished"
                    ) from None
                import logging

                logging.getLogger("geoidspline.store").warning(
                    "%s: removing the stale lock of pid %s, which is gone", self.path.parent, pid or "?")
                self.path.unlink(missing_ok=True)
                continue
            except PermissionError:
                raise StoreError(f"{self.path.parent}: not writable (cannot create {LOCK})") from None
            with os.fdopen(fd, "w") as fh:
                fh.write(str(os.getpid()))
            return self
        raise StoreError(f"{self.path.parent}: cannot take the writer lock")

    def __exit__(self, *exc):
        self.path.unlink(missing_ok=True)
        return False


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def tile_groups(spline: AmbientSpline, tile_size: float) -> dict:
    """Coefficients of every level grouped by tile: {tile key: (levels, indices, values)}."""
    all_idx, all_lvl, all_val, all_tile = [], [], [], []
    for lv in spline.levels:
        idx = lv.indices
        all_idx.append(idx)
        all_lvl.append(np.full(len(lv), lv.level))
        all_val.append(lv.coefficients)
        all_tile.append(_keys.pack_keys(cube_of_support_centres(idx, lv.h, lv.order, tile_size)))
    if not all_idx:
        return {}
    idx = np.concatenate(all_idx)
    lvl = np.concatenate(all_lvl)
    val = np.concatenate(all_val)
    tile_keys = np.concatenate(all_tile)
    order = np.argsort(tile_keys, kind="stable")
    unique, starts = np.unique(tile_keys[order], return_index=True)
    stops = np.append(starts[1:], order.size)
    return {int(key): (lvl[order[a:b]], idx[order[a:b]], val[order[a:b]]) for key, a, b in zip(unique, starts, stops)}


def write_tile_entry(root, key, group, version, spline_meta, stats, format_version=FORMAT_VERSION) -> dict:
    """Write one tile file under a new name and return its manifest entry."""
    lvl, idx, val = group
    tile = _keys.unpack_keys(np.array([key]))[0]
    name = tile_name(tile, version, format_version)
    write_tile_file(root / TILE_DIR / name, tile, lvl, idx, val, spline_meta, format_version)
    return {
        "tile": [int(v) for v in tile],
        "file": f"{TILE_DIR}/{name}",
        "bytes": (root / TILE_DIR / name).stat().st_size,
        "sha256": sha256_file(root / TILE_DIR / name),
        "coefficients": int(val.size),
        "levels": [int(v) for v in np.unique(lvl)],
        **stats,
    }


def quantisation_meta(step, levels) -> dict:
    """The manifest's statement of a format-2 store's quantisation (``spline`` keys)."""
    return {
        "value_step_m": step,
        "value_error_bound_m": value_error_bound(step, levels),
        "value_error_rule": "each coefficient within step/2; B-splines of a level are non-negative and sum "
                            "to at most 1, so the value moves by at most step/2 per level",
    }


def tile_encoding(manifest) -> tuple[int, dict]:
    """(format version, tile attributes) with which new tiles of a store are written: its
    own format and step, so that an update of a format-1 store stays format 1."""
    version = int(manifest["format_version"])
    step = manifest["spline"].get("value_step_m")
    return version, ({"value_step_m": step} if version >= 2 else {})


def tile_stats(node_errors, check_errors):
    nodes = error_stats(node_errors)
    checks = error_stats(check_errors)
    return {
        "max_error_m": checks["max_error_m"],
        "rms_error_m": checks["rms_error_m"],
        "check_points": checks["count"],
        "node_max_error_m": nodes["max_error_m"],
        "node_rms_error_m": nodes["rms_error_m"],
        "nodes": nodes["count"],
    }


def commit(root: Path, manifest: dict, keep_files=()):
    """Make ``manifest`` the store's state in one atomic rename, then remove tile files
    that neither it nor ``keep_files`` (the previous version's, for readers that
    opened it just before) name."""
    fsync_dir(root / TILE_DIR)
    crash_point("before-manifest")
    tmp = root / (MANIFEST + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(manifest, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    crash_point("manifest-written")
    os.replace(tmp, root / MANIFEST)
    fsync_dir(root)
    crash_point("after-manifest")
    live = {e["file"] for e in manifest["tiles"]} | set(keep_files)
    for stale in (root / TILE_DIR).iterdir():
        if f"{TILE_DIR}/{stale.name}" not in live:
            stale.unlink(missing_ok=True)


def write_store(path, result, provenance, check: CheckPoints | None = None,
                overwrite=False, extra=None, format_version=FORMAT_VERSION, value_step_m=None) -> Path:
    """Write a fit (:class:`geoidspline.fitting.driver.FitResult`) as a tile store at ``path``.

    An existing store is refused unless ``overwrite``; even then its files stay valid
    until the new manifest replaces the old one. ``format_version=1`` writes the old
    format (netCDF4 tiles, float64 values), kept for tests of older stores; format 2
    quantises the coefficients with ``value_step_m`` (default
    :func:`~geoidspline.store.codec.value_step` of the tolerance and level count); the
    check-point errors in the manifest are those of the stored (quantised) spline, the
    node errors the fit's (quantisation adds at most ``value_error_bound_m`` to them).
    """
    root = Path(path)
    manifest_path = root / MANIFEST
    previous = None
    if root.exists() and not root.is_dir():
        raise StoreError(f"{root}: exists and is not a directory")
    if manifest_path.exists():
        if not overwrite:
            raise StoreError(f"{root}: a store already exists here (pass overwrite=True to replace it)")
        try:
            previous = load_manifest(root)
        except StoreCorruptError:
            previous = None  # replacing a damaged store is what --overwrite is for
    elif root.exists() and any(p.name not in (TILE_DIR, LOCK) for p in root.iterdir()):
        raise StoreError(f"{root}: directory is not empty and is not a geoidspline store")
    (root / TILE_DIR).mkdir(parents=True, exist_ok=True)
    if not os.access(root, os.W_OK):
        raise StoreError(f"{root}: not writable")
    with StoreLock(root):
        version = (previous["store_version"] + 1) if previous else 1

        params = result.parameters
        spline = result.spline
        quantisation = {}
        stored = spline  # what the store will give: the check errors are its own
        if format_version >= 2:
            step = value_step_m or value_step(params.tolerance_m, len(spline.levels))
            quantisation = quantisation_meta(step, len(spline.levels))
            stored = quantised_spline(spline, step)
        node_tile = group_by_tile(result.node_directions, params.tile_size)
        check_errors = None
        if check is not None:
            check_errors = check.truth - stored.undulation(check.latitude, check.longitude)
            check_tile = group_by_tile(directions(check.latitude, check.longitude), params.tile_size)
        spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size}
        if format_version >= 2:
            spline_meta["value_step_m"] = quantisation["value_step_m"]
        entries = []
        crash_point("before-tiles")
        for key, group in tile_groups(spline, params.tile_size).items():
            stats = tile_stats(result.node_errors[node_tile == key],
                                check_errors[check_tile == key] if check is not None else [])
            entries.append(write_tile_entry(root, key, group, version, spline_meta, stats, format_version))
            crash_point("during-tiles")
        crash_point("after-tiles")

        node_stats = error_stats(result.node_errors)
        check_stats = error_stats(check_errors if check is not None else [])
        manifest = {
            "format": FORMAT_NAME,
            "format_version": format_version,
            "store_version": version,
            "created": previous["created"] if previous else utc_now(),
            "updated": utc_now(),
            "software": f"geoidspline {__version__}",
            "provenance": provenance.as_dict(),
            "region": list(result.region.as_tuple()),
            "spline": {
                "reference_manifold": "unit sphere; direction u = (cos lat cos lon, cos lat sin lon, sin lat)",
                "order": params.order,
                "h0": params.h0,
                "tile_size": params.tile_size,
                "levels": [
                    {"level": lv.level, "h": lv.h, "coefficients": len(lv)} for lv in spline.levels
                ],
                "coefficients": spline.coefficient_count,
                **quantisation,
            },
            "fit": {
                "method": "hierarchical overlays (Lehmann 2013, section 5.2)",
                "parameters": params.as_dict(),
                "tolerance_m": params.tolerance_m,
                "converged": bool(result.converged),
                "seconds": round(result.seconds, 3),
                "level_reports": [vars(r) for r in result.levels],
                **(extra or {}),
            },
            "accuracy": {
                "nodes": node_stats["count"],
                "node_max_error_m": node_stats["max_error_m"],
                "node_rms_error_m": node_stats["rms_error_m"],
                "node_p99_error_m": node_stats["p99_error_m"],
                "check_points": check_stats["count"],
                "check_truth": check.description if check is not None else None,
                "max_error_m": check_stats["max_error_m"],
                "rms_error_m": check_stats["rms_error_m"],
                "p99_error_m": check_stats["p99_error_m"],
                "units": "m",
            },
            "tiles": entries,
            "history": (previous.get("history", []) if previous else []) + [{
                "action": "fit",
                "time": utc_now(),
                "store_version": version,
                "source": provenance.source,
                "sha256": provenance.sha256,
                "region": list(result.region.as_tuple()),
            }],
        }
        keep = [e["file"] for e in previous["tiles"]] if previous else []
        commit(root, manifest, keep)
    return root
