"""Store format 2 (compact tiles) and format 1 stores still opening.

Format 2 keeps keys as runs and values quantised (geoidspline.store.codec); the
quantisation moves the spline's value by at most step/2 per level, because a level's
B-splines are non-negative and sum to at most 1. These tests quantise, evaluate and
compare, and check that a format-1 store (written by the kept format-1 writer) opens
and gives the fitted values bitwise.
"""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import netCDF4
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import geoidspline
from geoidspline.bspline.keys import pack_keys
from geoidspline.bspline.level import LevelSpline
from geoidspline.errors import StoreCorruptError
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.sphere.coordinates import directions
from geoidspline.store import codec
from geoidspline.store.format import FORMAT_VERSION
from geoidspline.store.reader import TileStore
from geoidspline.store.writer import tile_encoding, write_store


def _manifest(root: Path) -> dict:
    return json.loads((root / "manifest.json").read_text())


def _points(n, seed, radius=(1.0, 1.0)):
    """Directions of n random points in 0..40N 10..50E, scaled to radii in ``radius``."""
    rng = np.random.default_rng(seed)
    lat = rng.uniform(0.0, 40.0, n)
    lon = rng.uniform(10.0, 50.0, n)
    return directions(lat, lon) * rng.uniform(*radius, n)[:, None]


# -- the codec -----------------------------------------------------------------------


@st.composite
def _tiles(draw):
    """Coefficients of a tile: 1-3 levels, keys in runs along k, values of any sign."""
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    levels, indices = [], []
    for level in draw(st.lists(st.integers(0, 6), min_size=1, max_size=3, unique=True)):
        runs = draw(st.integers(1, 40))
        starts = rng.integers(-300, 300, size=(runs, 3))
        lengths = rng.integers(1, 25, size=runs)
        idx = np.concatenate([s + np.c_[np.zeros((n, 2), int), np.arange(n)] for s, n in zip(starts, lengths)])
        idx = np.unique(idx, axis=0)
        indices.append(idx)
        levels.append(np.full(len(idx), level))
    indices = np.concatenate(indices)
    levels = np.concatenate(levels)
    values = rng.normal(0.0, draw(st.sampled_from([1e-3, 1.0, 80.0])), len(levels))
    return levels, indices, values


@settings(max_examples=60, deadline=None)
@given(_tiles(), st.sampled_from([1e-4, 2.56e-4, 1e-3, 0.05]))
def test_codec_round_trip_keeps_keys_and_rounds_values(tile, step):
    levels, indices, values = tile
    shuffle = np.random.default_rng(0).permutation(len(values))  # any input order
    data = codec.encode_tile((1, -2, 3), levels[shuffle], indices[shuffle], values[shuffle], step)
    header, decoded = codec.decode_tile(data)
    assert header["tile"] == [1, -2, 3] and header["value_step_m"] == step
    assert sorted(decoded) == sorted(set(levels.tolist()))
    for level, (keys, got) in decoded.items():
        sel = levels == level
        want_keys = pack_keys(indices[sel])
        order = np.argsort(want_keys)
        assert np.array_equal(keys, want_keys[order])
        want = values[sel][order]
        assert np.all(np.abs(got - want) <= step / 2 * (1 + 1e-9))
        assert np.array_equal(got, np.rint(want / step) * step)


#: int32 [5, 7, -3, 2**31 - 1, -2**31, 0, 12345, 12346, 12350] as numcodecs 0.16.6 coded
#: it (Delta(int32), Shuffle(4), Zstd(level=19, checksum=True)): the layout the first
#: format-2 stores were written in, by numcodecs, before python-zstandard replaced it.
NUMCODECS_ARRAY = "KLUv/SQk9QAAQoIGD+BpDSoAABbwcVBmCaRMAa+1/334JhFlxoAAIVyG9A=="
NUMCODECS_VALUES = [5, 7, -3, 2**31 - 1, -2**31, 0, 12345, 12346, 12350]


