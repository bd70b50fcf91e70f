"""Reading a store: opening checks, lazy tile reads with their digests, the query API.

Opening reads the manifest and checks that every tile file exists with the size the
manifest gives; a tile's sha256 is checked when the tile is read, which is when a query
first needs it (or at opening with ``lazy=False``). A store whose files disagree with
the manifest is refused, naming the tile: it never returns numbers from such a tile.
A :class:`TileStore`'s queries are thread-safe (see :class:`StoreSpline`).
"""

from __future__ import annotations

import hashlib
import itertools
import os
import threading
from pathlib import Path

import numpy as np

from ..bspline.level import LevelSpline
from ..errors import StoreCorruptError, StoreError, StoreFileMissingError
from ..hierarchy.ambient import FOLDED_FROM_POINTS, AmbientSpline
from ..sphere.coordinates import check_coordinates, directions
from .coverage import coverage_of
from .format import LOCK, MANIFEST, MARKER, TileDirectory, load_manifest, read_tile_levels
from .signing import SignatureError, load_signed_manifest, signature_name

#: Fraction of a store's tiles from which a small batch that needs them loads them all
#: (one full read instead of many partial rebuilds).
FULL_LOAD_FRACTION = 0.5


class StoreSpline:
    """The ambient spline of a store, read tile by tile as queries need it.

    Batches of fewer than :data:`~geoidspline.hierarchy.ambient.FOLDED_FROM_POINTS` points
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
    (:class:`~geoidspline.bspline.index.BrickIndex`).

    Each tile's size and sha256 are checked (when ``verify``) as it is read; a damaged
    tile raises :class:`~geoidspline.errors.StoreCorruptError` naming it, for the query
    that needed it and for every later one.

    Memory: a tile read holds its file's bytes for a moment (30 kB to 0.5 MB for the
    stores measured) and then 16 bytes per coefficient while the store is partly read; the complete spline 16 bytes per
    coefficient (sorted int64 keys and float64 values per level: 3.0 MB for the
    186,518-coefficient global 0.5 m store); the folded index, built on the first batch
    of :data:`~geoidspline.hierarchy.ambient.FOLDED_FROM_POINTS` points or more, about 190-210
    bytes per coefficient on top for a six-level store (35 MB for that store), about 20
    for one or two dense levels (92 MB for a 4.7 M-coefficient EGM96 store), and
    0.3-0.7 s per 200,000 coefficients to build, with a transient peak of 2-3 GB for
    5 M coefficients. Nothing is evicted: memory grows to the complete spline at most,
    as with GeographicLib's ``Geoid::CacheAll``; a counterpart of its ``CacheArea``
    (keep one area only) is not offered, since a tile is read in a few ms and every
    tile of the global 0.5 m store in 0.3 s.

    Coverage: :meth:`undulation` answers NaN where the store has no data
    (:attr:`coverage`); :meth:`evaluate_points`, the spline on R³, and :attr:`full`
    answer everywhere, as the ambient spline does.

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
        #: where the store has data (:class:`~geoidspline.sphere.coverage.Coverage`)
        self.coverage = coverage_of(root / MANIFEST, manifest)
        meta = manifest["spline"]
        self.order = int(meta["order"])
        self.h0 = float(meta["h0"])
        self.tile_size = float(meta["tile_size"])
        coarsest = max([self.h0] + [float(lv["h"]) for lv in meta.get("levels", ())])
        self.reach = self.order * coarsest / 2.0
        self._entries = {tuple(int(v) for v in e["tile"]): e for e in manifest["tiles"]}
        self._lock = threading.RLock()
        self._tiles: dict = {}  # tile -> {level: (sorted keys, values)} as read
        self._partial = AmbientSpline([])  # the spline of the tiles read so far
        self._full: AmbientSpline | None = None

    # -- reading --------------------------------------------------------------------

    @property
    def tiles_read(self) -> int:
        """How many of the store's tiles have been read so far."""
        return len(self._entries) if self._full is not None else len(self._tiles)

    def _read(self, tile, tiles: TileDirectory):
        entry = self._entries[tile]
        path = self.path / entry["file"]
        try:
            data = tiles.read(entry)
        except FileNotFoundError:
            raise self._missing(path, entry) from None
        if self.verify and hashlib.sha256(data).hexdigest() != entry["sha256"]:
            raise StoreCorruptError(f"{path}: tile {entry['tile']} does not match its sha256 in the manifest")
        return read_tile_levels(path, entry, data, self.manifest)

    def _read_tiles(self, tiles):
        """Read ``tiles`` (not read yet) into self._tiles; the tile directory is opened once."""
        if not tiles:
            return
        try:
            directory = TileDirectory(self.path)
        except StoreFileMissingError:
            raise self._missing(self.path / "tiles", self._entries[tiles[0]]) from None
        with directory:
            for tile in tiles:
                self._tiles[tile] = self._read(tile, directory)

    def _missing(self, path, entry):
        try:
            now = load_manifest(self.path)["store_version"]
        except StoreError:
            now = None
        if now is not None and now != self.manifest["store_version"]:
            return StoreError(
                f"{path}: tile {entry['tile']} of store version {self.manifest['store_version']} is gone: the "
                f"store has been rewritten since it was opened (now version {now}); open it again")
        return StoreCorruptError(f"{path}: tile {entry['tile']} is missing")

    def _build(self, tiles, complete=False):
        # per level: only keys and values are held (16 bytes a coefficient), never index
        # triples. A coefficient's tile is the cube of its support centre, which grows
        # with its index, so the tiles of one first tile index (a "slab") hold a run of
        # keys of their own: each slab is joined and sorted on its own and copied into
        # the level's arrays. ``complete`` (the whole spline) reads the tiles not read yet
        # slab by slab and lets each slab's tiles go once copied, so the coefficients are
        # never held twice over; the level sizes are then the manifest's, and checked
        tiles = sorted(tiles)
        if complete:
            sizes = {int(lv["level"]): int(lv["coefficients"]) for lv in self.manifest["spline"]["levels"]}
        else:
            sizes = {}
            for tile in tiles:
                for level, (keys, _) in self._tiles[tile].items():
                    sizes[level] = sizes.get(level, 0) + keys.size
        joined = {level: (np.empty(n, np.int64), np.empty(n)) for level, n in sizes.items()}
        filled = dict.fromkeys(sizes, 0)
        for _, slab in itertools.groupby(tiles, key=lambda tile: tile[0]):
            slab = list(slab)
            if complete:
                self._read_tiles([t for t in slab if t not in self._tiles])
            by_level: dict[int, list] = {}
            for tile in slab:
                for level, part in (self._tiles.pop(tile) if complete else self._tiles[tile]).items():
                    by_level.setdefault(level, []).append(part)
            for level, parts in by_level.items():
                keys = np.concatenate([p[0] for p in parts])
                val = np.concatenate([p[1] for p in parts])
                if len(parts) > 1:
                    order = np.argsort(keys, kind="stable")
                    keys, val = keys[order], val[order]
                at = filled.get(level, 0)
                if at + keys.size > sizes.get(level, 0):
                    raise self._count_mismatch(level, f"more than {sizes.get(level, 0)}")
                joined[level][0][at:at + keys.size] = keys
                joined[level][1][at:at + keys.size] = val
                filled[level] = at + keys.size
            del by_level, parts
        out = []
        for level in sorted(joined):
            keys, val = joined.pop(level)
            if filled[level] != keys.size:
                raise self._count_mismatch(level, filled[level])
            if keys.size > 1 and np.any(keys[1:] <= keys[:-1]):
                why = ("a coefficient is stored twice" if np.any(keys[1:] == keys[:-1])
                       else "a coefficient lies outside the order of its tile's cube")
                raise StoreCorruptError(f"{self.path}: the tiles of level {level} disagree ({why})")
            if keys.size:
                out.append(LevelSpline(level, self.h0 / 2.0**level, self.order, keys, val))
        step = self.manifest["spline"].get("value_step_m")
        return AmbientSpline(out, value_step=float(step) if step else None)

    def _count_mismatch(self, level, held):
        wanted = {int(lv["level"]): int(lv["coefficients"]) for lv in self.manifest["spline"]["levels"]}
        return StoreCorruptError(f"{self.path / MANIFEST}: the tiles hold {held} coefficients of level {level}, "
                                 f"the manifest says {wanted.get(level, 0)}")

    @property
    def full(self) -> AmbientSpline:
        """The complete spline (every tile read, once)."""
        if self._full is None:
            with self._lock:
                if self._full is None:
                    self._full = self._build(list(self._entries), complete=True)  # reads the rest
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
            self._read_tiles(missing)
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
        :meth:`geoidspline.hierarchy.ambient.AmbientSpline.evaluate_points`."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if points.shape[0] >= FOLDED_FROM_POINTS:
            return self.full.evaluate_points(points, nderiv)
        return self._covering(points).evaluate_points(points, nderiv)

    def undulation(self, latitude, longitude):
        """N in metres at latitude/longitude in degrees, NaN outside the store's coverage
        (:attr:`coverage`); see
        :meth:`geoidspline.hierarchy.ambient.AmbientSpline.undulation`."""
        latitude, longitude = check_coordinates(latitude, longitude)
        shape = latitude.shape
        covered = np.asarray(self.coverage.covers(latitude, longitude))
        if latitude.size >= FOLDED_FROM_POINTS or covered.all():
            # the whole spline evaluates every point at once: cheaper than gathering
            values = np.asarray(self._spline_undulation(latitude, longitude), dtype=np.float64)
            if not covered.all():
                values = np.where(covered, values, np.nan)
        else:
            # only the covered points: their tiles, none for the points outside
            values = np.full(shape, np.nan)
            if covered.any():
                values[covered] = self._spline_undulation(latitude[covered], longitude[covered])
        return values[()] if shape == () else values

    def _spline_undulation(self, latitude, longitude):
        """The spline's values (covered or not) at checked coordinates."""
        if latitude.size >= FOLDED_FROM_POINTS:
            return self.full.undulation(latitude, longitude)
        shape = latitude.shape
        points = directions(latitude.ravel(), longitude.ravel())
        return self._covering(points).evaluate_points(points).reshape(shape)


