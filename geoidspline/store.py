"""The tile store: one netCDF4 file per tile plus a JSON manifest.

Layout of a store directory::

    STORE/manifest.json                      the commit point: lists the live tile files
    STORE/tiles/t+0001-0002+0000.v1.nc       one file per tile and store version

A tile file holds every coefficient, of every level, whose B-spline support centre
lies in the tile's cube: variables ``index`` (coefficient, axis: the B-spline's
integer position on its level's grid), ``level`` and ``value`` (metres).

Writing is atomic: tile files are written under new names (they are never changed
once written), then ``manifest.json`` is replaced with :func:`os.replace`, so a crash
leaves either the old manifest with its old files or the new one with all of its own.
Files no manifest names are removed afterwards. A directory without
``manifest.json`` is not a store (a first write that crashed), and opening it says so.

Opening reads the manifest and checks that every tile file exists with the size the
manifest gives; a tile's sha256 is checked when the tile is read, which is when a query
first needs it (or at opening with ``lazy=False``). A store whose files disagree with
the manifest is refused, naming the tile: it never returns numbers from such a tile.
A :class:`TileStore`'s queries are thread-safe (see :class:`StoreSpline`).
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from . import __version__
from . import _keys  # pack_keys/unpack_keys without importing numba
from .errors import StoreError, StoreCorruptError
from .spline import FOLDED_FROM_POINTS, AmbientSpline, LevelSpline, check_coordinates, directions, tile_of_indices

__all__ = ["TileStore", "StoreSpline", "write_store", "verify_store", "StoreLock", "FORMAT_NAME",
           "FORMAT_VERSION"]

FORMAT_NAME = "geoidspline-tile-store"
FORMAT_VERSION = 1
MANIFEST = "manifest.json"
TILE_DIR = "tiles"


def _sha256(path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _fsync_dir(path):
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _tile_name(tile, version):
    i, j, k = (int(v) for v in tile)
    return f"t{i:+05d}{j:+05d}{k:+05d}.v{version}.nc"


def _now():
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def _error_stats(errors):
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


@dataclass(frozen=True)
class CheckPoints:
    """Points that were not fit sites, with their true undulations (metres)."""

    latitude: np.ndarray
    longitude: np.ndarray
    truth: np.ndarray
    description: str


def _group_by_tile(dirs, tile_size):
    tiles = np.floor(dirs / tile_size).astype(np.int64)
    keys = _keys.pack_keys(tiles)
    return keys


def _write_tile_file(path, tile, levels, indices, values, attrs):
    import netCDF4

    tmp = path.with_name(path.name + ".tmp")
    with netCDF4.Dataset(tmp, "w", format="NETCDF4") as ds:
        ds.setncattr("Conventions", "CF-1.8")
        ds.setncattr("title", "geoidspline ambient B-spline tile")
        ds.setncattr("format", FORMAT_NAME)
        ds.setncattr("format_version", FORMAT_VERSION)
        ds.setncattr("tile", np.asarray(tile, dtype=np.int32))
        for key, value in attrs.items():
            if value is not None:
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
    with open(tmp, "rb+") as fh:
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _read_tile_file(path, entry, data=None):
    """(indices (M, 3), levels (M,), values (M,)) of a tile file, or of its bytes ``data``."""
    import netCDF4

    try:
        if data is None:
            ds = netCDF4.Dataset(path, "r")
        else:
            ds = netCDF4.Dataset(str(path), "r", memory=data)
        with ds:
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


LOCK = ".lock"


def _crash_point(name):
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
        all_tile.append(_keys.pack_keys(tile_of_indices(idx, lv.h, lv.order, tile_size)))
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


def _write_tile_entry(root, key, group, version, spline_meta, stats) -> dict:
    """Write one tile file under a new name and return its manifest entry."""
    lvl, idx, val = group
    tile = _keys.unpack_keys(np.array([key]))[0]
    name = _tile_name(tile, version)
    _write_tile_file(root / TILE_DIR / name, tile, lvl, idx, val, spline_meta)
    return {
        "tile": [int(v) for v in tile],
        "file": f"{TILE_DIR}/{name}",
        "bytes": (root / TILE_DIR / name).stat().st_size,
        "sha256": _sha256(root / TILE_DIR / name),
        "coefficients": int(val.size),
        "levels": [int(v) for v in np.unique(lvl)],
        **stats,
    }


def _tile_stats(node_errors, check_errors):
    nodes = _error_stats(node_errors)
    checks = _error_stats(check_errors)
    return {
        "max_error_m": checks["max_error_m"],
        "rms_error_m": checks["rms_error_m"],
        "check_points": checks["count"],
        "node_max_error_m": nodes["max_error_m"],
        "node_rms_error_m": nodes["rms_error_m"],
        "nodes": nodes["count"],
    }


def _commit(root: Path, manifest: dict, keep_files=()):
    """Make ``manifest`` the store's state in one atomic rename, then remove tile files
    that neither it nor ``keep_files`` (the previous version's, for readers that
    opened it just before) name."""
    _fsync_dir(root / TILE_DIR)
    _crash_point("before-manifest")
    tmp = root / (MANIFEST + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(manifest, fh, indent=1)
        fh.flush()
        os.fsync(fh.fileno())
    _crash_point("manifest-written")
    os.replace(tmp, root / MANIFEST)
    _fsync_dir(root)
    _crash_point("after-manifest")
    live = {e["file"] for e in manifest["tiles"]} | set(keep_files)
    for stale in (root / TILE_DIR).iterdir():
        if f"{TILE_DIR}/{stale.name}" not in live:
            stale.unlink(missing_ok=True)


def write_store(path, result, provenance, check: CheckPoints | None = None,
                overwrite=False, extra=None) -> Path:
    """Write a fit (:class:`geoidspline.fit.FitResult`) as a tile store at ``path``.

    An existing store is refused unless ``overwrite``; even then its files stay valid
    until the new manifest replaces the old one.
    """
    root = Path(path)
    manifest_path = root / MANIFEST
    previous = None
    if root.exists() and not root.is_dir():
        raise StoreError(f"{root}: exists and is not a directory")
    if manifest_path.exists():
        if not overwrite:
            raise StoreError(f"{root}: a store already exists here (use --overwrite to replace it)")
        try:
            previous = _load_manifest(root)
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
        node_tile = _group_by_tile(result.node_directions, params.tile_size)
        check_errors = None
        if check is not None:
            check_errors = check.truth - spline.undulation(check.latitude, check.longitude)
            check_tile = _group_by_tile(directions(check.latitude, check.longitude), params.tile_size)
        spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size}
        entries = []
        _crash_point("before-tiles")
        for key, group in tile_groups(spline, params.tile_size).items():
            stats = _tile_stats(result.node_errors[node_tile == key],
                                check_errors[check_tile == key] if check is not None else [])
            entries.append(_write_tile_entry(root, key, group, version, spline_meta, stats))
            _crash_point("during-tiles")
        _crash_point("after-tiles")

        node_stats = _error_stats(result.node_errors)
        check_stats = _error_stats(check_errors if check is not None else [])
        manifest = {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "store_version": version,
            "created": previous["created"] if previous else _now(),
            "updated": _now(),
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
                "time": _now(),
                "store_version": version,
                "source": provenance.source,
                "sha256": provenance.sha256,
                "region": list(result.region.as_tuple()),
            }],
        }
        keep = [e["file"] for e in previous["tiles"]] if previous else []
        _commit(root, manifest, keep)
    return root


def _load_manifest(root: Path) -> dict:
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
    missing = [key for key in _MANIFEST_KEYS if key not in manifest]
    if missing:
        raise StoreCorruptError(f"{path}: manifest lacks {', '.join(missing)}")
    return manifest


_MANIFEST_KEYS = ("format_version", "store_version", "spline", "fit", "accuracy", "tiles", "region", "provenance")


#: Fraction of a store's tiles from which a small batch that needs them loads them all
#: (one full read instead of many partial rebuilds).
FULL_LOAD_FRACTION = 0.5


class StoreSpline:
    """The ambient spline of a store, read tile by tile as queries need it.

    Batches of fewer than :data:`~geoidspline.spline.FOLDED_FROM_POINTS` points
    (:meth:`evaluate_points`, :meth:`undulation`) read only the tiles that can hold a
    B-spline non-zero at one of the points and evaluate them with numpy. A coefficient
    lives in the tile holding its support centre ``(k + order/2) h`` and its B-spline is
    non-zero only within ``order h / 2`` of that centre on each axis; so the tiles
    needed at a point x are those meeting the cube ``x ± reach`` (per axis),
    ``reach = order · h_max / 2`` with ``h_max`` the coarsest level's spacing (h0),
    widened by 1e-9 for rounding: exact and conservative. A cubic store with h0 = 0.1 and
    0.4-wide tiles needs at most 8 tiles per point (of 219 for a global store).
    A point's value depends only on those B-splines, so it is bitwise the same as with
    every tile read. When the tiles needed reach :data:`FULL_LOAD_FRACTION` of the
    store, all are read.

    Larger batches, and :attr:`levels`, :attr:`index` or :attr:`full`, read every tile
    (once) and evaluate with the compiled folded index
    (:class:`~geoidspline.spline.BrickIndex`).

    Each tile's size and sha256 are checked (when ``verify``) as it is read; a damaged
    tile raises :class:`~geoidspline.errors.StoreCorruptError` naming it, for the query
    that needed it and for every later one.

    Memory: a tile read holds its file's bytes for a moment (30 kB to 0.5 MB for the
    stores measured) and then 16 bytes per coefficient while the store is partly read; the complete spline 16 bytes per
    coefficient (sorted int64 keys and float64 values per level: 3.0 MB for the
    186,518-coefficient global 0.5 m store); the folded index, built on the first batch
    of :data:`~geoidspline.spline.FOLDED_FROM_POINTS` points or more, about 190-210
    bytes per coefficient on top for a six-level store (35 MB for that store), about 20
    for one or two dense levels (92 MB for a 4.7 M-coefficient EGM96 store), and
    0.3-0.7 s per 200,000 coefficients to build, with a transient peak of 2-3 GB for
    5 M coefficients. Nothing is evicted: memory grows to the complete spline at most,
    as with GeographicLib's ``Geoid::CacheAll``; a counterpart of its ``CacheArea``
    (keep one area only) is not offered, since a tile is read in a few ms and every
    tile of the global 0.5 m store in 0.3 s.

    Thread safety: tiles are read and the partial spline rebuilt under a lock; the
    splines handed to evaluation are immutable snapshots, so concurrent queries from
    any number of threads are safe and see the same values. A reader keeps using the
    manifest it opened: after a regional update (``geoid-fit --update``) its tiles are
    still on disk (kept for exactly this), but after a second update they are gone and
    a tile not yet read raises :class:`~geoidspline.errors.StoreError` asking to open
    the store again.
    """

    def __init__(self, root: Path, manifest: dict, verify: bool = True):
        self.path = root
        self.manifest = manifest
        self.verify = verify
        meta = manifest["spline"]
        self.order = int(meta["order"])
        self.h0 = float(meta["h0"])
        self.tile_size = float(meta["tile_size"])
        coarsest = max([self.h0] + [float(lv["h"]) for lv in meta.get("levels", ())])
        self.reach = self.order * coarsest / 2.0
        self._entries = {tuple(int(v) for v in e["tile"]): e for e in manifest["tiles"]}
        self._lock = threading.RLock()
        self._tiles: dict = {}  # tile -> (levels, indices, values) as read
        self._partial = AmbientSpline([])  # the spline of the tiles read so far
        self._full: AmbientSpline | None = None

    # -- reading --------------------------------------------------------------------

    @property
    def tiles_read(self) -> int:
        """How many of the store's tiles have been read so far."""
        return len(self._entries) if self._full is not None else len(self._tiles)

    def _read(self, tile):
        entry = self._entries[tile]
        path = self.path / entry["file"]
        try:
            with open(path, "rb") as fh:
                data = fh.read()
        except FileNotFoundError:
            raise self._missing(path, entry) from None
        if len(data) != entry["bytes"]:
            raise StoreCorruptError(
                f"{path}: tile {entry['tile']} is {len(data)} bytes, the manifest says {entry['bytes']} "
                f"(truncated or altered)")
        if self.verify and hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise StoreCorruptError(f"{path}: tile {entry['tile']} does not match its sha256 in the manifest")
        indices, levels, values = _read_tile_file(path, entry, data)
        return levels, indices, values

    def _missing(self, path, entry):
        try:
            now = _load_manifest(self.path)["store_version"]
        except StoreError:
            now = None
        if now is not None and now != self.manifest["store_version"]:
            return StoreError(
                f"{path}: tile {entry['tile']} of store version {self.manifest['store_version']} is gone: the "
                f"store has been rewritten since it was opened (now version {now}); open it again")
        return StoreCorruptError(f"{path}: tile {entry['tile']} is missing")

    def _build(self, tiles):
        by_level: dict[int, list] = {}
        for tile in tiles:
            levels, indices, values = self._tiles[tile]
            for level in np.unique(levels):
                sel = levels == level
                by_level.setdefault(int(level), []).append((indices[sel], values[sel]))
        out = []
        for level in sorted(by_level):
            idx = np.concatenate([p[0] for p in by_level[level]])
            val = np.concatenate([p[1] for p in by_level[level]])
            out.append(LevelSpline.from_indices(level, self.h0 / 2.0**level, self.order, idx, val))
        return AmbientSpline(out)

    @property
    def full(self) -> AmbientSpline:
        """The complete spline (every tile read, once)."""
        if self._full is None:
            with self._lock:
                if self._full is None:
                    for tile in self._entries:  # manifest order
                        if tile not in self._tiles:
                            self._tiles[tile] = self._read(tile)
                    self._full = self._build(list(self._entries))
                    self._tiles = {}
                    self._partial = None
        return self._full

    def tiles_at(self, points) -> list:
        """The store's tiles that can hold a B-spline non-zero at any of points (M, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        if points.size == 0:
            return []
        size = self.tile_size
        lo = np.floor((points - self.reach) / size - 1e-9).astype(np.int64)
        hi = np.floor((points + self.reach) / size + 1e-9).astype(np.int64)
        span = int((hi - lo).max()) + 1
        steps = np.arange(span)
        offsets = np.stack(np.meshgrid(steps, steps, steps, indexing="ij"), axis=-1).reshape(-1, 3)
        cand = lo[:, None, :] + offsets[None, :, :]
        cand = cand[np.all(cand <= hi[:, None, :], axis=2)]
        return [t for t in map(tuple, np.unique(cand, axis=0).tolist()) if t in self._entries]

    def _covering(self, points) -> AmbientSpline:
        """A spline holding every tile needed at points: the complete one, or a partial one."""
        if self._full is not None:
            return self._full
        needed = self.tiles_at(points)
        with self._lock:
            if self._full is not None:
                return self._full
            missing = [t for t in needed if t not in self._tiles]
            if not missing:
                return self._partial
            if len(self._tiles) + len(missing) >= FULL_LOAD_FRACTION * len(self._entries):
                return self.full
            for tile in missing:
                self._tiles[tile] = self._read(tile)
            # a new snapshot: evaluations already running keep theirs
            self._partial = self._build(sorted(self._tiles))
            return self._partial

    # -- the spline's interface ----------------------------------------------------

    @property
    def levels(self):
        return self.full.levels

    @property
    def index(self):
        return self.full.index

    @property
    def coefficient_count(self) -> int:
        return int(self.manifest["spline"]["coefficients"])

    def evaluate_points(self, points, nderiv=0):
        """Values (M,) or value+derivatives (M, 4|10) at ambient points (M, 3); see
        :meth:`geoidspline.spline.AmbientSpline.evaluate_points`."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if points.shape[0] >= FOLDED_FROM_POINTS:
            return self.full.evaluate_points(points, nderiv)
        return self._covering(points).evaluate_points(points, nderiv)

    def undulation(self, latitude, longitude):
        """N in metres at latitude/longitude in degrees; see
        :meth:`geoidspline.spline.AmbientSpline.undulation`."""
        if np.size(latitude) >= FOLDED_FROM_POINTS or np.size(longitude) >= FOLDED_FROM_POINTS:
            return self.full.undulation(latitude, longitude)  # checks the coordinates in its kernel
        latitude, longitude = check_coordinates(latitude, longitude)
        if latitude.size >= FOLDED_FROM_POINTS:  # broadcasting made it a large batch
            return self.full.undulation(latitude, longitude)
        shape = latitude.shape
        points = directions(latitude.ravel(), longitude.ravel())
        values = self._covering(points).evaluate_points(points).reshape(shape)
        return values[()] if shape == () else values


