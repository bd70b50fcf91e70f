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
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path

import numpy as np

from ..bspline.level import LevelSpline
from ..errors import StoreCorruptError, StoreError, StoreFileMissingError
from ..hierarchy.ambient import FOLDED_FROM_POINTS, AmbientSpline
from ..sphere.coordinates import check_coordinates, directions
from .coverage import coverage_of
from .format import LOCK, MANIFEST, MARKER, TileDirectory, load_manifest, read_tile_levels
from .signing import SignatureError, load_signed_manifest, signature_name

#: Fraction of a store's tiles from which a batch that needs them reads them all (one
#: complete read instead of a partial spline nearly as large).
FULL_LOAD_FRACTION = 0.5


CACHE_BYTES = 512 * 1024**2
"""Default bound (bytes) of what a :class:`StoreSpline` keeps between queries besides the
complete spline: its decoded tiles (least recently used dropped first) and how far its
partial spline may grow (see :class:`StoreSpline`)."""


PARTIAL_BYTES_PER_COEFFICIENT = 40
"""Bytes a coefficient of a partial spline is taken to hold with its query index: 16 for
its key and value, the rest a bound on the index's share for one level (int16 tables of a
store of 50 M coefficients or more, float64 below; measured: benchmarks/README.md, the
EGM2008 1 mm and EGM96 2 mm stores' index bytes)."""


_LATLON_BOX_SLACK = 2
"""A large lat/lon batch's tiles are those of its bounding lat/lon rectangle when these
are at most this many times the tiles its points need one by one: later batches in the
same rectangle then find them all held, after a cheap test (no directions, no sort)."""


_SAMPLE_POINTS = 16_384
"""A large batch first finds the tiles of this many of its points (evenly spaced in the
batch): when these already reach FULL_LOAD_FRACTION of the store, the whole store is read
without finding the tiles of every point (a global batch)."""


def _level_bytes(levels) -> int:
    return sum(keys.nbytes + values.nbytes for keys, values in levels.values())


def _latlon_box(latitude, longitude):
    """The box (lo, hi) in R³ of the directions of points in the smallest latitude/longitude
    rectangle holding the given ones (degrees, checked; NaN ignored), widened by 1e-9 for
    the rounding of directions; None when the longitudes need a rectangle more than half
    way round (a box of little use) or there is no finite point."""
    # reductions only (a few ms for 10^6 points): later batches in a rectangle test this
    south, north = float(np.fmin.reduce(latitude)), float(np.fmax.reduce(latitude))
    west, east = float(np.fmin.reduce(longitude)), float(np.fmax.reduce(longitude))
    if not (np.isfinite(south) and np.isfinite(west)):
        return None
    if west < -180.0 or east > 180.0:
        longitude = np.remainder(longitude + 180.0, 360.0) - 180.0
        west, east = float(np.fmin.reduce(longitude)), float(np.fmax.reduce(longitude))
    if east - west > 180.0:  # perhaps across the antimeridian
        shifted = np.remainder(longitude, 360.0)
        west, east = float(np.fmin.reduce(shifted)), float(np.fmax.reduce(shifted))
        if east - west > 180.0:
            return None
    # x = cos φ cos λ, y = cos φ sin λ, z = sin φ: products of factors each extreme at an
    # edge of the rectangle or at φ = 0 / λ = a multiple of 90° inside it
    phis = [south, north] + ([0.0] if south < 0.0 < north else [])
    quarter = np.arange(np.ceil(west / 90.0), np.floor(east / 90.0) + 1) * 90.0
    lams = np.r_[west, east, quarter]
    phi, lam = np.meshgrid(np.radians(phis), np.radians(lams), indexing="ij")
    corners = np.stack([np.cos(phi) * np.cos(lam), np.cos(phi) * np.sin(lam), np.sin(phi)], axis=-1).reshape(-1, 3)
    return corners.min(axis=0) - 1e-9, corners.max(axis=0) + 1e-9


