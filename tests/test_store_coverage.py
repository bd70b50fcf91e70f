"""Coverage is part of the store (issue 10 items 1 and 2, store side): a store answers
where its source had data and NaN elsewhere, says why, and keeps its coverage through
regional updates."""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest
from conftest import stored_spline
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

import geoidspline
from geoidspline.api import build_store
from geoidspline.fitting.driver import fit_source
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.base import NodeSample, Provenance
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.coverage import INSIDE, NO_DATA, OUTSIDE, Coverage, CoveragePart
from geoidspline.sphere.region import Region
from geoidspline.api.regional import update_store
from geoidspline.store.writer import write_store

#: An "Andes" store (S W N E), as in the issue's first report.
ANDES = Region(-36.0, -76.0, -16.0, -64.0)
PARAMS = FitParameters(h0=0.2, max_level=2, tolerance_m=0.02, tile_size=1.0)
#: The hole of the holed store: nodes (2° grid) with 18 <= lat <= 22 and 28 <= lon <= 32.
HOLE_LAT, HOLE_LON = (18.0, 22.0), (28.0, 32.0)
HOLED_REGION = Region(10.0, 20.0, 30.0, 40.0)


def _grid(values, name, latitude, longitude):
    return GeoidGrid(latitude, longitude, values, Provenance(source=name, model=name, kind="grid"))


def _national(field, name, bounds, step=0.25):
    """A national grid: ``field(lat, lon)`` on a ``step``° lattice over ``bounds`` (S W N E)
    only, fine enough for a 100 km blend (a 2° grid cannot fall to the store's values
    within 100 km)."""
    s, w, n, e = bounds
    lat, lon = np.arange(s, n + 1e-9, step), np.arange(w, e + 1e-9, step)
    return _grid(field(*np.meshgrid(lat, lon, indexing="ij")), name, lat, lon)


@pytest.fixture(scope="module")
def andes(tmp_path_factory, synthetic_grid):
    path = tmp_path_factory.mktemp("andes") / "store"
    result, _ = build_store(synthetic_grid, path, ANDES, PARAMS)
    return path, result


@pytest.fixture(scope="module")
def holed(tmp_path_factory, synthetic_grid):
    g = synthetic_grid
    values = g.values.copy()
    lat2, lon2 = np.meshgrid(g.latitude, g.longitude, indexing="ij")
    hole = (lat2 >= HOLE_LAT[0]) & (lat2 <= HOLE_LAT[1]) & (lon2 >= HOLE_LON[0]) & (lon2 <= HOLE_LON[1])
    values[hole] = np.nan
    grid = _grid(values, "holed.gtx", g.latitude, g.longitude)
    path = tmp_path_factory.mktemp("holed") / "store"
    result, _ = build_store(grid, path, HOLED_REGION, PARAMS)
    return path, result, grid


# -- outside the region -----------------------------------------------------------------


def test_outside_the_region_is_nan_never_a_number(andes):
    """Seen: Paris from an Andes store answered 0.0; two degrees outside, 31.05 m."""
    path, result = andes
    store = geoidspline.open_store(path)
    paris = store.undulation(48.85, 2.35)
    assert math.isnan(paris) and isinstance(paris, float)
    assert store.covers(48.85, 2.35) is False
    assert store.covers(48.85, 2.35, reason=True) == store.coverage_reason(48.85, 2.35) == OUTSIDE
    near = store.undulation(-38.0, -70.0)  # two degrees south of the region
    assert math.isnan(near)
    assert np.isfinite(result.spline.undulation(-38.0, -70.0))  # the spline has a number there
    inside = store.undulation(-26.0, -70.0)
    assert inside == stored_spline(result.spline, path).undulation(-26.0, -70.0) and store.covers(-26.0, -70.0) is True
    assert store.coverage_reason(-26.0, -70.0) == INSIDE
    # every derived quantity follows
    for value in (store.error_bound(48.85, 2.35), store.orthometric_height(48.85, 2.35, 100.0),
                  store.ellipsoidal_height(48.85, 2.35, 100.0), *store.deflection(48.85, 2.35)):
        assert math.isnan(value)
    assert np.isfinite(store.deflection(-26.0, -70.0).xi_arcsec)