class TileStore:
    """A tile store opened read-only.

    Opening reads the manifest and checks that every tile file is there with its
    manifest size (a few ms for 219 tiles); tiles are read, sha256-checked and merged
    into the store's spline (:attr:`spline`, a :class:`StoreSpline`) as queries need
    them: a one-point query reads at most 8 tiles of a global store, a batch of
    :data:`~geoidspline.spline.FOLDED_FROM_POINTS` points or more reads all of them.
    ``lazy=False`` reads and checks every tile at opening. Memory and thread safety:
    see :class:`StoreSpline`; queries are thread-safe.
    """

    def __init__(self, root: Path, manifest: dict, spline: AmbientSpline | None = None, verify: bool = True):
        self.path = root
        self.manifest = manifest
        self.spline = StoreSpline(root, manifest, verify=verify)
        if spline is not None:
            self.spline._full = spline

    @classmethod
    def open(cls, path, verify=True, lazy=True):
        """Open the store at ``path``: the manifest now, the tiles when needed (all now
        with ``lazy=False``). ``verify=False`` skips the sha256 checks (sizes are
        always checked)."""
        root = Path(path)
        manifest = _load_manifest(root)
        for entry in manifest["tiles"]:
            tile_path = root / entry["file"]
            try:
                size = tile_path.stat().st_size
            except FileNotFoundError:
                raise StoreCorruptError(f"{tile_path}: tile {entry['tile']} is missing") from None
            if size != entry["bytes"]:
                raise StoreCorruptError(
                    f"{tile_path}: tile {entry['tile']} is {size} bytes, the manifest says {entry['bytes']} (truncated or altered)"
                )
        store = cls(root, manifest, verify=verify)
        if not lazy:
            store.spline.full  # noqa: B018 (reads and checks every tile now)
        return store

    def undulation(self, latitude, longitude):
        """Geoid undulation N in metres at latitude/longitude (degrees).

        Scalars give a scalar, arrays broadcast; NaN gives NaN; a latitude outside
        [-90, 90] raises :class:`~geoidspline.errors.CoordinateError`. Outside the
        store's region the value is not meaningful (see :meth:`covers`).
        """
        return self.spline.undulation(latitude, longitude)

    def covers(self, latitude, longitude):
        """Whether points lie inside the region the store was fitted for."""
        from .region import Region

        latitude, longitude = check_coordinates(latitude, longitude)
        return Region(*self.manifest["region"]).contains(latitude, longitude)

    def info(self) -> dict:
        """The manifest summary that ``geoid-info --json`` prints."""
        m = self.manifest
        acc = m["accuracy"]
        size = (self.path / MANIFEST).stat().st_size + sum(e["bytes"] for e in m["tiles"])
        return {
            "store": str(self.path),
            "format_version": m["format_version"],
            "store_version": m["store_version"],
            "provenance": m["provenance"],
            "region": m["region"],
            "order": m["spline"]["order"],
            "h0": m["spline"]["h0"],
            "tolerance_m": m["fit"]["tolerance_m"],
            "converged": m["fit"]["converged"],
            "coefficients": m["spline"]["coefficients"],
            "levels": m["spline"]["levels"],
            "tiles": len(m["tiles"]),
            "max_error_m": acc["max_error_m"],
            "rms_error_m": acc["rms_error_m"],
            "p99_error_m": acc["p99_error_m"],
            "check_points": acc["check_points"],
            "check_truth": acc["check_truth"],
            "node_max_error_m": acc["node_max_error_m"],
            "node_rms_error_m": acc["node_rms_error_m"],
            "nodes": acc["nodes"],
            "bytes": size,
            "fit_seconds": m["fit"]["seconds"],
        }


def verify_store(path) -> list[str]:
    """Every problem of a store's files, one message each naming the tile file:
    missing, truncated (size differs from the manifest) or altered (sha256 differs).
    An empty list means every tile matches its manifest entry."""
    root = Path(path)
    manifest = _load_manifest(root)
    problems = []
    for entry in manifest["tiles"]:
        tile_path = root / entry["file"]
        if not tile_path.exists():
            problems.append(f"{tile_path}: tile {entry['tile']} is missing")
            continue
        size = tile_path.stat().st_size
        if size != entry["bytes"]:
            problems.append(f"{tile_path}: tile {entry['tile']} is {size} bytes, the manifest says {entry['bytes']}"
                            f" ({'truncated' if size < entry['bytes'] else 'altered'})")
        elif _sha256(tile_path) != entry["sha256"]:
            problems.append(f"{tile_path}: tile {entry['tile']} is altered (sha256 differs from the manifest)")
    return problems