class StoreSpline:
    """The ambient spline of a store, read tile by tile as queries need it.

    Which tiles a batch needs. A coefficient lives in the tile holding its support
    centre ``(k + order/2) h`` and its B-spline is non-zero only within ``order h / 2``
    of that centre on each axis; ``reach = order · h_max / 2``, ``h_max`` the spacing of
    the coarsest level holding coefficients, widened by 1e-9 for rounding.

    - Batches of fewer than :data:`~geoidspline.hierarchy.ambient.FOLDED_FROM_POINTS`
      points (:meth:`evaluate_points`, :meth:`undulation`) are evaluated with numpy from
      the tiles meeting the cube ``x ± reach`` of each point x (:meth:`tiles_at`: a cubic
      store with h0 = 0.1 and 0.4-wide tiles needs at most 8 tiles a point, of 219 for a
      global store). A point's value depends only on the B-splines non-zero there.
    - Larger batches are evaluated with the compiled index
      (:class:`~geoidspline.bspline.index.BrickIndex`) of the tiles meeting, for each
      point, the cube of its brick of the coarsest level (``2**BRICK_BITS`` cells of
      ``h_max``, which holds its brick of every finer level) widened by ``reach``
      (:meth:`index_tiles_at`): every B-spline touching a brick that holds the point, of
      every level. The index of those tiles has the point's bricks with the same
      tables, column runs and full-column maps as the index of the whole store, and
      the same values where the point reads them (a folded value the point reads sums
      coarser B-splines whose supports hold the point: all read; a coarser B-spline
      not read adds 0 elsewhere), so every value, gradient and Hessian has the same
      bits as the whole store's index gives (tests: single- and multi-level stores,
      seams, poles). Its tables hold the store's integers when the whole store's
      would (stores of 50 M coefficients or more), a point's brick with the same integers
      and base (its whole table is there): same bits, same bytes a coefficient.
      A batch of latitudes/longitudes takes the tiles of its bounding rectangle's
      box when they are at most ``_LATLON_BOX_SLACK`` times those of its points.

    When the tiles a batch needs reach :data:`FULL_LOAD_FRACTION` of the store, every
    tile is read (:attr:`full`, also what :attr:`levels` and :attr:`index` give), once;
    every later query uses that complete spline. Tiles are decoded on
    :func:`~geoidspline._kernels._clib.threads` threads (the decoder's C code, Zstandard,
    sha256 and file reads release the GIL).

    Caching (GeographicLib's ``Geoid`` is the model: its cache is a rectangle of the grid
    grown as queries need it, or all of it): the spline a batch was evaluated with (the
    *partial* spline, with its index once a large batch needed one) is kept and serves
    every later batch whose tiles it holds. A batch needing tiles it lacks replaces it by
    the spline of the tiles of both, while these hold at most ``cache_bytes /``
    :data:`PARTIAL_BYTES_PER_COEFFICIENT` coefficients, else by the spline of the new
    batch's tiles alone. Decoded tiles are kept too, least recently used dropped first,
    at most ``cache_bytes`` bytes of them (16 bytes a coefficient), so that a rebuilt
    partial spline decodes only tiles it did not hold.

    Memory, then: while a batch is evaluated, the spline and index of the tiles it needs
    (about :data:`PARTIAL_BYTES_PER_COEFFICIENT` bytes a coefficient); between batches,
    at most ``cache_bytes`` of decoded tiles plus the last partial spline (at most
    ``cache_bytes`` unless one batch needed more: then the tiles that batch needed);
    once complete, the complete spline alone (16 bytes a coefficient, and its index), as
    ``Geoid::CacheAll``; reading it whole holds two slabs of decoded tiles at most (the
    one joined, the next decoding). A tile read holds its file's bytes for a moment.
    Figures: benchmarks/README.md, "a big store answers a point or a region".

    Each tile's size and sha256 are checked (when ``verify``) as it is read; a damaged
    tile raises :class:`~geoidspline.errors.StoreCorruptError` naming it, for the query
    that needed it and for every later one.

    Coverage: :meth:`undulation` answers NaN where the store has no data
    (:attr:`coverage`), and reads no tile for such points; :meth:`evaluate_points`, the
    spline on R³, and :attr:`full` answer everywhere, as the ambient spline does.

    Thread safety: tiles are read, splines built and indexes built under one lock (a
    query waits while another builds); the splines handed to evaluation are immutable
    snapshots, kept by the evaluations running with them when a new one replaces them,
    so concurrent queries from any number of threads are safe and see the same values.
    A reader keeps using the manifest it opened: after a regional update (``geoid-fit
    --update``) its tiles are still on disk (kept for exactly this), but after a second
    update they are gone and a tile not yet read raises
    :class:`~geoidspline.errors.StoreError` asking to open the store again.
    """

    def __init__(self, root: Path, manifest: dict, verify: bool = True, cache_bytes: int = CACHE_BYTES):
        self.path = root
        self.manifest = manifest
        self.verify = verify
        if int(cache_bytes) < 0:
            raise ValueError(f"cache_bytes must be 0 or more, not {cache_bytes}")
        #: bytes of decoded tiles kept, and the growth bound of the partial spline
        self.cache_bytes = int(cache_bytes)
        #: where the store has data (:class:`~geoidspline.sphere.coverage.Coverage`)
        self.coverage = coverage_of(root / MANIFEST, manifest)
        meta = manifest["spline"]
        self.order = int(meta["order"])
        self.h0 = float(meta["h0"])
        self.tile_size = float(meta["tile_size"])
        held = [float(lv["h"]) for lv in meta.get("levels", ()) if int(lv["coefficients"])]
        #: spacing of the coarsest level holding coefficients (unit sphere)
        self.h_max = max(held, default=self.h0)
        self.reach = self.order * self.h_max / 2.0
        step = meta.get("value_step_m")
        self._value_step = float(step) if step else None
        self._entries = {tuple(int(v) for v in e["tile"]): e for e in manifest["tiles"]}
        self._entry_tiles = np.array(sorted(self._entries), dtype=np.int64).reshape(-1, 3)
        self._lock = threading.RLock()
        self._tiles: OrderedDict = OrderedDict()  # decoded tiles kept: tile -> {level: (keys, values)}
        self._tile_bytes = 0
        self._seen: set = set()  # every tile read since opening
        self._partial = AmbientSpline([], value_step=self._value_step)  # the spline of _partial_tiles
        self._partial_tiles: frozenset = frozenset()
        self._full: AmbientSpline | None = None

    # -- reading --------------------------------------------------------------------

    @property
    def tiles_read(self) -> int:
        """How many of the store's tiles have been read since opening."""
        return len(self._entries) if self._full is not None else len(self._seen)

    @property
    def tiles_held(self) -> frozenset:
        """The tiles of the partial spline now (all of them once complete)."""
        return frozenset(self._entries) if self._full is not None else self._partial_tiles

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

    def _directory(self, first_tile):
        try:
            return TileDirectory(self.path)
        except StoreFileMissingError:
            raise self._missing(self.path / "tiles", self._entries[first_tile]) from None

    def _decode(self, tiles) -> dict:
        """{tile: {level: (keys, values)}} of ``tiles`` read now, on threads()
        threads; the first failing tile (in the order given) raises."""
        if not tiles:
            return {}
        from .._kernels._clib import threads

        workers = min(threads(), len(tiles))
        with self._directory(tiles[0]) as directory:
            if workers < 2:
                decoded = [self._read(tile, directory) for tile in tiles]
            else:
                with ThreadPoolExecutor(workers) as pool:
                    futures = [pool.submit(self._read, tile, directory) for tile in tiles]
                    try:
                        decoded = [f.result() for f in futures]
                    finally:
                        for f in futures:
                            f.cancel()
        self._seen.update(tiles)
        return dict(zip(tiles, decoded))

    def _parts(self, tiles) -> dict:
        """{tile: levels} of ``tiles``: the kept ones, the others decoded now."""
        missing = [t for t in tiles if t not in self._tiles]
        decoded = self._decode(missing)
        return {t: decoded[t] if t in decoded else self._tiles[t] for t in tiles}

    def _keep(self, parts: dict):
        """Keep decoded tiles (most recently used last), within cache_bytes."""
        for tile, levels in parts.items():
            if tile in self._tiles:
                self._tiles.move_to_end(tile)
            else:
                self._tiles[tile] = levels
                self._tile_bytes += _level_bytes(levels)
        while self._tile_bytes > self.cache_bytes and self._tiles:
            _, levels = self._tiles.popitem(last=False)
            self._tile_bytes -= _level_bytes(levels)

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

    def _build(self, tiles, parts_of_slab, sizes=None):
        """The spline of ``tiles``; ``parts_of_slab(slab)`` gives {tile: levels} of a slab's
        tiles (of any list of them); ``sizes``: {level: coefficients} the tiles must hold
        (the manifest's, for the complete spline), else counted from the parts.

        Per level only keys and values are held (16 bytes a coefficient), never index
        triples. A coefficient's tile is the cube of its support centre, which grows
        with its index, so the tiles of one first tile index (a "slab") hold a run of
        keys of their own: each slab is joined and sorted on its own and copied into the
        level's arrays. The complete spline decodes its tiles slab by slab and lets each
        slab's go once copied, so the coefficients are never held twice over."""
        tiles = sorted(tiles)
        if sizes is None:
            sizes = {}
            for tile in tiles:
                for level, (keys, _) in parts_of_slab([tile])[tile].items():
                    sizes[level] = sizes.get(level, 0) + keys.size
        joined = {level: (np.empty(n, np.int64), np.empty(n)) for level, n in sizes.items()}
        filled = dict.fromkeys(sizes, 0)
        for _, slab in itertools.groupby(tiles, key=lambda tile: tile[0]):
            slab = list(slab)
            by_level: dict[int, list] = {}
            for levels in parts_of_slab(slab).values():
                for level, part in levels.items():
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
        return AmbientSpline(out, value_step=self._value_step)

    def _build_complete(self, kept=None):
        """The complete spline: the kept tiles (``kept``, else the cache's) and every
        other tile decoded slab by slab on threads() threads, the next slab's while the
        current one is joined."""
        from .._kernels._clib import threads

        kept = self._tiles if kept is None else kept
        tiles = sorted(self._entries)
        slabs = [list(g) for _, g in itertools.groupby(tiles, key=lambda tile: tile[0])]
        sizes = {int(lv["level"]): int(lv["coefficients"]) for lv in self.manifest["spline"]["levels"]}
        with self._directory(tiles[0]) as directory, ThreadPoolExecutor(max(1, threads())) as pool:
            submitted = {}

            def take(tile):  # a kept tile, no longer counted in the cache
                levels = kept.pop(tile)
                if kept is self._tiles:
                    self._tile_bytes -= _level_bytes(levels)
                return levels

            def submit(i):
                if i < len(slabs):
                    submitted[i] = [(t, take(t) if t in kept else pool.submit(self._read, t, directory))
                                    for t in slabs[i]]

            def parts_of_slab(slab):
                i = slab_at[slab[0]]
                submit(i + 1)  # decoded while this one is joined
                got = submitted.pop(i)
                try:
                    parts = {t: (p.result() if isinstance(p, Future) else p) for t, p in got}
                except BaseException:
                    for pending in [got] + list(submitted.values()):
                        for _, p in pending:
                            if isinstance(p, Future):
                                p.cancel()
                    raise
                self._seen.update(slab)
                return parts

            slab_at = {slab[0]: i for i, slab in enumerate(slabs)}
            submit(0)
            return self._build(tiles, parts_of_slab, sizes)

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
                    self._full = self._build_complete()
                    self._tiles, self._tile_bytes = OrderedDict(), 0
                    self._partial, self._partial_tiles = None, frozenset()
        return self._full

    # -- the tiles a batch needs ---------------------------------------------------------

    def _tiles_in_ranges(self, lo, hi) -> set:
        """The store's tiles in any of the tile ranges lo..hi (K, 3), inclusive."""
        if lo.shape[0] == 0:
            return set()
        bound = int(np.ceil(1.0 / self.tile_size)) + 2  # every tile lies within ±bound
        lo = np.clip(lo, -bound, bound)
        hi = np.clip(hi, -bound - 1, bound)
        width = 2 * bound + 1
        span = np.maximum(hi - lo + 1, 0)
        spans = int(span.max()) + 1
        packed = ((lo + bound) @ np.array([width * width, width, 1], np.int64)) * spans**3 \
            + span @ np.array([spans * spans, spans, 1], np.int64)
        packed = np.unique(packed)  # the distinct ranges
        span = np.stack([packed // spans**2 % spans, packed // spans % spans, packed % spans], axis=1)
        corner = packed // spans**3
        lo = np.stack([corner // (width * width), corner // width % width, corner % width], axis=1) - bound
        found = set()
        for s in np.unique(span, axis=0):
            if s.min() == 0:
                continue
            at = lo[np.all(span == s, axis=1)]
            steps = np.stack(np.meshgrid(*(np.arange(v) for v in s), indexing="ij"), axis=-1).reshape(-1, 3)
            found.update(map(tuple, np.unique((at[:, None, :] + steps[None]).reshape(-1, 3), axis=0).tolist()))
        return {t for t in found if t in self._entries}

    def tiles_at(self, points) -> list:
        """The store's tiles that can hold a B-spline non-zero at any of points (M, 3)."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        lo = np.floor((points - self.reach) / self.tile_size - 1e-9).astype(np.int64)
        hi = np.floor((points + self.reach) / self.tile_size + 1e-9).astype(np.int64)
        return sorted(self._tiles_in_ranges(lo, hi))

    def _brick_cube_tiles(self, lo_brick, hi_brick):
        """Tile ranges of the cubes from brick lo_brick to brick hi_brick (coarsest level,
        integer arrays (..., 3)) widened by the reach."""
        side = self._brick_side()
        lo = np.floor((lo_brick * side - self.reach) / self.tile_size - 1e-9).astype(np.int64)
        hi = np.floor(((hi_brick + 1) * side + self.reach) / self.tile_size + 1e-9).astype(np.int64)
        return lo, hi

    def _brick_side(self) -> float:
        from .._kernels.query import BRICK_BITS  # the index's: large batches only

        return (1 << BRICK_BITS) * self.h_max

    def index_tiles_at(self, points) -> list:
        """The store's tiles that can hold a B-spline touching a brick (of any level of
        the query index) that holds one of points (M, 3): what the index needs to
        evaluate them as the whole store's does."""
        points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        points = points[np.isfinite(points).all(axis=1)]
        bricks = np.floor(np.clip(points, -4.0, 4.0) / self._brick_side()).astype(np.int64)  # far points: no tile
        return sorted(self._tiles_in_ranges(*self._brick_cube_tiles(bricks, bricks)))

    def _many(self, tiles) -> bool:
        return len(tiles) >= FULL_LOAD_FRACTION * len(self._entries)

    def _index_needed(self, points):
        """What the index needs at points (M, 3): index_tiles_at's tiles, or every tile
        when those of a sample of the points reach FULL_LOAD_FRACTION of the store."""
        if points.shape[0] > 2 * _SAMPLE_POINTS and self._many(
                self.index_tiles_at(points[::points.shape[0] // _SAMPLE_POINTS])):
            return frozenset(self._entries)
        return set(self.index_tiles_at(points))

    def _box_tiles(self, lo, hi) -> set:
        """The store's tiles an index needs for points anywhere in the box lo..hi (R³)."""
        side = self._brick_side()
        first, last = self._brick_cube_tiles(np.floor(lo / side), np.floor(hi / side))
        inside = np.all((self._entry_tiles >= first) & (self._entry_tiles <= last), axis=1)
        return set(map(tuple, self._entry_tiles[inside].tolist()))

    def _index_tiles_latlon(self, latitude, longitude) -> set:
        """The tiles an index needs at latitude/longitude (degrees, checked, 1-D): those
        of the points' bounding rectangle when held already or at most
        _LATLON_BOX_SLACK times those of the points, else the points' own."""
        if latitude.size == 0:
            return set()
        box = _latlon_box(latitude, longitude)
        if box is None and not np.isfinite(latitude + longitude).any():
            return set()
        boxed = self._box_tiles(*box) if box is not None else None
        if boxed is not None and boxed <= self._partial_tiles:
            return boxed
        if latitude.size > 2 * _SAMPLE_POINTS:
            every = latitude.size // _SAMPLE_POINTS
            if self._many(self.index_tiles_at(directions(latitude[::every], longitude[::every]))):
                return frozenset(self._entries)
        exact = set(self.index_tiles_at(directions(latitude, longitude)))
        if boxed is not None and len(boxed) <= _LATLON_BOX_SLACK * len(exact) and not self._many(boxed):
            return boxed
        return exact

    # -- the spline a batch is evaluated with --------------------------------------------

    def _covering(self, needed, index=False) -> AmbientSpline:
        """A spline holding every tile of ``needed`` (a set): the complete one, the partial
        one, or a new partial one; with its index built when ``index``."""
        with self._lock:
            if self._full is not None:
                spline = self._full
            elif needed <= self._partial_tiles:
                spline = self._partial
            elif self._many(needed):
                spline = self.full
            else:
                keep = needed | self._partial_tiles
                count = sum(self._entries[t]["coefficients"] for t in keep)
                if count * PARTIAL_BYTES_PER_COEFFICIENT > self.cache_bytes:
                    keep = needed
                parts = self._parts(sorted(keep))
                spline = self._build(keep, lambda slab: {t: parts[t] for t in slab})
                self._keep(parts)
                # a new snapshot: evaluations already running keep theirs
                self._partial, self._partial_tiles = spline, frozenset(keep)
            if index and spline._folded is None:
                from ..bspline.index import QUANTISE_FROM_COEFFICIENTS

                # the whole store's index would hold integers: so does a part of it
                spline.quantise = self.coefficient_count >= QUANTISE_FROM_COEFFICIENTS
                spline.index  # noqa: B018 (built once, here, not by each thread evaluating)
            return spline

    # -- the spline's interface ----------------------------------------------------

    @property
    def levels(self):
        return self.full.levels

    @property
    def index(self):
        self.full  # noqa: B018
        return self._covering(frozenset(), index=True).index

    @property
    def coefficient_count(self) -> int:
        return int(self.manifest["spline"]["coefficients"])

    def evaluate_points(self, points, nderiv=0):
        """Values (M,) or value+derivatives (M, 4|10) at ambient points (M, 3); see
        :meth:`geoidspline.hierarchy.ambient.AmbientSpline.evaluate_points`."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if points.shape[0] >= FOLDED_FROM_POINTS:
            needed = frozenset() if self._full is not None else self._index_needed(points)
            return self._covering(needed, index=True).evaluate_points(points, nderiv)
        if self._full is not None:
            return self._full.evaluate_points(points, nderiv)
        return self._covering(set(self.tiles_at(points))).evaluate_points(points, nderiv)

    def undulation(self, latitude, longitude):
        """N in metres at latitude/longitude in degrees, NaN outside the store's coverage
        (:attr:`coverage`); see
        :meth:`geoidspline.hierarchy.ambient.AmbientSpline.undulation`."""
        if self._full is not None and self.coverage.is_everywhere and np.size(latitude) >= FOLDED_FROM_POINTS:
            # every tile read and a sphere covered everywhere: the compiled batch checks the
            # coordinates in its own threaded pass (raising as check_coordinates does) and
            # gives NaN for NaN, so no serial reductions here (check_coordinates' four and
            # the two NaN tests: about 2 ms a 1,000,000-point batch)
            return self._covering(frozenset(), index=True).undulation(latitude, longitude)
        latitude, longitude = check_coordinates(latitude, longitude)
        shape = latitude.shape
        if latitude.size >= FOLDED_FROM_POINTS:
            # the index evaluates every point at once (cheaper than gathering); the tiles
            # are those of the covered points only
            if self.coverage.is_everywhere and not (np.isnan(latitude.min()) or np.isnan(longitude.min())):
                # no NaN (min propagates it) on a sphere covered everywhere: every point is
                # covered, known from two reductions instead of a mask built on one core
                covered, everywhere = True, True
            else:
                covered = np.asarray(self.coverage.covers(latitude, longitude))
                everywhere = bool(covered.all())
            needed = frozenset()
            if self._full is None:
                lat, lon = latitude.ravel(), longitude.ravel()
                if not everywhere:
                    lat, lon = lat[covered.ravel()], lon[covered.ravel()]
                needed = self._index_tiles_latlon(lat, lon)
            spline = self._covering(needed, index=True)
            values = np.asarray(spline.undulation(latitude, longitude), dtype=np.float64)
            if not everywhere:
                values = np.where(covered, values, np.nan)
            return values
        covered = np.asarray(self.coverage.covers(latitude, longitude))
        if covered.all():
            values = np.asarray(self._small_undulation(latitude, longitude), dtype=np.float64)
        else:
            # only the covered points: their tiles, none for the points outside
            values = np.full(shape, np.nan)
            if covered.any():
                values[covered] = self._small_undulation(latitude[covered], longitude[covered])
        return values[()] if shape == () else values

    def _small_undulation(self, latitude, longitude):
        """The spline's values (covered or not) at checked coordinates of a small batch."""
        shape = latitude.shape
        points = directions(latitude.ravel(), longitude.ravel())
        return self.evaluate_points(points).reshape(shape)


class TileStore:
    """A tile store opened read-only.

    Opening reads the manifest and checks that every tile file is there with its
    manifest size (a few ms for 219 tiles); tiles are read, sha256-checked and merged
    into the store's spline (:attr:`spline`, a :class:`StoreSpline`) as queries need
    them: a one-point query reads at most 8 tiles of a global store, a batch the tiles
    its points need (a regional batch a few % of a global store's), a batch needing half
    of them or more all of them. ``lazy=False`` reads and checks every tile at opening.
    Memory (bounded by ``cache_bytes`` between queries), caching and thread safety: see
    :class:`StoreSpline`; queries are thread-safe.
    """

    def __init__(self, root: Path, manifest: dict, spline: AmbientSpline | None = None, verify: bool = True,
                 cache_bytes: int = CACHE_BYTES):
        self.path = root
        self.manifest = manifest
        self.spline = StoreSpline(root, manifest, verify=verify, cache_bytes=cache_bytes)
        if spline is not None:
            self.spline._full = spline

    @classmethod
    def open(cls, path, verify=True, lazy=True, key=None, cache_bytes=CACHE_BYTES):
        """Open the store at ``path``: the manifest now, the tiles when needed (all now
        with ``lazy=False``). ``verify=False`` skips the sha256 checks (sizes, names and
        the tiles' own records are always checked). ``key``: an Ed25519 public key
        (object or PEM file) that must have signed the manifest
        (:mod:`geoidspline.store.signing`); the tiles' sha256 are then always checked,
        since the signature covers the tiles through them. ``cache_bytes``: the bound of
        what the store keeps between queries short of reading it whole
        (:class:`StoreSpline`)."""
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
        store = cls(root, manifest, verify=verify, cache_bytes=cache_bytes)
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
    decoded = {}
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
                        decoded[tile] = read_tile_levels(root / entry["file"], entry, data, manifest)
                except FileNotFoundError:
                    problem = f"{root / entry['file']}: tile {entry['tile']} is missing"
                except StoreError as exc:
                    problem = str(exc)
            if problem:
                problems.append(problem)
    if not problems:
        try:
            spline._build_complete(kept=decoded)
        except StoreError as exc:
            problems.append(str(exc))
    return problems