def test_arrays_coded_by_numcodecs_decode_and_ours_round_trip():
    import base64

    blob = base64.b64decode(NUMCODECS_ARRAY)
    values = codec._delta_decode(blob, np.int32, len(NUMCODECS_VALUES))
    assert values.dtype == np.int32 and values.tolist() == NUMCODECS_VALUES
    ours = codec._delta_encode(np.array(NUMCODECS_VALUES, np.int32), np.int32)
    assert codec._delta_decode(ours, np.int32, len(NUMCODECS_VALUES)).tolist() == NUMCODECS_VALUES
    with pytest.raises(ValueError, match="header says 10 numbers"):
        codec._delta_decode(blob, np.int32, 10)
    damaged = bytearray(blob)
    damaged[len(damaged) // 2] ^= 0xFF
    with pytest.raises(ValueError, match="damaged array"):
        codec._delta_decode(bytes(damaged), np.int32, len(NUMCODECS_VALUES))


def test_keys_cost_little_as_runs():
    # one level of 20,000 coefficients in 400 runs of 50: the keys are nearly free
    starts = np.c_[np.repeat(np.arange(20), 20), np.tile(np.arange(20), 20), np.full(400, -25)]
    idx = np.concatenate([s + np.c_[np.zeros((50, 2), int), np.arange(50)] for s in starts])
    zero = codec.encode_tile((0, 0, 0), np.zeros(len(idx)), idx, np.zeros(len(idx)), 1e-3)
    assert len(zero) < 600  # header and three arrays, ~0.03 bytes a coefficient


def test_value_step_follows_the_tolerance_and_level_count():
    for tolerance, levels in [(0.0015, 2), (0.5, 6), (0.002, 3), (1e-4, 1)]:
        step = codec.value_step(tolerance, levels)
        bound = codec.value_error_bound(step, levels)
        share = codec.QUANTISATION_SHARE * tolerance
        # the largest whole number of micrometres within the share of the tolerance
        assert bound <= share * (1 + 1e-9) and codec.value_error_bound(step + 1e-6, levels) > share
        assert abs(step / 1e-6 - round(step / 1e-6)) < 1e-6
    assert codec.value_step(0.0015, 2) == pytest.approx(1e-3)  # bound 1 mm for two levels


@pytest.mark.parametrize("damage", ["header", "array", "truncated"])
def test_damaged_tile_bytes_are_refused(damage):
    idx = np.c_[np.zeros((30, 2), int), np.arange(30)]
    data = bytearray(codec.encode_tile((0, 0, 0), np.zeros(30), idx, np.linspace(-5, 5, 30), 1e-3))
    if damage == "header":
        data[len(codec.MAGIC) + 6] ^= 0xFF
    elif damage == "array":
        data[-3] ^= 0xFF
    else:
        data = data[:-7]
    with pytest.raises(ValueError):
        codec.decode_tile(bytes(data))


# -- the error bound: quantise, evaluate, compare --------------------------------------


def test_quantisation_moves_a_level_by_at_most_half_a_step(small_store):
    spline = small_store.result.spline
    step = 0.01  # coarse, so that rounding dominates float noise
    quantised = codec.quantised_spline(spline, step)
    points = _points(4000, seed=11, radius=(0.97, 1.03))  # on and off the sphere
    for exact, rounded in zip(spline.levels, quantised.levels):
        delta = AmbientSpline([rounded]).evaluate_points(points) - AmbientSpline([exact]).evaluate_points(points)
        assert np.abs(delta).max() <= step / 2 + 1e-12
    total = quantised.evaluate_points(points) - spline.evaluate_points(points)
    assert np.abs(total).max() <= codec.value_error_bound(step, len(spline.levels)) + 1e-12


def test_the_half_step_bound_is_reached_where_rounding_is_one_sided(small_store):
    # every coefficient 0.49 step below a multiple: each rounds up by 0.49 step, and
    # where the level's B-splines sum to 1 the value moves by exactly that
    level = small_store.result.spline.levels[0]
    step = 0.01
    coefficients = (np.round(level.coefficients / step) - 0.49) * step
    exact = LevelSpline(0, level.h, level.order, level.keys, coefficients)
    exact = AmbientSpline([exact])
    rounded = codec.quantised_spline(exact, step)
    points = _points(2000, seed=12)
    region = small_store.region
    lat = np.degrees(np.arcsin(points[:, 2]))
    lon = np.degrees(np.arctan2(points[:, 1], points[:, 0]))
    inside = region.contains(lat, lon)
    delta = rounded.evaluate_points(points[inside]) - exact.evaluate_points(points[inside])
    np.testing.assert_allclose(delta, 0.49 * step, rtol=1e-9)


def test_store_values_are_within_the_stated_bound(small_store):
    m = _manifest(small_store.path)
    spline = m["spline"]
    assert spline["value_step_m"] <= codec.value_step(small_store.params.tolerance_m, len(spline["levels"]))
    assert spline["value_error_bound_m"] == codec.value_error_bound(spline["value_step_m"], len(spline["levels"]))
    store = geoidspline.open_store(small_store.path)
    points = _points(3000, seed=13)
    got = store.spline.evaluate_points(points)
    fitted = small_store.result.spline.evaluate_points(points)
    assert np.abs(got - fitted).max() <= spline["value_error_bound_m"]
    assert np.abs(got - fitted).max() > 0  # the values are rounded: the test can fail


# -- the tolerance still holds at the nodes -------------------------------------------


def _grid_nodes_in(region, grid):
    nodes = grid.nodes(region)
    lat, lon = np.meshgrid(nodes.latitude, nodes.longitude, indexing="ij")
    has_data = np.isfinite(nodes.undulation)
    return lat[has_data], lon[has_data], nodes.undulation[has_data]


def test_the_stored_store_meets_its_tolerance_at_every_node(small_store):
    # what a user gets back from the files, at every node of the source in the region,
    # independently of the manifest's figures
    lat, lon, truth = _grid_nodes_in(small_store.region, small_store.grid)
    store = geoidspline.open_store(small_store.path)
    errors = np.abs(store.undulation(lat, lon) - truth)
    m = _manifest(small_store.path)
    assert m["fit"]["converged"]
    assert errors.max() <= small_store.params.tolerance_m
    assert m["accuracy"]["node_max_error_m"] == pytest.approx(errors.max(), rel=1e-6)
    assert m["accuracy"]["fit_node_max_error_m"] == pytest.approx(small_store.result.node_max_error_m)
    assert m["spline"]["value_error_bound_m"] == codec.value_error_bound(m["spline"]["value_step_m"],
                                                                         len(m["spline"]["levels"]))


def test_the_step_shrinks_until_the_nodes_meet_the_tolerance(small_store):
    # a fit with no room left at its nodes (its worst node at the tolerance itself): the
    # step of the level-count rule alone would push nodes over it, the chosen one does not
    result = small_store.result
    spline, dirs = result.spline, result.node_directions
    tolerance = float(np.abs(result.node_errors).max())
    first = codec.value_step(tolerance, len(spline.levels))
    moved = result.node_errors - codec.quantisation_change(spline, first, dirs)
    assert np.abs(moved).max() > tolerance  # the case the search is for
    step, stored = codec.node_safe_step(spline, dirs, result.node_errors, tolerance)
    assert step < first
    truth = result.node_errors + spline.evaluate_points(dirs)
    again = truth - codec.quantised_spline(spline, step).evaluate_points(dirs)
    np.testing.assert_allclose(stored, again, atol=1e-12)
    assert np.abs(again).max() <= tolerance


def test_a_model_store_promises_the_tolerance_asked_for():
    from geoidspline.fitting.parameters import FitParameters
    from geoidspline.store.writer import tolerance_asked

    fit = {"tolerance_m": 0.0016, "choices": {"tolerance_asked_m": 0.002}}
    assert tolerance_asked(fit) == 0.002
    assert tolerance_asked({"tolerance_m": FitParameters().tolerance_m}) == FitParameters().tolerance_m


# -- format 1 stores ------------------------------------------------------------------


@pytest.fixture(scope="module")
def v1_store(small_store, tmp_path_factory):
    """The session fit written by the kept format-1 writer (netCDF4 tiles, float64)."""
    path = tmp_path_factory.mktemp("v1") / "store"
    write_store(path, small_store.result, small_store.grid.provenance, format_version=1)
    return path


def test_format_1_store_is_written_as_before(v1_store):
    m = _manifest(v1_store)
    assert m["format_version"] == 1 and "value_step_m" not in m["spline"]
    entry = m["tiles"][0]
    assert entry["file"].endswith(".nc")
    with netCDF4.Dataset(v1_store / entry["file"]) as ds:
        assert ds.getncattr("format_version") == 1
        assert ds["value"].units == "m" and ds["value"].dtype == np.float64
        assert ds.dimensions["coefficient"].size == entry["coefficients"]
    assert tile_encoding(m) == (1, {})


@pytest.mark.parametrize("lazy", [True, False])
def test_format_1_store_opens_with_the_fitted_values(small_store, v1_store, lazy):
    store = TileStore.open(v1_store, lazy=lazy)
    assert store.info()["format_version"] == 1
    rng = np.random.default_rng(14)
    lat, lon = rng.uniform(10, 30, 5), rng.uniform(20, 40, 5)
    one = store.undulation(lat, lon)  # a small batch: the tiles around the points
    assert np.array_equal(one, small_store.result.spline.undulation(lat, lon))
    if lazy:
        assert 0 < store.spline.tiles_read < len(store.manifest["tiles"])
    lat, lon = rng.uniform(10, 30, 5000), rng.uniform(20, 40, 5000)
    assert np.array_equal(store.undulation(lat, lon), small_store.result.spline.undulation(lat, lon))
    for a, b in zip(store.spline.levels, small_store.result.spline.levels):
        assert np.array_equal(a.keys, b.keys) and np.array_equal(a.coefficients, b.coefficients)


def test_format_2_store_is_smaller_than_format_1(small_store, v1_store):
    size = lambda root: sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert size(small_store.path) < size(v1_store) / 5


def test_a_damaged_format_2_tile_is_refused_without_the_digest(store_copy):
    entry = max(_manifest(store_copy)["tiles"], key=lambda e: e["coefficients"])
    path = store_copy / entry["file"]
    data = bytearray(path.read_bytes())
    data[-5] ^= 0x55  # same size: only the digest (skipped here) or the decoder can tell
    path.write_bytes(bytes(data))
    store = TileStore.open(store_copy, verify=False, lazy=True)
    with pytest.raises(StoreCorruptError, match=re.escape(path.name)):
        _ = store.spline.full  # reads every tile


def test_upgrade_rewrites_a_format_1_store_atomically(small_store, v1_store, tmp_path):
    from geoidspline.errors import StoreError
    from geoidspline.store.upgrade import upgrade_store

    root = Path(shutil.copytree(v1_store, tmp_path / "v1"))
    old = _manifest(root)
    record = upgrade_store(root)
    new = _manifest(root)
    assert (new["format_version"], new["store_version"]) == (FORMAT_VERSION, old["store_version"] + 1)
    assert record["tile_bytes_after"] < record["tile_bytes_before"] / 5
    assert all(e["file"].endswith(".gst") for e in new["tiles"])
    assert all((root / e["file"]).exists() for e in old["tiles"])  # kept for readers of version 1
    assert [e["tile"] for e in new["tiles"]] == [e["tile"] for e in old["tiles"]]
    assert new["history"][-1]["action"] == "upgrade"
    # the nodes are not in the store: the proven bound fits in the room the fit left
    room = old["fit"]["tolerance_m"] - old["accuracy"]["node_max_error_m"]
    assert 0 < new["spline"]["value_error_bound_m"] <= room
    store = TileStore.open(root)
    rng = np.random.default_rng(15)
    lat, lon = rng.uniform(10, 30, 3000), rng.uniform(20, 40, 3000)
    step = new["spline"]["value_step_m"]
    assert np.array_equal(store.undulation(lat, lon),
                          codec.quantised_spline(small_store.result.spline, step).undulation(lat, lon))
    with pytest.raises(StoreError, match="already in store format 4"):
        upgrade_store(root)


UPGRADE_POINTS = ["after-lock", "before-tiles", "during-tiles", "after-tiles", "before-manifest", "manifest-written"]


@pytest.mark.parametrize("point", UPGRADE_POINTS)
def test_an_upgrade_killed_halfway_leaves_the_format_1_store(small_store, v1_store, tmp_path, point):
    # `geoid-info --upgrade` killed (no clean-up, like SIGKILL) at each commit point
    # before the manifest is replaced: the format-1 store is as it was, byte for byte
    # in its manifest and tiles, opens, verifies and gives the fitted values; the next
    # upgrade succeeds
    import os
    import subprocess
    import sys

    from geoidspline.store.reader import verify_store
    from geoidspline.store.upgrade import upgrade_store

    root = Path(shutil.copytree(v1_store, tmp_path / "v1"))
    before = {p.relative_to(root): p.read_bytes() for p in root.rglob("*") if p.is_file() and p.name != ".lock"}
    env = dict(os.environ, GEOIDSPLINE_CRASH_AT=point)
    run = subprocess.run([sys.executable, "-m", "geoidspline", "info", "--store", str(root), "--upgrade"],
                         env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 77, run.stderr
    for rel, data in before.items():
        assert (root / rel).read_bytes() == data, rel
    assert _manifest(root)["format_version"] == 1
    assert verify_store(root) == []
    rng = np.random.default_rng(16)
    lat, lon = rng.uniform(10, 30, 500), rng.uniform(20, 40, 500)
    assert np.array_equal(TileStore.open(root).undulation(lat, lon), small_store.result.spline.undulation(lat, lon))
    assert upgrade_store(root)["to_format"] == FORMAT_VERSION
    assert verify_store(root) == []
