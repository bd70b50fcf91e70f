"""Lazy tile reading: which tiles a query reads, and that it changes no value.

A store opened with :func:`geoidspline.open_store` reads the manifest only; a batch of
fewer than FOLDED_FROM_POINTS points reads the tiles that can hold B-splines non-zero at
its points, evaluated with numpy. The values must be bitwise those of the store read
whole, for values and derivatives.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading

import numpy as np
import pytest

import geoidspline
from geoidspline.api import build_store
from geoidspline.bspline import keys as _keys
from geoidspline.bspline.level import cube_of_support_centres
from geoidspline.errors import CoordinateError, StoreError
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import FOLDED_FROM_POINTS
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region
from geoidspline.store.reader import TileStore


def _points(rng, n, region=None):
    if region is None:
        lat = np.degrees(np.arcsin(rng.uniform(-1, 1, n)))
        lon = rng.uniform(-180, 180, n)
    else:
        lat = rng.uniform(region.south, region.north, n)
        lon = rng.uniform(region.west, region.east, n)
    return lat, lon


def test_tiles_at_holds_every_bspline_non_zero_at_the_point(small_store):
    """For points on, near and off the sphere, every stored B-spline whose support
    holds the point lives in one of the tiles tiles_at names (exact and conservative)."""
    store = geoidspline.open_store(small_store.path)
    levels = store.spline.full.levels
    size = store.spline.tile_size
    rng = np.random.default_rng(1)
    u = directions(*_points(rng, 400))
    u = np.vstack([u, u * rng.uniform(0.8, 1.2, (400, 1)), directions(*_points(rng, 400, small_store.region))])
    checked = 0
    for x in u:
        tiles = set(store.spline.tiles_at(x))
        for lv in levels:
            n = lv.order
            cell = np.floor(x / lv.h).astype(np.int64)
            r = np.arange(n)
            k = np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T + cell - n + 1
            present = np.isin(_keys.pack_keys(k), lv.keys)
            for t in cube_of_support_centres(k[present], lv.h, n, size):
                assert tuple(int(v) for v in t) in tiles
                checked += 1
        # and no tile beyond the reach of the coarsest level
        reach = store.spline.reach
        for t in tiles:
            lo = np.array(t) * size
            assert np.all(lo - reach - 1e-9 <= x) and np.all(x <= lo + size + reach + 1e-9)
    assert checked > 10_000


def test_one_point_reads_few_tiles_and_gives_the_same_bits(small_store):
    eager = TileStore.open(small_store.path, lazy=False)
    total = len(eager.manifest["tiles"])
    assert eager.spline.tiles_read == total
    rng = np.random.default_rng(2)
    lat, lon = 20.0 + rng.uniform(-1, 1, 30), 30.0 + rng.uniform(-1, 1, 30)  # around one spot
    lazy = geoidspline.open_store(small_store.path)
    assert lazy.spline.tiles_read == 0
    value = lazy.undulation(lat[0], lon[0])
    assert isinstance(value, float) and value == eager.undulation(lat[0], lon[0])
    assert 0 < lazy.spline.tiles_read <= 27  # 3 tiles an axis: reach 0.4 = tile size here
    for la, lo in zip(lat, lon):
        assert lazy.undulation(la, lo) == eager.undulation(la, lo)
        u = directions(la, lo)[None]
        for nderiv in (1, 2):
            np.testing.assert_array_equal(lazy.spline.evaluate_points(u, nderiv), eager.spline.evaluate_points(u, nderiv))
    assert lazy.spline.tiles_read < total
    # the derived quantities go through the same lazy spline
    from geoidspline.query.derived import deflection

    for got, want in zip(deflection(lazy, lat[:5], lon[:5]), deflection(eager, lat[:5], lon[:5])):
        np.testing.assert_array_equal(got, want)
    assert lazy.spline.tiles_read < total
    # and small batches equal the fitted spline itself, bit for bit
    la, lo = _points(rng, FOLDED_FROM_POINTS - 1, small_store.region)
    np.testing.assert_array_equal(lazy.undulation(la, lo), small_store.stored.undulation(la, lo))


def test_large_batches_and_the_levels_read_every_tile(small_store):
    store = geoidspline.open_store(small_store.path)
    total = len(store.manifest["tiles"])
    lat, lon = _points(np.random.default_rng(3), FOLDED_FROM_POINTS, small_store.region)
    values = store.undulation(lat, lon)
    assert store.spline.tiles_read == total
    np.testing.assert_array_equal(values, small_store.stored.undulation(lat, lon))
    other = geoidspline.open_store(small_store.path)
    assert sum(len(lv) for lv in other.spline.levels) == other.spline.coefficient_count
    assert other.spline.tiles_read == total
    lat[-1] = 90.5  # checked inside the compiled call for a large batch
    with pytest.raises(CoordinateError, match="latitude"):
        store.undulation(lat, lon)
    with pytest.raises(CoordinateError, match="latitude"):
        store.undulation(lat[-5:], lon[-5:])


def test_scattered_small_batch_reads_the_whole_store_at_once(small_store):
    store = geoidspline.open_store(small_store.path)
    lat, lon = _points(np.random.default_rng(4), 200, small_store.region)  # all over the store
    values = store.undulation(lat, lon)
    assert store.spline.tiles_read == len(store.manifest["tiles"])
    assert store.spline._full is not None
    np.testing.assert_array_equal(values, small_store.stored.undulation(lat, lon))


def _assert_threads_see_the_eager_values(lazy, eager, batches, nthreads):
    """``nthreads`` threads query the lazy store with ``batches`` (thread k takes every
    nthreads-th from k); each answer must be bitwise the eagerly read store's."""
    results = [None] * len(batches)
    errors = []

    def work(k):
        try:
            for i in range(k, len(batches), nthreads):
                results[i] = lazy.undulation(*batches[i])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(nthreads)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for (lat, lon), got in zip(batches, results):
        np.testing.assert_array_equal(got, eager.undulation(lat, lon))