class TileStore:
    """A tile store opened read-only.

    Opening reads the manifest and checks that every tile file is there with its
    manifest size (a few ms for 219 tiles); tiles are read, sha256-checked and merged
    into the store's spline (:attr:`spline`, a :class:`StoreSpline`) as queries need
    them: a one-point query reads at most 8 tiles of a global store, a batch of
    :data:`~geoidspline.hierarchy.ambient.FOLDED_FROM_POINTS` points or more reads all of them.
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
    def open(cls, path, verify=True, lazy=True, key=None):
        """Open the store at ``path``: the manifest now, the tiles when needed (all now
        with ``lazy=False``). ``verify=False`` skips the sha256 checks (sizes, names and
        the tiles' own records are always checked). ``key``: an Ed25519 public key
        (object or PEM file) that must have signed the manifest
        (:mod:`geoidspline.store.signing`); the tiles' sha256 are then always checked,
        since the signature covers the tiles through them."""
        root = Path(path)
        if key is not None:
            manifest = load_signed_manifest(root, key)
            verify = True
        else:
            manifest = load_manifest(root)
        with TileDirectory(root) as tiles:
            for entry in manifest["tiles"]:
                problem = tiles.stat_problem(entry)
                if problem:
                    raise StoreCorruptError(problem)
        store = cls(root, manifest, verify=verify)
        if not lazy:
            store.spline.full  # noqa: B018 (reads and checks every tile now)
        return store

    @property
    def coverage(self):
        """Where the store has data: :class:`~geoidspline.sphere.coverage.Coverage`."""
        return self.spline.coverage

    def undulation(self, latitude, longitude):
        """Geoid undulation N in metres at latitude/longitude (degrees).

        Scalars give a scalar, arrays broadcast; NaN gives NaN; a latitude outside
        [-90, 90] raises :class:`~geoidspline.errors.CoordinateError`. Outside the
        store's coverage (its region and where its source had data, see :meth:`covers`)
        the value is NaN: never a number the data do not support.
        """
        return self.spline.undulation(latitude, longitude)

    def deflection(self, latitude, longitude):
        """Deflection of the vertical (ξ, η, arcseconds) and the geoid slope (metres per
        metre) from the spline's analytic gradient; see
        :func:`geoidspline.query.derived.deflection`."""
        from ..hierarchy.derived import Deflection, deflection

        result = deflection(self, latitude, longitude)
        covered = np.asarray(self.covers(latitude, longitude))
        if covered.all():
            return result
        return Deflection(*(np.where(covered, np.asarray(v, dtype=np.float64), np.nan)[()] for v in result))

    def orthometric_height(self, latitude, longitude, ellipsoidal_height):
        """Orthometric height H = h − N (metres) from the ellipsoidal height h (metres)."""
        from ..geodesy.heights import convert_height

        return convert_height(self.undulation(latitude, longitude), ellipsoidal_height, "ellipsoidal")

    def ellipsoidal_height(self, latitude, longitude, orthometric_height):
        """Ellipsoidal height h = H + N (metres) from the orthometric height H (metres)."""
        from ..geodesy.heights import convert_height

        return convert_height(self.undulation(latitude, longitude), orthometric_height, "orthometric")

    def error_bound(self, latitude, longitude):
        """The measured error bound (metres) of the tile each point falls in; see
        :func:`geoidspline.store.error_bound.tile_error_bound`."""
        from .error_bound import tile_error_bound

        bound = tile_error_bound(self, latitude, longitude)
        covered = self.covers(latitude, longitude)
        return np.where(covered, bound, np.nan)[()]

    def __repr__(self):
        m = self.manifest
        prov = m.get("provenance", {})
        s, w, n, e = m["region"]
        return (f"<TileStore {str(self.path)!r} version {m['store_version']}: {m['spline']['coefficients']:,} "
                f"coefficients of order {m['spline']['order']} in {len(m['tiles'])} tiles; "
                f"{prov.get('model', 'unknown')} from {prov.get('source', '?')}; region S {s:g} W {w:g} N {n:g} E {e:g}>")

    def covers(self, latitude, longitude, reason: bool = False):
        """Whether the store has data at points (latitude/longitude in degrees): inside
        its region and, for a grid source, where every node of the source cell holding
        the point had data. A bool for scalars, else a boolean array; NaN coordinates
        are not covered. With ``reason``, :meth:`coverage_reason` instead."""
        if reason:
            return self.coverage_reason(latitude, longitude)
        latitude, longitude = check_coordinates(latitude, longitude)
        covered = self.coverage.covers(latitude, longitude)
        return bool(covered) if np.ndim(covered) == 0 else covered

    def coverage_reason(self, latitude, longitude):
        """Per point ``"inside"``, ``"outside the region"`` or ``"no data in the source
        here"`` (the point is in the region, but the source had no data in the cell
        holding it); a str for scalars, else an array of str. A NaN coordinate is
        ``"outside the region"``."""
        latitude, longitude = check_coordinates(latitude, longitude)
        return self.coverage.reasons(latitude, longitude)

    def info(self) -> dict:
        """The manifest summary that ``geoid-info --json`` prints."""
        m = self.manifest
        acc = m["accuracy"]
        params = m["fit"].get("parameters") or {}
        max_level = int(params.get("max_level", max((lv["level"] for lv in m["spline"]["levels"]), default=0)))
        size = sum(e["bytes"] for e in m["tiles"])
        signature = signature_name(m["store_version"])
        signed = os.path.isfile(self.path / signature)
        for name in (MANIFEST, MARKER, LOCK) + ((signature,) if signed else ()):  # the store's own small files
            try:
                size += os.stat(self.path / name, follow_symlinks=False).st_size
            except OSError:
                pass
        return {
            "store": str(self.path),
            "format_version": m["format_version"],
            "store_version": m["store_version"],
            "signature": signature if signed else None,
            "provenance": m["provenance"],
            "region": m["region"],
            "order": m["spline"]["order"],
            "h0": m["spline"]["h0"],
            "tolerance_m": m["fit"]["tolerance_m"],
            "converged": m["fit"]["converged"],
            "coefficients": m["spline"]["coefficients"],
            "levels": m["spline"]["levels"],
            # levels 0..max_level were allowed; a hierarchical fit may leave coarse ones
            # empty (their B-splines replaced by children) and stop before the finest
            "levels_chosen": max_level + 1,
            "levels_used": sum(1 for lv in m["spline"]["levels"] if lv["coefficients"] and lv["level"] <= max_level),
            "fit_method": m["fit"].get("method"),  # absent from damaged manifests: shown as unknown
            "fit_parameters": params,
            "tiles": len(m["tiles"]),
            "max_error_m": acc["max_error_m"],
            "rms_error_m": acc["rms_error_m"],
            "p99_error_m": acc["p99_error_m"],
            "check_points": acc["check_points"],
            "check_truth": acc["check_truth"],
            "node_max_error_m": acc["node_max_error_m"],
            "node_rms_error_m": acc["node_rms_error_m"],
            "cell_centre_max_m": acc.get("cell_centre_max_m"),
            "nodes": acc["nodes"],
            "bytes": size,
            "fit_seconds": m["fit"]["seconds"],
            "history": m.get("history", []),
            "coverage": [
                {"region": list(part.region.as_tuple()), "source": part.source,
                 "nodata_nodes": int(part.lattice.nodata.sum()) if part.lattice is not None else 0}
                for part in self.coverage.parts
            ],
        }


def verify_store(path, key=None) -> list[str]:
    """Every problem of a store's files, one message each naming the tile file:
    missing, not a regular file, truncated or altered (size or sha256 differs from
    the manifest), or in the wrong place (its own record of tile, store and spline,
    or the support centres of its coefficients, disagree with its manifest entry);
    then whether the tiles together hold the coefficients the manifest counts.
    An empty list means every tile matches its manifest entry. A manifest that
    cannot be read or breaks the schema raises :class:`StoreError`. ``key``: an Ed25519
    public key that must have signed the manifest; a missing or mismatching signature
    is a problem naming the file (checksums find damage; only a signature finds a
    forgery that recomputed them).
    """
    root = Path(path)
    if key is not None:
        try:
            manifest = load_signed_manifest(root, key)  # the tiles below are this manifest's
        except SignatureError as exc:
            return [str(exc)]
    else:
        manifest = load_manifest(root)
    store = TileStore(root, manifest, verify=True)  # decodes the coverage record
    spline = store.spline
    problems = []
    with TileDirectory(root) as tiles:
        for entry in manifest["tiles"]:
            tile = tuple(int(v) for v in entry["tile"])
            problem = tiles.stat_problem(entry)
            if problem is None:
                try:
                    data = tiles.read(entry)
                    if hashlib.sha256(data).hexdigest() != entry["sha256"]:
                        problem = f"{root / entry['file']}: tile {entry['tile']} is altered (sha256 differs from the manifest)"
                    else:
                        spline._tiles[tile] = read_tile_levels(root / entry["file"], entry, data, manifest)
                except FileNotFoundError:
                    problem = f"{root / entry['file']}: tile {entry['tile']} is missing"
                except StoreError as exc:
                    problem = str(exc)
            if problem:
                problems.append(problem)
    if not problems:
        try:
            spline._build(list(spline._entries), complete=True)
        except StoreError as exc:
            problems.append(str(exc))
    return problems