def test_batches_mix_answers_and_nan(andes):
    path, result = andes
    store = geoidspline.open_store(path)
    rng = np.random.default_rng(3)
    for n in (7, 5000):  # the numpy path and the compiled one
        lat = rng.uniform(-50, -2, n)
        lon = rng.uniform(-90, -50, n)
        lat[0], lon[0] = np.nan, -70.0
        inside = ANDES.contains(lat, lon)
        values = store.undulation(lat, lon)
        stored = stored_spline(result.spline, path)
        np.testing.assert_array_equal(values[inside], stored.undulation(lat, lon)[inside])
        assert np.isnan(values[~inside]).all() and inside.any() and (~inside).any()
        np.testing.assert_array_equal(store.covers(lat, lon), inside)
        reasons = store.coverage_reason(lat, lon)
        assert set(reasons[inside]) == {INSIDE} and set(reasons[~inside]) == {OUTSIDE}


def test_covers_scalar_array_and_broadcast(andes):
    store = geoidspline.open_store(andes[0])
    assert store.covers(-20.0, -70.0) is True
    mask = store.covers(np.array([[-20.0], [10.0]]), np.array([-70.0, -65.0, 0.0]))
    assert mask.shape == (2, 3) and mask.tolist() == [[True, True, False], [False, False, False]]
    assert store.covers(-20.0, -70.0 + 360.0) is True  # longitudes wrap
    assert store.coverage_reason(np.nan, -70.0) == OUTSIDE


# -- holes in the source ----------------------------------------------------------------


def test_no_data_holes_are_recorded_and_answer_nan(holed):
    """Seen: a 2°×2° block of no-data nodes was fitted as data; a query inside it
    answered 26.996 m (5 m off) with an error bound of 0.349 m."""
    path, result, _ = holed
    manifest = json.loads((path / "manifest.json").read_text())
    (part,) = manifest["coverage"]["parts"]
    assert part["region"] == list(HOLED_REGION.as_tuple()) and part["source"] == "holed.gtx"
    lattice = part["lattice"]
    assert lattice["dlat"] == lattice["dlon"] == 2.0 and lattice["nodata_count"] == 9
    store = geoidspline.open_store(path)
    centre = (20.0, 30.0)
    assert math.isnan(store.undulation(*centre)) and math.isnan(store.error_bound(*centre))
    assert store.coverage_reason(*centre) == NO_DATA
    # conservative: a cell with one no-data corner is not covered; the next cell is
    assert store.coverage_reason(16.5, 30.0) == NO_DATA  # cell 16-18 has the node at 18
    assert store.coverage_reason(15.5, 30.0) == INSIDE  # cell 14-16: all nodes have data
    assert store.undulation(15.5, 30.0) == stored_spline(result.spline, path).undulation(15.5, 30.0)
    assert store.coverage_reason(5.0, 30.0) == OUTSIDE


def test_holes_match_the_cell_rule_everywhere(holed):
    path, result, grid = holed
    store = geoidspline.open_store(path)
    rng = np.random.default_rng(5)
    lat, lon = rng.uniform(8, 32, 4000), rng.uniform(18, 42, 4000)
    i = np.floor((lat - grid.latitude[0]) / 2.0).astype(int)
    j = np.floor((lon - grid.longitude[0]) / 2.0).astype(int) % grid.longitude.size
    j2 = (j + 1) % grid.longitude.size
    nan = np.isnan(grid.values)
    cell_has_data = ~(nan[i, j] | nan[i + 1, j] | nan[i, j2] | nan[i + 1, j2])
    want = HOLED_REGION.contains(lat, lon) & cell_has_data
    np.testing.assert_array_equal(store.covers(lat, lon), want)
    values = store.undulation(lat, lon)
    np.testing.assert_array_equal(values[want], stored_spline(result.spline, path).undulation(lat[want], lon[want]))
    assert np.isnan(values[~want]).all()


def test_a_region_beyond_a_regional_grid(tmp_path, synthetic_grid):
    """A regional grid fitted over a larger region: no data beyond the grid's nodes."""
    g = synthetic_grid
    rows = (g.latitude >= 0) & (g.latitude <= 40)
    cols = (g.longitude >= 0) & (g.longitude <= 60)
    regional = _grid(g.values[np.ix_(rows, cols)], "regional", g.latitude[rows], g.longitude[cols])
    region = Region(-10.0, -10.0, 30.0, 50.0)
    # build_store refuses this (its check points need the grid), a fit does not
    result = fit_source(regional, region, PARAMS)
    write_store(tmp_path / "s", result, regional.provenance)
    store = geoidspline.open_store(tmp_path / "s")
    assert store.coverage_reason(-5.0, 20.0) == NO_DATA  # in the region, south of the grid
    assert store.coverage_reason(20.0, -5.0) == NO_DATA  # west of the grid
    assert store.coverage_reason(20.0, 20.0) == INSIDE
    assert store.coverage_reason(35.0, 20.0) == OUTSIDE
    assert math.isnan(store.undulation(-5.0, 20.0)) and np.isfinite(store.undulation(20.0, 20.0))


