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


def test_concurrent_queries_see_the_same_values(small_store):
    eager = TileStore.open(small_store.path, lazy=False)
    lazy = geoidspline.open_store(small_store.path)
    rng = np.random.default_rng(5)
    batches = [_points(rng, int(rng.integers(1, 40)), small_store.region) for _ in range(64)]
    results = [None] * len(batches)
    errors = []

    def work(k):
        try:
            for i in range(k, len(batches), 4):
                results[i] = lazy.undulation(*batches[i])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors
    for (lat, lon), got in zip(batches, results):
        np.testing.assert_array_equal(got, eager.undulation(lat, lon))


def test_a_reader_after_two_rewrites_is_told_to_reopen(small_store, store_copy):
    reader = geoidspline.open_store(store_copy)
    params = FitParameters(h0=0.2, max_level=0, tolerance_m=1.0)
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    lat, lon = 20.0, 30.0
    assert reader.undulation(lat, lon) == TileStore.open(small_store.path, lazy=False).undulation(lat, lon)
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    read = set(reader.spline._tiles)
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
store.undulation(np.linspace(20, 21, 5000), np.linspace(30, 31, 5000))  # every tile, the index
library = _memory._pinned
from geoidspline.cli.info import main
main([{str(small_store.path)!r}], standalone_mode=False)
print(library, _memory._pinned)
"""
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert run.stdout.strip().splitlines()[-1] == "False True"