def test_concurrent_queries_see_the_same_values(small_store):
    eager = TileStore.open(small_store.path, lazy=False)
    lazy = geoidspline.open_store(small_store.path)
    rng = np.random.default_rng(5)
    batches = [_points(rng, int(rng.integers(1, 40)), small_store.region) for _ in range(64)]
    _assert_threads_see_the_eager_values(lazy, eager, batches, 4)


def test_a_reader_after_two_rewrites_is_told_to_reopen(small_store, store_copy):
    reader = geoidspline.open_store(store_copy)
    params = FitParameters(h0=0.2, max_level=0, tolerance_m=1.0)
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    lat, lon = 20.0, 30.0
    assert reader.undulation(lat, lon) == TileStore.open(small_store.path, lazy=False).undulation(lat, lon)
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    read = reader.spline.tiles_held
    lat, lon = _points(np.random.default_rng(6), 500, small_store.region)
    unread = [(a, b) for a, b in zip(lat, lon) if set(reader.spline.tiles_at(directions(a, b))) - read]
    with pytest.raises(StoreError, match="open it again"):
        reader.undulation(*unread[0])  # needs tiles not read yet, and now gone


def test_one_point_query_imports_no_heavy_library(small_store):
    """geoid-query on one point (and the API) never import scipy, pyproj, xarray or dask
    (the cold-start budget); of the compiled kernels it loads only the store codec's,
    which decodes format-3 tiles (loading the library: ~1 ms, benchmarks/README.md,
    "Store codec"), and not the query kernels."""
    code = f"""
import sys
from geoidspline.cli.query import main
try:
    main(["--store", {str(small_store.path)!r}, "20.5", "30.5"], standalone_mode=False)
finally:
    heavy = sorted(m for m in ("geoidspline._kernels.query", "geoidspline._kernels.interpolation", "scipy",
                               "pyproj", "xarray", "dask", "pandas")
                   if m in sys.modules)
    print("HEAVY:" + ",".join(heavy))
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    value, heavy = run.stdout.strip().splitlines()
    assert heavy == "HEAVY:"
    want = TileStore.open(small_store.path, lazy=False).undulation(20.5, 30.5)
    assert float(value) == pytest.approx(want, abs=5e-5)
    manifest = json.loads((small_store.path / "manifest.json").read_text())
    assert abs(want) > 1.0 and manifest["spline"]["coefficients"] > 0


def test_only_the_command_line_pins_the_allocator(small_store):
    """glibc's mmap threshold is the whole process's: a program reading a store and
    building its index through the library keeps its own, a geoid-* command (which owns
    its process) pins it so that the index build's temporaries go back to the system."""
    code = f"""
import numpy as np
import geoidspline
from geoidspline import _memory
store = geoidspline.open_store({str(small_store.path)!r})
store.undulation(np.linspace(20, 21, 5000), np.linspace(30, 31, 5000))  # a large batch: tiles, an index
library = _memory._pinned
from geoidspline.cli.info import main
main([{str(small_store.path)!r}], standalone_mode=False)
print(library, _memory._pinned)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip().splitlines()[-1] == "False True"


# -- large batches from the tiles they need: the index of a part of the store ------------


def _patch_store(path, order, h0, patches, tile_size, seed):
    """A store (written as a fit's would be) whose level i (h0 / 2**i) holds random
    coefficients on every B-spline whose support meets the sphere inside the rectangles
    patches[i] (S W N E degrees): small, many tiles, levels of different extents."""
    from geoidspline.bspline.level import LevelSpline
    from geoidspline.fitting.result import FitResult
    from geoidspline.hierarchy.ambient import AmbientSpline
    from geoidspline.sources.base import Provenance
    from geoidspline.sphere.region import GLOBAL
    from geoidspline.store.writer import write_store

    rng = np.random.default_rng(seed)
    r = np.arange(order)
    offsets = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3) - order + 1
    levels = []
    for level, boxes in enumerate(patches):
        h = h0 / 2.0**level
        keys = []
        for s, w, n, e in boxes:
            # random points uniform in area, four a cell: (nearly) every cell of the patch
            area = (np.sin(np.radians(n)) - np.sin(np.radians(s))) * np.radians(e - w)
            lat, lon = _points(rng, int(4 * area / h**2), Region(s, w, n, e))
            cells = np.floor(directions(lat, lon) / h).astype(np.int64)
            keys.append(_keys.pack_keys((cells[:, None, :] + offsets[None]).reshape(-1, 3)))
        keys = np.unique(np.concatenate(keys))
        levels.append(LevelSpline(level, h, order, keys, rng.normal(0.0, 10.0, keys.size)))
    params = FitParameters(order=order, h0=h0, max_level=len(patches) - 1, tile_size=tile_size,
                           margin_cells=order, tolerance_m=0.01)
    result = FitResult(spline=AmbientSpline(levels), parameters=params, region=GLOBAL,
                       node_directions=np.zeros((0, 3)), node_errors=np.zeros(0))
    write_store(path, result, Provenance(source="synthetic", model="synthetic", kind="model"), value_step_m=1e-3)
    return path


#: seams: the antimeridian (one patch across it), the poles, the equator; tiles of 0.05
#: on the unit sphere (about 2.9 degrees), level-0 bricks of 16 h0 = 0.16 and 0.08
PATCHES = [[(30.0, -20.0, 60.0, 40.0), (70.0, -180.0, 90.0, 180.0), (-15.0, 160.0, 15.0, 200.0)],
           [(38.0, -5.0, 52.0, 25.0), (80.0, -180.0, 90.0, 180.0), (-6.0, 170.0, 6.0, 190.0)],
           [(42.0, 2.0, 48.0, 14.0), (86.0, -180.0, 90.0, 180.0), (-2.0, 176.0, 2.0, 184.0)]]

#: batches inside the patches: (S W N E) of random points
BATCHES = [(44.0, 5.0, 46.0, 12.0), (87.0, -180.0, 90.0, 180.0), (-1.5, 177.0, 1.5, 183.0), (41.0, 2.0, 49.0, 20.0)]


@pytest.fixture(scope="module")
def patch_stores(tmp_path_factory):
    base = tmp_path_factory.mktemp("patch_stores")
    return {"three levels, order 4": _patch_store(base / "multi", 4, 0.01, PATCHES, 0.05, 7),
            "one level, order 6": _patch_store(base / "single", 6, 0.005, PATCHES[1:2], 0.05, 8)}


@pytest.mark.parametrize("name", ["three levels, order 4", "one level, order 6"])
def test_large_batches_read_only_their_tiles_and_give_the_whole_stores_bits(patch_stores, name):
    """A batch of FOLDED_FROM_POINTS points or more in a small area is evaluated by the
    index of the tiles it needs: every value, gradient and Hessian, on the sphere, off it
    (inside and outside the levels' folded bands) and at the poles and across the
    antimeridian, has the bits of the whole store's index."""
    path = patch_stores[name]
    eager = TileStore.open(path, lazy=False)
    total = len(eager.manifest["tiles"])
    assert total > 100 and len({lv.level for lv in eager.spline.full.levels}) == (3 if "three" in name else 1)
    rng = np.random.default_rng(9)
    for s, w, n, e in BATCHES:
        lazy = geoidspline.open_store(path)
        lat, lon = rng.uniform(s, n, 3 * FOLDED_FROM_POINTS), rng.uniform(w, e, 3 * FOLDED_FROM_POINTS)
        got = lazy.undulation(lat, lon)
        assert lazy.spline._full is None and 0 < len(lazy.spline.tiles_held) < total / 2
        np.testing.assert_array_equal(got, eager.undulation(lat, lon))
        assert np.abs(got).max() > 1.0  # the batch is where the coefficients are
        u = directions(lat, lon) * rng.choice([1.0, 1.0 - 1e-3, 1.0 + 1e-3, 0.97, 1.05], lat.size)[:, None]
        for nderiv in (0, 1, 2):
            np.testing.assert_array_equal(lazy.spline.evaluate_points(u, nderiv),
                                          eager.spline.evaluate_points(u, nderiv))
        assert lazy.spline._full is None and lazy.spline.tiles_read < total / 2


def test_quantised_indexes_of_a_part_give_the_whole_stores_bits(patch_stores, monkeypatch):
    """A store big enough for integer tables (the threshold lowered to 0 here): the index
    of the tiles a batch needs holds the point's bricks with the same integers and base as
    the whole store's, so the full-column sums (w q summed, the base added once) give the
    same bits, values and derivatives."""
    from geoidspline.bspline import index as index_module

    monkeypatch.setattr(index_module, "QUANTISE_FROM_COEFFICIENTS", 0)
    path = patch_stores["one level, order 6"]
    eager = TileStore.open(path, lazy=False)
    assert eager.spline.full.index.qvalues is not None
    rng = np.random.default_rng(12)
    for s, w, n, e in BATCHES:
        lazy = geoidspline.open_store(path)
        lat, lon = rng.uniform(s, n, 3 * FOLDED_FROM_POINTS), rng.uniform(w, e, 3 * FOLDED_FROM_POINTS)
        got = lazy.undulation(lat, lon)
        assert lazy.spline._full is None and lazy.spline._partial.index.qvalues is not None
        np.testing.assert_array_equal(got, eager.undulation(lat, lon))
        assert np.abs(got).max() > 1.0
        u = directions(lat, lon) * rng.choice([1.0, 1.0 - 1e-4, 1.0 + 1e-4], lat.size)[:, None]
        for nderiv in (0, 1, 2):
            np.testing.assert_array_equal(lazy.spline.evaluate_points(u, nderiv),
                                          eager.spline.evaluate_points(u, nderiv))


def test_index_tiles_hold_every_bspline_touching_the_points_bricks(patch_stores):
    """index_tiles_at names every tile holding a coefficient whose B-spline touches a
    brick (of its level) that holds a point: what the index of those tiles needs to have
    the point's bricks as the whole store's index has them."""
    from geoidspline._kernels.query import BRICK_BITS

    store = TileStore.open(patch_stores["three levels, order 4"], lazy=False)
    spline = store.spline
    rng = np.random.default_rng(10)
    u = np.vstack([directions(rng.uniform(s, n, 20), rng.uniform(w, e, 20)) for s, w, n, e in BATCHES])
    checked = 0
    for x in u:
        tiles = set(spline.index_tiles_at(x))
        for lv in spline.full.levels:
            side = (1 << BRICK_BITS) * lv.h
            brick = np.floor(x / side)
            k = _keys.unpack_keys(lv.keys)
            # support [k h, (k + order) h) meets the brick [b side, (b + 1) side)
            touching = np.all((k * lv.h < (brick + 1) * side) & ((k + lv.order) * lv.h > brick * side), axis=1)
            for t in cube_of_support_centres(k[touching], lv.h, lv.order, spline.tile_size):
                assert tuple(int(v) for v in t) in tiles
                checked += 1
    assert checked > 10_000


def test_tiles_are_cached_within_the_bound_and_the_partial_spline_reused(patch_stores):
    path = patch_stores["one level, order 6"]
    eager = TileStore.open(path, lazy=False)
    rng = np.random.default_rng(11)
    batches = [(rng.uniform(s, n, FOLDED_FROM_POINTS), rng.uniform(w, e, FOLDED_FROM_POINTS))
               for s, w, n, e in BATCHES[:3]]
    store = geoidspline.open_store(path)
    first = store.undulation(*batches[0])
    held = store.spline.tiles_held
    partial = store.spline._partial
    np.testing.assert_array_equal(store.undulation(*batches[0]), first)
    assert store.spline._partial is partial  # held: nothing read, nothing built
    store.undulation(*batches[1])  # grown: both batches' tiles
    assert held < store.spline.tiles_held
    for lat, lon in batches:
        np.testing.assert_array_equal(store.undulation(lat, lon), eager.undulation(lat, lon))

    # no room to grow or keep: each batch its own tiles, nothing kept between batches
    from geoidspline.store.reader import StoreSpline

    tight = StoreSpline(path, store.manifest, cache_bytes=0)
    for lat, lon in batches + batches[:1]:
        np.testing.assert_array_equal(tight.undulation(lat, lon), eager.undulation(lat, lon))
        assert tight.tiles_held == frozenset(tight._index_tiles_latlon(lat, lon)) and not tight._tiles
    some = StoreSpline(path, store.manifest, cache_bytes=200_000)
    for lat, lon in batches:
        some.undulation(lat, lon)
        assert 0 < some._tile_bytes <= 200_000
    with pytest.raises(ValueError, match="cache_bytes"):
        StoreSpline(path, store.manifest, cache_bytes=-1)


def test_large_batches_outside_the_coverage_read_no_tile_there(small_store):
    """The coverage contract holds for large batches: NaN outside (never a number), the
    same bits inside; the tiles read are those the covered points need."""
    eager = TileStore.open(small_store.path, lazy=False)
    rng = np.random.default_rng(12)
    lat, lon = rng.uniform(-60, 60, 4 * FOLDED_FROM_POINTS), rng.uniform(-60, 100, 4 * FOLDED_FROM_POINTS)
    store = geoidspline.open_store(small_store.path)
    got = store.undulation(lat, lon)
    covered = store.covers(lat, lon)
    assert 0 < covered.sum() < lat.size
    assert np.isnan(got[~covered]).all() and np.isfinite(got[covered]).all()
    np.testing.assert_array_equal(got, eager.undulation(lat, lon))
    outside = geoidspline.open_store(small_store.path)
    assert (~covered).sum() >= FOLDED_FROM_POINTS
    assert np.isnan(outside.undulation(lat[~covered], lon[~covered])).all()
    assert outside.spline.tiles_read == 0


def test_concurrent_large_batches_see_the_whole_stores_values(patch_stores):
    path = patch_stores["three levels, order 4"]
    eager = TileStore.open(path, lazy=False)
    lazy = geoidspline.open_store(path)
    rng = np.random.default_rng(13)
    batches = [(rng.uniform(s, n, FOLDED_FROM_POINTS), rng.uniform(w, e, FOLDED_FROM_POINTS))
               for s, w, n, e in BATCHES * 3]
    _assert_threads_see_the_eager_values(lazy, eager, batches, 3)


def test_the_bricks_not_the_reach_decide_the_bits_of_a_folded_index():
    """Why a large batch reads the tiles of its points' coarsest bricks, not only of
    their reach: at a point whose level-1 brick holds level-1 B-splines, none of them
    non-zero at the point, the whole store's index evaluates the level's folded table
    there (the coarser levels subdivided), an index of the coefficients within reach
    has no such brick and evaluates level 0's: the same number but not the same bits.
    The coefficients whose support centres lie in the point's level-0 brick widened by
    the reach (the finest grain a set of tiles can have) give the whole index's bits."""
    from geoidspline._kernels.query import BRICK_BITS
    from geoidspline.bspline.index import BrickIndex
    from geoidspline.bspline.level import LevelSpline

    rng = np.random.default_rng(14)
    order, h0 = 4, 0.01
    r = np.arange(order)
    offsets = np.stack(np.meshgrid(r, r, r, indexing="ij"), axis=-1).reshape(-1, 3) - order + 1
    levels = []
    for level, region in enumerate([Region(30.0, -20.0, 60.0, 40.0), Region(44.0, 5.0, 46.0, 7.0)]):
        h = h0 / 2.0**level
        cells = np.floor(directions(*_points(rng, 40_000, region)) / h).astype(np.int64)
        keys = np.unique(_keys.pack_keys((cells[:, None, :] + offsets[None]).reshape(-1, 3)))
        levels.append(LevelSpline(level, h, order, keys, rng.normal(0.0, 10.0, keys.size)))
    whole = BrickIndex(levels, order)
    reach = order * h0 / 2.0 + 1e-9
    side = (1 << BRICK_BITS) * h0

    def within(lo, hi):  # the coefficients whose support centre lies in lo..hi
        parts = []
        for lv in levels:
            centre = (_keys.unpack_keys(lv.keys) + order / 2.0) * lv.h
            keep = np.all((centre >= lo) & (centre <= hi), axis=1)
            parts.append(LevelSpline(lv.level, lv.h, order, lv.keys[keep], lv.coefficients[keep]))
        return parts

    # points 1.3-3.5 degrees east of level 1's patch: in its bricks (4.6 degrees), beyond its reach
    u = directions(*_points(rng, 40, Region(44.0, 8.3, 46.0, 10.5)))
    differ = 0
    for x in u[:, None, :]:
        want = np.zeros((1, 1))
        whole.add_to(x, want)
        brick = np.floor(x / side)
        got = np.zeros((1, 1))
        BrickIndex(within(brick * side - reach, (brick + 1) * side + reach), order).add_to(x, got)
        assert got[0, 0] == want[0, 0]
        near = np.zeros((1, 1))
        BrickIndex(within(x - reach, x + reach), order).add_to(x, near)
        assert near[0, 0] == pytest.approx(want[0, 0], abs=1e-9)
        differ += near[0, 0] != want[0, 0]
    assert differ > 0


def test_a_sphere_covered_everywhere_answers_every_point_but_the_nan_ones(small_store):
    """A store covering the whole sphere without holes skips the coverage mask of a large
    batch (two NaN reductions instead): the same bits at every real coordinate as the
    mask path, NaN where a latitude or a longitude is NaN."""
    from geoidspline.sphere.coverage import Coverage
    from geoidspline.sphere.region import GLOBAL

    masked = TileStore.open(small_store.path)
    everywhere = TileStore.open(small_store.path)
    everywhere.spline.coverage = Coverage.of_region(GLOBAL)
    assert everywhere.spline.coverage.is_everywhere and not masked.spline.coverage.is_everywhere
    lat, lon = _points(np.random.default_rng(21), 3 * FOLDED_FROM_POINTS, small_store.region)
    want = masked.undulation(lat, lon)
    assert np.isfinite(want).all()  # inside the store's region: covered on both paths
    np.testing.assert_array_equal(everywhere.undulation(lat, lon), want)
    lat[5], lon[7] = np.nan, np.nan
    got = everywhere.undulation(lat, lon)
    real = np.isfinite(lat) & np.isfinite(lon)
    assert np.isnan(got[~real]).all() and (~real).sum() == 2
    np.testing.assert_array_equal(got[real], want[real])
    np.testing.assert_array_equal(got, masked.undulation(lat, lon))