def test_a_model_covers_its_region(tmp_path, toy24):
    region = Region(-20.0, 100.0, 0.0, 130.0)
    build_store(toy24, tmp_path / "m", region, FitParameters(h0=0.2, max_level=1, tolerance_m=0.05,
                                                              tile_size=1.0), check_count=200)
    manifest = json.loads((tmp_path / "m" / "manifest.json").read_text())
    assert [p["lattice"] for p in manifest["coverage"]["parts"]] == [None]
    store = geoidspline.open_store(tmp_path / "m")
    rng = np.random.default_rng(1)
    lat, lon = rng.uniform(-20, 0, 500), rng.uniform(100, 130, 500)
    assert store.covers(lat, lon).all() and np.isfinite(store.undulation(lat, lon)).all()


def test_a_global_region_without_holes_covers_every_real_coordinate():
    """No lattice and 360 degrees of longitude: any latitude in [-90, 90] with any
    non-NaN longitude is covered (the poles too), a NaN coordinate never is; the
    same answers for a large batch, and a NaN is "outside the region" (it was "no data"
    for a NaN longitude)."""
    coverage = Coverage((CoveragePart(Region(-90.0, -180.0, 90.0, 180.0)),))
    lat = np.array([90.0, -90.0, 0.0, 45.0, np.nan, 10.0, -90.0])
    lon = np.array([1e5, 12.0, 359.5, -720.0, 0.0, np.nan, np.nan])
    want = np.array([True, True, True, True, False, False, False])
    np.testing.assert_array_equal(coverage.covers(lat, lon), want)
    np.testing.assert_array_equal(coverage.covers(np.tile(lat, 1000), np.tile(lon, 1000)), np.tile(want, 1000))
    assert coverage.covers(-90.0, 5.0) and not coverage.covers(-90.0, np.nan)
    np.testing.assert_array_equal(coverage.reasons(lat, lon)[4:], [OUTSIDE] * 3)


# -- coverage through updates -----------------------------------------------------------


def test_an_update_fills_a_hole_with_data_and_only_with_data(holed, analytic, tmp_path):
    path = Path(shutil.copytree(holed[0], tmp_path / "store"))
    old = geoidspline.open_store(path)
    # new data over the hole's west half only: the east half stays a hole
    def patch(lat, lon):
        return np.where((lat >= 16) & (lat <= 24) & (lon >= 31) & (lon <= 34), np.nan, analytic(lat, lon) + 0.5)

    source = _national(patch, "patch", (14.0, 22.0, 26.0, 36.0))
    update_store(path, source, Region(16.0, 24.0, 24.0, 34.0), blend_width_km=100.0)
    store = geoidspline.open_store(path)
    assert store.coverage_reason(20.0, 27.0) == INSIDE  # a hole before, data now
    assert old.coverage_reason(20.0, 27.0) == NO_DATA
    assert store.coverage_reason(20.0, 31.0) == NO_DATA  # no data in either source
    assert abs(store.undulation(20.0, 27.0) - (analytic(20.0, 27.0) + 0.5)) < 0.02
    # far from the update: the old coverage and values
    rng = np.random.default_rng(2)
    lat, lon = rng.uniform(10, 14, 200), rng.uniform(20, 40, 200)
    np.testing.assert_array_equal(store.covers(lat, lon), old.covers(lat, lon))


