"""The query API: ``geoidspline.open_store(path).undulation(lat, lon)``."""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest

import geoidspline
from geoidspline.errors import CoordinateError, GeoidSplineError


@pytest.fixture(scope="module")
def store(small_store):
    return geoidspline.open_store(small_store.path)


def test_scalars_stay_scalars(store, analytic):
    for lat, lon in [(20.0, 30.0), (20, 30), (np.float32(20.5), np.int64(31)), (np.array(20.0), 30.0)]:
        v = store.undulation(lat, lon)
        assert np.ndim(v) == 0
        assert isinstance(v, (float, np.floating))
        assert abs(float(v) - analytic(float(lat), float(lon))) < 0.01


def test_arrays_keep_their_shape(store):
    rng = np.random.default_rng(5)
    lat = rng.uniform(10, 30, (3, 4))
    lon = rng.uniform(20, 40, (3, 4))
    v = store.undulation(lat, lon)
    assert v.shape == (3, 4)
    flat = store.undulation(lat.ravel(), lon.ravel())
    assert flat.shape == (12,)
    assert np.array_equal(v.ravel(), flat)
    # element by element, as scalars
    assert np.array_equal(v, np.array([[store.undulation(a, b) for a, b in zip(r1, r2)] for r1, r2 in zip(lat, lon)]))
    assert store.undulation([20.0, 21.0], [30.0, 31.0]).shape == (2,)
    assert store.undulation(np.empty((0,)), np.empty((0,))).shape == (0,)


def test_broadcasting(store):
    lat = np.array([12.0, 18.5, 25.0, 29.0])
    v = store.undulation(lat, 33.0)
    assert v.shape == (4,)
    assert np.array_equal(v, [store.undulation(a, 33.0) for a in lat])
    lon = np.array([21.0, 30.0, 39.0])
    grid = store.undulation(lat[:, None], lon[None, :])
    assert grid.shape == (4, 3)
    assert np.array_equal(grid[:, 1], store.undulation(lat, 30.0))
    assert np.array_equal(grid[2], store.undulation(25.0, lon))
    with pytest.raises(ValueError):
        store.undulation(np.zeros(3), np.zeros(4))


def test_nan_in_nan_out(store):
    lat = np.array([20.0, np.nan, 22.0, 24.0])
    lon = np.array([30.0, 31.0, np.nan, 35.0])
    v = store.undulation(lat, lon)
    assert np.isnan(v[1]) and np.isnan(v[2])
    assert v[0] == store.undulation(20.0, 30.0)
    assert v[3] == store.undulation(24.0, 35.0)
    assert np.isnan(store.undulation(np.nan, 30.0))
    assert np.ndim(store.undulation(np.nan, 30.0)) == 0


@pytest.mark.parametrize("lat", [90.0001, -91.0, 180.0, np.inf, -np.inf])
def test_latitude_out_of_range_raises(store, lat):
    with pytest.raises(CoordinateError) as err:
        store.undulation(lat, 30.0)
    assert isinstance(err.value, GeoidSplineError)
    assert "latitude" in str(err.value)
    # one bad value in an array is enough
    with pytest.raises(CoordinateError):
        store.undulation(np.array([20.0, lat]), np.array([30.0, 30.0]))


def test_poles_are_valid_where_a_store_covers_them(store, synthetic_grid, tmp_path):
    for lat in (90.0, -90.0):  # the session store is regional: the poles are outside its coverage
        assert np.isnan(store.undulation(lat, 0.0))
    from geoidspline.api import build_store
    from geoidspline.fitting.parameters import FitParameters

    build_store(synthetic_grid, tmp_path / "global", None, FitParameters(h0=0.25, max_level=0, tolerance_m=1.0))
    whole = geoidspline.open_store(tmp_path / "global")
    for lat in (90.0, -90.0):
        v = whole.undulation(lat, 0.0)
        assert np.isfinite(v)
        # every longitude is the same point at a pole
        assert whole.undulation(lat, 123.0) == pytest.approx(v, abs=1e-9)


@pytest.mark.parametrize("lon", [np.inf, -np.inf])
def test_infinite_longitude_raises(store, lon):
    with pytest.raises(CoordinateError, match="longitude"):
        store.undulation(20.0, lon)
    with pytest.raises(GeoidSplineError):
        store.undulation(np.array([20.0, 21.0]), np.array([30.0, lon]))


def test_longitude_wraps(store):
    rng = np.random.default_rng(6)
    lat = rng.uniform(10, 30, 200)
    lon = rng.uniform(20, 40, 200)
    base = store.undulation(lat, lon)
    for turns in (1, -1, 2, -3):
        shifted = store.undulation(lat, lon + 360.0 * turns)
        assert np.max(np.abs(shifted - base)) < 1e-9
    # the same meridian written as negative / positive
    assert abs(store.undulation(20.0, -330.0) - store.undulation(20.0, 30.0)) < 1e-9


def test_values_agree_with_the_analytic_field(small_store, store, analytic):
    """Inside the region (2° away from its edges) the fit is within its tolerance."""
    tolerance = store.info()["tolerance_m"]
    assert tolerance == small_store.params.tolerance_m
    s, w, n, e = store.manifest["region"]
    rng = np.random.default_rng(7)
    lat = rng.uniform(s + 2, n - 2, 5000)
    lon = rng.uniform(w + 2, e - 2, 5000)
    error = store.undulation(lat, lon) - analytic(lat, lon)
    assert np.max(np.abs(error)) < tolerance
    assert np.sqrt(np.mean(error**2)) < tolerance / 2
    # at the data nodes inside the region, too (node values are float32-rounded: 1e-6 m)
    nodes_lat, nodes_lon = np.meshgrid(np.arange(s, n + 1, 2.0), np.arange(w, e + 1, 2.0), indexing="ij")
    assert np.max(np.abs(store.undulation(nodes_lat, nodes_lon) - analytic(nodes_lat, nodes_lon))) < tolerance


def test_covers_the_fitted_region_only(store):
    assert store.covers(20.0, 30.0)
    assert store.covers(10.0, 20.0) and store.covers(30.0, 40.0)  # edges included
    assert not store.covers(5.0, 30.0)
    assert not store.covers(20.0, 45.0)
    assert store.covers(20.0, 390.0)  # wrapped longitude
    mask = store.covers(np.array([20.0, 50.0]), np.array([30.0, 30.0]))
    assert mask.tolist() == [True, False]


def test_concurrent_queries_agree(store):
    rng = np.random.default_rng(8)
    lat = rng.uniform(10, 30, 2000)
    lon = rng.uniform(20, 40, 2000)
    want = store.undulation(lat, lon)
    with ThreadPoolExecutor(max_workers=2) as pool:
        results = list(pool.map(lambda _: store.undulation(lat, lon), range(4)))
    for got in results:
        assert np.array_equal(got, want)