def test_a_national_grid_with_no_data_at_sea_keeps_the_store_there(andes, analytic, tmp_path):
    """The new source has NaN west of -70° (its "sea"): the store keeps its coverage and
    its own values there, and takes the new data east of it."""
    path = Path(shutil.copytree(andes[0], tmp_path / "store"))
    old = geoidspline.open_store(path)

    def land(lat, lon):
        return np.where(lon < -70.0, np.nan, analytic(lat, lon) + 1.0)

    national = _national(land, "national", (-34.0, -76.0, -18.0, -64.0))
    record = update_store(path, national, Region(-32.0, -74.0, -20.0, -66.0), blend_width_km=100.0)
    store = geoidspline.open_store(path)
    manifest = store.manifest
    # inside a region the store covered whole, the update adds no coverage part
    assert [p["source"] for p in manifest["coverage"]["parts"]] == ["synthetic"]
    assert record["store_version"] == 2 and manifest["history"][-1]["source"] == "national"
    sea = (-26.0, -73.0)
    land = (-26.0, -67.0)
    assert store.covers(*sea) and store.covers(*land)
    assert abs(store.undulation(*sea) - old.undulation(*sea)) < PARAMS.tolerance_m  # kept, not dragged
    # (the 1 m step at the coast itself is more than the tolerance allows: not converged there)
    assert abs(store.undulation(*land) - (analytic(*land) + 1.0)) < PARAMS.tolerance_m
    # outside the store's region the update adds nothing where the source has no data
    assert store.coverage_reason(-40.0, -73.0) == OUTSIDE


def test_an_update_beyond_the_region_adds_only_where_its_source_has_data(andes, synthetic_grid, tmp_path):
    """An update region reaching beyond the store's region (its centre inside) covers
    there only where the new source has data."""
    path = Path(shutil.copytree(andes[0], tmp_path / "store"))
    g = synthetic_grid
    values = g.values + 1.0
    values[np.ix_(g.latitude < -38.0, g.longitude < 360)] = np.nan  # no data south of -38°
    update_store(path, _grid(values, "beyond", g.latitude, g.longitude), Region(-42.0, -72.0, -30.0, -66.0),
                 blend_width_km=100.0)
    store = geoidspline.open_store(path)
    assert [p["source"] for p in store.manifest["coverage"]["parts"]] == ["synthetic", "beyond"]
    assert store.coverage_reason(-37.0, -69.0) == INSIDE  # beyond the old region, new data
    assert store.coverage_reason(-41.0, -69.0) == NO_DATA  # in the update's region, no data
    assert store.coverage_reason(-37.0, -75.0) == OUTSIDE  # beyond both regions
    assert np.isfinite(store.undulation(-37.0, -69.0)) and math.isnan(store.undulation(-41.0, -69.0))


def test_union_keeps_one_part_for_updates_inside_a_whole_region():
    whole = Coverage.of_region(Region(-40, -80, 0, -60), "fit")
    inner = Coverage.of_region(Region(-30, -75, -20, -65), "update")
    assert whole.union(inner).parts == whole.parts
    bigger = Coverage.of_region(Region(-50, -90, 10, -50), "bigger")
    assert bigger.union(whole).parts == bigger.parts and whole.union(bigger).parts == bigger.parts
    across = Coverage.of_region(Region(-10, 170, 10, -170), "across")  # the antimeridian
    assert across.union(Coverage.of_region(Region(-5, 175, 5, 185))).parts == across.parts


# -- the coverage rule itself (property-based) -------------------------------------------


@st.composite
def lattices_and_regions(draw):
    dlat = draw(st.sampled_from([0.5, 1.0, 2.0, 2.5]))
    dlon = draw(st.sampled_from([0.5, 1.0, 2.0, 3.0]))
    periodic = draw(st.booleans())
    nlat = draw(st.integers(3, 12))
    lat0 = draw(st.integers(-20, 20)) * dlat
    lat0 = max(-90.0, min(lat0, 90.0 - (nlat - 1) * dlat))
    if periodic:
        nlon = int(round(360 / dlon))
        lon0 = draw(st.integers(-180, 179)) * 1.0
    else:
        nlon = draw(st.integers(3, 14))
        lon0 = draw(st.integers(-200, 200)) * 1.0
    density = draw(st.sampled_from([0.0, 0.05, 0.3, 0.8]))
    nodata = np.random.default_rng(draw(st.integers(0, 2**32 - 1))).random((nlat, nlon)) < density
    south = draw(st.floats(lat0 - 3, lat0 + (nlat - 1) * dlat, allow_nan=False))
    height = draw(st.floats(0.1, 30))
    west = draw(st.floats(-180, 180, allow_nan=False))
    width = draw(st.floats(0.1, 400 if periodic else (nlon - 1) * dlon + 5))
    assume(south + height <= 90 and south >= -90)
    region = Region(south, west, south + height, west + min(width, 360.0))
    return lat0, dlat, nlat, lon0, dlon, nlon, nodata, region


#: Examples of the coverage property (counted in benchmarks/README.md "Trust").
COVERAGE_EXAMPLES = 200


@settings(max_examples=COVERAGE_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(case=lattices_and_regions(), seed=st.integers(0, 2**32 - 1))
def test_covered_exactly_where_a_cell_of_the_region_has_data(case, seed):
    """Against the rule computed on the whole lattice: a point strictly inside a lattice
    cell is covered iff it is in the region and all four nodes of that cell have data."""
    lat0, dlat, nlat, lon0, dlon, nlon, nodata, region = case
    lat = lat0 + dlat * np.arange(nlat)
    lon = lon0 + dlon * np.arange(nlon)
    sample = NodeSample(lat, lon, np.where(nodata, np.nan, 1.0))
    coverage = Coverage.from_sample(sample, region)
    rng = np.random.default_rng(seed)
    plat = rng.uniform(max(-90, region.south - 2), min(90, region.north + 2), 300)
    plon = rng.uniform(region.west - 5, region.west + region.longitude_span + 5, 300)
    fi = (plat - lat0) / dlat
    offset = np.mod(plon - lon0, 360.0)
    fj = offset / dlon
    periodic = abs(nlon * dlon - 360.0) < 1e-9
    strict = (np.abs(fi - np.round(fi)) > 1e-6) & (np.abs(fj - np.round(fj)) > 1e-6)
    ok = (fi > 0) & (fi < nlat - 1) & (periodic | (fj < nlon - 1))
    i = np.clip(np.floor(fi).astype(int), 0, nlat - 2)
    j = np.floor(fj).astype(int) % nlon
    j2 = (j + 1) % nlon if periodic else np.minimum(j + 1, nlon - 1)
    data = ~(nodata[i, j] | nodata[i + 1, j] | nodata[i, j2] | nodata[i + 1, j2])
    want = region.contains(plat, plon) & ok & data
    got = coverage.covers(plat, plon)
    np.testing.assert_array_equal(got[strict], want[strict])
    reasons = coverage.reasons(plat, plon)
    assert set(reasons[got]) <= {INSIDE}
    assert set(reasons[~got & region.contains(plat, plon)]) <= {NO_DATA}
    assert set(reasons[~region.contains(plat, plon)]) <= {OUTSIDE}


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(case=lattices_and_regions(), seed=st.integers(0, 2**32 - 1))
def test_large_batches_take_the_compiled_lookup_with_the_same_answers(case, seed):
    """A batch of COMPILED_FROM_POINTS points or more is looked up by the compiled kernel:
    the same answer as numpy's at every point, nodes, lattice edges, a hair beyond them,
    far longitudes, NaN and infinities included."""
    from geoidspline.sphere.coordinates import COMPILED_FROM_POINTS
    from geoidspline.sphere.coverage import NodataLattice

    lat0, dlat, nlat, lon0, dlon, nlon, nodata, region = case
    lattice = NodataLattice(lat0, dlat, lon0, dlon, nodata)
    rng = np.random.default_rng(seed)
    n = COMPILED_FROM_POINTS
    lat = np.concatenate([
        rng.uniform(lat0 - dlat, lat0 + nlat * dlat, n),
        lat0 + dlat * rng.integers(-1, nlat + 1, n),  # on nodes and lattice edges
        lat0 + dlat * rng.integers(0, nlat, n) + rng.choice([-1e-12, 1e-12, -1e-8, 1e-8], n),
    ])
    lon = np.concatenate([
        rng.uniform(lon0 - 400, lon0 + 400, n),
        lon0 + dlon * rng.integers(-1, nlon + 1, n),
        lon0 + dlon * rng.integers(0, nlon, n) + rng.choice([-1e-12, 1e-12, -1e-8, 1e-8], n),
    ])
    lat[::97], lon[1::89], lon[2::83] = np.nan, np.nan, np.inf
    compiled = lattice.cells_have_data(lat, lon)
    np.testing.assert_array_equal(compiled, lattice._numpy_cells_have_data(lat, lon))
    # with the region test in the same pass: the region's and the lattice's answers
    np.testing.assert_array_equal(lattice.cells_have_data(lat, lon, region=region),
                                  region.contains(lat, lon) & lattice._numpy_cells_have_data(lat, lon))
