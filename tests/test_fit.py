"""Fitting: exactness, convergence order, overlays, tiles and seams."""

import math

import numpy as np
import pytest

from geoidspline._kernels.fitting import cells_meet_sphere
from geoidspline.bspline.domain import active_cells
from geoidspline.bspline.keys import MAX_INDEX
from geoidspline.fitting.driver import fit_nodes
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.base import NodeSample
from geoidspline.sphere.region import GLOBAL, Region


def smooth_field(lat, lon):
    """A low-degree field on the sphere (metres): degree-2/3 spherical harmonics."""
    p, l = np.radians(lat), np.radians(lon)
    return 20 * np.sin(2 * p) * np.cos(l) + 10 * np.cos(p) ** 2 * np.sin(2 * l) + 3 * np.cos(p) ** 3 * np.cos(3 * l)


def bumpy_field(lat, lon):
    """The smooth field plus a narrow 2 m Gaussian bump at (5N, 3E), 2° wide."""
    return smooth_field(lat, lon) + 2 * np.exp(-((lat - 5) ** 2 + (lon - 3) ** 2) / 4)


def lattice(field, step_deg, south=-90, north=90, west=-180, east=180):
    lat = np.arange(south, north + 1e-9, step_deg)
    lon = np.arange(west, east - 1e-9, step_deg)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    return NodeSample(lat, lon, field(lat2, lon2))


REGION = Region(-20, -30, 20, 30)


def random_points(region, count, seed=0, inset=5.0):
    rng = np.random.default_rng(seed)
    lat = rng.uniform(region.south + inset, region.north - inset, count)
    lon = rng.uniform(region.west + inset, region.east - inset, count)
    return lat, lon


def test_active_cells_are_exactly_the_cells_meeting_the_sphere():
    h = 0.25
    cells = active_cells(h, GLOBAL)
    r = np.arange(-6, 6)
    every = np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T
    lo = every * h
    hi = lo + h
    near = np.sqrt((np.clip(0, lo, hi) ** 2).sum(axis=1))
    far = np.sqrt(np.maximum(lo**2, hi**2).sum(axis=1))
    expected = every[(near <= 1) & (far >= 1)]
    assert {tuple(c) for c in cells} == {tuple(c) for c in expected}


def test_constant_field_is_reproduced_exactly():
    sample = lattice(lambda la, lo: np.full_like(la, 7.25), 1.5, -60, 60, -90, 90)
    result = fit_nodes(sample, REGION, FitParameters(h0=0.1, max_level=0, tolerance_m=1e-6))
    lat, lon = random_points(REGION, 2000)
    # the second-difference penalty vanishes on constants; only the 1e-10 ridge remains
    np.testing.assert_allclose(result.spline.undulation(lat, lon), 7.25, atol=1e-6)


def test_convergence_order_is_about_h4_for_cubic_splines():
    """Max error at random points of a single-level fit for h, h/2, h/4.

    Theorem 3.3 of the thesis: ||g - s|| <= c h^n for order n = 4. Nodes are dense
    enough (h/5) that the data do not limit the fit.
    """
    errors = []
    lat, lon = random_points(REGION, 5000, seed=1)
    for h0 in (0.2, 0.1, 0.05):
        sample = lattice(smooth_field, math.degrees(h0 / 5), -70, 70, -100, 100)
        result = fit_nodes(sample, REGION, FitParameters(h0=h0, max_level=0, tolerance_m=1e-9))
        errors.append(np.abs(result.spline.undulation(lat, lon) - smooth_field(lat, lon)).max())
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert errors[-1] < 5e-5  # 20 m amplitude field, h = 0.05
    assert np.all(orders > 3.5), (errors, orders)


def test_overlays_refine_only_where_the_tolerance_is_violated():
    sample = lattice(bumpy_field, 0.5, -60, 60, -90, 90)
    params = FitParameters(h0=0.1, max_level=4, tolerance_m=0.01)
    result = fit_nodes(sample, REGION, params)
    assert result.converged
    assert result.node_max_error_m <= 0.01
    assert len(result.levels) >= 2
    # every overlay's B-splines sit near the bump or near nodes that were above tolerance
    fine = result.spline.levels[-1]
    centres = (fine.indices + params.order / 2) * fine.h
    lat = np.degrees(np.arcsin(centres[:, 2] / np.linalg.norm(centres, axis=1)))
    lon = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    assert np.all(REGION.expanded(2.0).contains(lat, lon))
    # finer levels have fewer coefficients than full coverage would need
    full = FitParameters(h0=fine.h, max_level=0)
    assert len(fine) < 0.5 * len(active_cells(full.h0, REGION)) * 8
    # the reported error is the real one at the nodes
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    inside = REGION.contains(lat2, lon2)
    err = np.abs(result.spline.undulation(lat2[inside], lon2[inside]) - sample.undulation[inside])
    assert err.max() == pytest.approx(result.node_max_error_m, rel=1e-9)



def island_field(lat, lon):
    """The smooth field plus a 1 m peak 0.5° wide on an island of radius 1° at (5N, 3E),
    NaN ("sea") from 1° to 4° around it: on a 0.5° lattice the island has 12 nodes and the
    peak is as narrow as the data."""
    r2 = (lat - 5) ** 2 + (lon - 3) ** 2
    return np.where((r2 > 1.0) & (r2 < 16.0), np.nan, smooth_field(lat, lon) + np.exp(-r2 / 0.25))


@pytest.fixture(scope="module")
def island_fits():
    """The island fitted to 1 cm with one pass of the data-limited finest level and with
    the default passes (level 5 would be finer than half the 0.5° spacing: level 4 is the finest)."""
    from geoidspline.fitting import driver

    sample = lattice(island_field, 0.5, -60, 60, -90, 90)
    params = FitParameters(h0=0.1, max_level=8, tolerance_m=0.01)
    passes = driver.FINEST_LEVEL_PASSES
    driver.FINEST_LEVEL_PASSES = 1
    try:
        one = fit_nodes(sample, REGION, params)
    finally:
        driver.FINEST_LEVEL_PASSES = passes
    return sample, one, fit_nodes(sample, REGION, params)


def test_a_data_limited_finest_level_takes_what_it_left_again(island_fits):
    """The peak on the island keeps 17.5 mm after the finest level's first pass (its ridge
    holds back what 12 nodes determine); passes of the same level on the nodes bring it
    within the tolerance, in the same levels (one spline per level, keys a superset)."""
    sample, one, more = island_fits
    assert one.data_limited and not one.converged
    assert one.node_max_error_m == pytest.approx(0.0175, abs=0.001)
    assert more.data_limited and more.converged and more.node_max_error_m <= 0.01
    assert [lv.level for lv in more.spline.levels] == [lv.level for lv in one.spline.levels] == [0, 1, 2, 3, 4]
    assert np.all(np.isin(one.spline.levels[-1].keys, more.spline.levels[-1].keys))
    finest = more.levels[-1]
    assert finest.level == 4 and finest.passes == 3
    assert finest.pass_max_error_m[0] == one.node_max_error_m
    assert np.all(np.diff(finest.pass_max_error_m) < 0) and finest.pass_max_error_m[-1] == more.node_max_error_m
    assert finest.pass_nodes_above_tolerance == [1, 1, 0]
    assert one.levels[-1].passes == 1 and one.levels[-1].pass_max_error_m == []  # no pass tried
    # the same when max_level stops at that finest level (as geoid-fit chooses it): the
    # passes follow whether the next level was refused or never asked for
    at_max = fit_nodes(sample, REGION, FitParameters(h0=0.1, max_level=4, tolerance_m=0.01))
    assert at_max.data_limited and at_max.levels[-1].pass_max_error_m == finest.pass_max_error_m
    # with max_level below it, no pass: a finer level may still come
    coarser = fit_nodes(sample, REGION, FitParameters(h0=0.1, max_level=3, tolerance_m=0.01))
    assert not coarser.data_limited and coarser.levels[-1].passes == 1
    # the reported error is the real one at the nodes
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    nodes = REGION.contains(lat2, lon2) & np.isfinite(sample.undulation)
    err = np.abs(more.spline.undulation(lat2[nodes], lon2[nodes]) - sample.undulation[nodes])
    assert err.max() == pytest.approx(more.node_max_error_m, rel=1e-9)


def test_the_finest_level_passes_add_no_wiggle_between_the_nodes(island_fits):
    """Between the island's nodes (cell centres, where a level finer than the data would
    be free) the passes change the error by millimetres (measured: 31.2 -> 33.8 mm, the
    peak being as narrow as the node spacing), and the sea beyond the island not at all."""
    _, one, more = island_fits
    lat, lon = np.meshgrid(np.arange(4.25, 6.0, 0.5), np.arange(2.25, 4.0, 0.5), indexing="ij")
    on_island = (lat - 5) ** 2 + (lon - 3) ** 2 < 1.0
    lat, lon = lat[on_island], lon[on_island]
    truth = smooth_field(lat, lon) + np.exp(-((lat - 5) ** 2 + (lon - 3) ** 2) / 0.25)
    before = np.abs(one.spline.undulation(lat, lon) - truth).max()
    after = np.abs(more.spline.undulation(lat, lon) - truth).max()
    assert lat.size == 12 and after < before + 0.005
    sea_lon = np.linspace(4.5, 6.8, 50)  # 1.5-3.8° from the island's centre
    sea_lat = np.full(sea_lon.size, 5.0)
    np.testing.assert_allclose(more.spline.undulation(sea_lat, sea_lon), one.spline.undulation(sea_lat, sea_lon),
                               atol=1e-12)


def test_add_levels_is_the_sum_of_the_two_splines():
    from geoidspline.bspline.level import LevelSpline, add_levels
    from geoidspline.hierarchy.ambient import AmbientSpline

    rng = np.random.default_rng(11)
    sample = lattice(smooth_field, 2.0, -30, 30, -40, 40)
    keys = fit_nodes(sample, Region(-10, -10, 10, 10), FitParameters(h0=0.1, max_level=0)).spline.levels[0].keys
    a_keys, b_keys = np.sort(rng.choice(keys, 300, replace=False)), np.sort(rng.choice(keys, 200, replace=False))
    a = LevelSpline(0, 0.1, 4, a_keys, rng.normal(size=a_keys.size))
    b = LevelSpline(0, 0.1, 4, b_keys, rng.normal(size=b_keys.size))
    total = add_levels(a, b)
    assert total.keys.size == np.union1d(a_keys, b_keys).size
    lat, lon = random_points(Region(-10, -10, 10, 10), 2000, inset=0.0)
    np.testing.assert_allclose(AmbientSpline([total]).undulation(lat, lon),
                               AmbientSpline([a]).undulation(lat, lon) + AmbientSpline([b]).undulation(lat, lon),
                               atol=1e-12)
    with pytest.raises(ValueError, match="cannot add level 1"):
        add_levels(a, LevelSpline(1, 0.05, 4, b_keys, b.coefficients))

@pytest.fixture(scope="module")
def tiled_and_whole():
    sample = lattice(bumpy_field, 0.5, -60, 60, -90, 90)
    params = FitParameters(h0=0.1, max_level=2, tolerance_m=0.01, block_cells=8, margin_cells=10,
                           untiled_max_unknowns=0)
    whole = fit_nodes(sample, REGION, FitParameters(h0=0.1, max_level=2, tolerance_m=0.01,
                                                    untiled_max_unknowns=10**9))
    tiled = fit_nodes(sample, REGION, params)
    return whole, tiled


def test_tiled_fit_agrees_with_untiled_fit(tiled_and_whole):
    whole, tiled = tiled_and_whole
    assert all(r.blocks_solved > 1 for r in tiled.levels)
    assert [r.coefficients for r in tiled.levels] == [r.coefficients for r in whole.levels]
    lat, lon = random_points(REGION, 20000, seed=2, inset=0.0)
    diff = np.abs(tiled.spline.undulation(lat, lon) - whole.spline.undulation(lat, lon))
    # measured: max 1.0 mm, RMS 0.07 mm with a 10-cell margin, tolerance 10 mm
    assert diff.max() < 0.2 * 0.01
    assert np.sqrt(np.mean(diff**2)) < 0.02 * 0.01


def test_c2_across_block_seams(tiled_and_whole):
    """Value, gradient and Hessian continuous across the faces between solve blocks."""
    _, tiled = tiled_and_whole
    spline = tiled.spline
    lat, lon = random_points(REGION, 400, seed=3)
    from geoidspline.sphere.coordinates import directions

    u = directions(lat, lon)
    fine_h = spline.levels[-1].h
    block = 8 * fine_h  # block_cells * h of the finest level: a multiple of every cell face
    for axis in range(3):
        x = u.copy()
        x[:, axis] = np.round(x[:, axis] / block) * block
        x /= np.linalg.norm(x, axis=1)[:, None]  # back onto the sphere, near the seam
        x[:, axis] = np.round(x[:, axis] / block) * block  # exactly on the seam plane
        # A continuous quantity changes across the seam in proportion to the step
        # (by its derivative times 2 delta); a jump would stay the same size. Steps of
        # 1e-6 and 1e-7: a cubic's third derivative jumps at every knot, adding a
        # delta**2 term that at 1e-5 can cancel the linear one (a point of this fit:
        # Hessian yz across z = 0 changes by 2.2 delta - 3.6e5 delta**2, ratio 1.9).
        jumps = []
        for delta in (1e-6, 1e-7):
            step = np.zeros(3)
            step[axis] = delta
            jumps.append(np.abs(spline.evaluate_points(x + step, nderiv=2)
                                - spline.evaluate_points(x - step, nderiv=2)))
        big = jumps[0] > 1e-9 * (1 + np.abs(spline.evaluate_points(x, nderiv=2)))
        ratio = jumps[0][big] / np.maximum(jumps[1][big], 1e-300)
        assert big.any()
        assert np.all(ratio > 5), f"axis {axis}: not continuous, ratios {np.sort(ratio)[:5]}"


def test_restriction_derivatives_match_finite_differences_along_the_sphere():
    """d/dλ of the restricted spline from the ambient gradient equals a central
    difference in longitude; the tolerance is the O(ε²) truncation of the quotient."""
    sample = lattice(smooth_field, 1.0, -60, 60, -90, 90)
    result = fit_nodes(sample, REGION, FitParameters(h0=0.1, max_level=0, tolerance_m=1e-6))
    lat, lon = random_points(REGION, 300, seed=4)
    from geoidspline.sphere.coordinates import directions

    u = directions(lat, lon)
    grad = result.spline.evaluate_points(u, nderiv=1)[:, 1:4]
    # ∂u/∂λ = (-cos φ sin λ, cos φ cos λ, 0) per radian
    du = np.stack([-np.cos(np.radians(lat)) * np.sin(np.radians(lon)),
                   np.cos(np.radians(lat)) * np.cos(np.radians(lon)), np.zeros_like(lat)], axis=1)
    analytic = (grad * du).sum(axis=1)
    eps = 1e-3  # degrees
    fd = (result.spline.undulation(lat, lon + eps) - result.spline.undulation(lat, lon - eps)) / (2 * math.radians(eps))
    coef = np.abs(result.spline.levels[0].coefficients).max()
    bound = math.radians(eps) ** 2 / 6 * 8 * 3 * coef / 0.1**3 * 3
    np.testing.assert_allclose(fd, analytic, atol=bound)


def test_keys_cover_the_index_range_of_the_finest_level():
    params = FitParameters(h0=0.1, max_level=12)
    assert 1.0 / params.spacing(12) + 8 < MAX_INDEX


def test_fit_straight_from_a_spherical_harmonic_model(make_synthesis):
    """A degree-12 model is fitted from its synthesis; the store is checked against
    the exact synthesis at random points that were not fit sites."""
    from geoidspline.fitting.check_points import check_points
    from geoidspline.fitting.driver import fit_source

    synthesis = make_synthesis(12, 11, "toy12")
    region = Region(10, 10, 30, 40)
    params = FitParameters(h0=0.1, tolerance_m=0.01, max_level=3, sample_spacing_deg=1.0)
    result = fit_source(synthesis, region, params)
    assert result.converged and result.node_max_error_m <= 0.01
    check = check_points(synthesis, region, count=3000, seed=3)
    err = np.abs(check.truth - result.spline.undulation(check.latitude, check.longitude))
    assert err.max() < 3 * 0.01
    assert np.sqrt(np.mean(err**2)) < 0.01


@pytest.mark.parametrize("count", [0, 1, 5, 3000])
@pytest.mark.parametrize("step, lo, hi", [(1, -7, 3), (1, 0, 0), (1000, -2, 5), (1 << 21, -16, 16), (1 << 42, 0, 5)])
def test_dilate_axis_equals_unique_of_all_shifts(count, step, lo, hi):
    from geoidspline.bspline.keys import dilate_axis

    rng = np.random.default_rng(count)
    # runs of consecutive keys (as a shell's columns give) and scattered ones
    starts = rng.integers(0, 10**6, count) * 37
    keys = np.unique(np.concatenate([starts, starts + 1, starts + 2, rng.integers(0, 4 * 10**7, count)]))
    shifts = np.arange(lo, hi + 1) * step
    expected = np.unique((keys[:, None] + shifts[None, :]).ravel())
    np.testing.assert_array_equal(dilate_axis(keys, step, lo, hi), expected)


@pytest.mark.parametrize("h", [0.1, 0.04, 0.005, 0.0025])
def test_cells_touching_the_sphere_at_the_axis_points_meet_it(h):
    """Where 1/h is an integer the sphere touches cell faces at (±1, 0, 0), (0, ±1, 0),
    (0, 0, ±1): the cells just outside must count, whatever the rounding of k h."""
    n = round(1 / h)
    outside, beyond = [], []
    for axis in range(3):
        for sign in (1, -1):
            cell = np.zeros(3, np.int64)
            cell[axis] = n if sign > 0 else -n - 1
            outside.append(cell.copy())
            cell[axis] += sign
            beyond.append(cell)
    assert cells_meet_sphere(np.array(outside), h, 1.0).all()
    assert not cells_meet_sphere(np.array(beyond), h, 1.0).any()


def test_overlays_at_the_poles_fit_both_sides_of_the_sphere(toy24):
    """An overlay over a polar cap improves the poles like everywhere else (it used to
    fit rays with their outer sites dropped at the pole and make it 20 times worse)."""
    from geoidspline.fitting.driver import fit_source

    model = toy24
    rng = np.random.default_rng(7)
    # at h = 0.005, -201 h + h rounds below -1: level 0 lost the cells outside the south
    # pole, and the overlay's outer sites there saw a level 0 with B-splines missing
    cap = Region(-90, -180, -88, 180)
    base = fit_source(model, cap, FitParameters(h0=0.005, max_level=0, tolerance_m=1.0, method="interpolation"))
    tolerance = 0.25 * base.node_max_error_m
    refined = fit_source(model, cap, FitParameters(h0=0.005, max_level=1, tolerance_m=tolerance,
                                                   method="interpolation", sample_spacing_deg=0.02))
    lat = np.concatenate([[-90.0], rng.uniform(-90, -89, 300)])
    lon = np.concatenate([[0.0], rng.uniform(-180, 180, 300)])
    err = np.abs(model.undulation(lat, lon) - refined.spline.undulation(lat, lon))
    assert refined.levels[1].coefficients > 0
    assert err.max() < 2 * tolerance


def test_model_check_points_come_in_rings_uniform_in_area():
    """A model's check points: RING_POINTS a random latitude (uniform in sin), each with
    its own random longitude over the region; the count asked for, whatever it is; the
    same points for the same seed."""
    from geoidspline.fitting.check_points import RING_POINTS, random_positions

    region = Region(-30.0, 100.0, 60.0, 130.0)
    lat, lon = random_positions(region, 25, seed=4)
    assert lat.size == lon.size == 25 and RING_POINTS == 10
    assert [np.unique(lat[a:a + 10]).size for a in (0, 10, 20)] == [1, 1, 1]
    assert np.unique(lat).size == 3 and np.unique(lon).size == 25
    assert lat.min() >= -30.0 and lat.max() <= 60.0 and lon.min() >= 100.0 and lon.max() <= 130.0
    again = random_positions(region, 25, seed=4)
    np.testing.assert_array_equal(again[0], lat)
    np.testing.assert_array_equal(again[1], lon)
    z = np.sin(np.radians(random_positions(GLOBAL, 20_000, seed=0)[0][::10]))
    assert np.histogram(z, bins=4, range=(-1, 1))[0].min() > 400  # 2,000 rings, 500 a bin expected


@pytest.mark.parametrize("with_gaps", [False, True])
def test_data_nodes_are_the_samples_points_row_by_row_one_at_a_pole(with_gaps):
    """A sample's data nodes: every finite point of its lattice row by row, its row
    counted on the whole lattice (``first_row``), one node on a pole row; the values a
    copy, not the sample's array (a fit subtracts its levels from them)."""
    from geoidspline.fitting.sites import DataNodes

    latitude = np.array([-90.0, -89.5, -89.0, 88.0])
    longitude = np.array([-180.0, -90.0, 0.0, 90.0, 179.0])
    undulation = np.arange(20.0).reshape(4, 5)
    if with_gaps:
        undulation[1, 2] = np.nan
    region = Region(-89.6, -180.0, 90.0, 180.0)
    nodes = DataNodes.from_sample(NodeSample(latitude, longitude, undulation, first_row=7), region)
    rows = [0] + [1] * 5 + [2] * 5 + [3] * 5
    cols = [0] + list(range(5)) * 3
    if with_gaps:
        del rows[3], cols[3]
    np.testing.assert_array_equal(nodes.row, np.array(rows) + 7)
    np.testing.assert_array_equal(nodes.col, cols)
    np.testing.assert_array_equal(nodes.latitude, latitude[rows])
    np.testing.assert_array_equal(nodes.longitude, longitude[cols])
    np.testing.assert_array_equal(nodes.values, undulation[rows, cols])
    np.testing.assert_array_equal(nodes.in_region, latitude[rows] >= -89.6)
    assert nodes.directions.shape == (len(rows), 3) and nodes.directions[0, 2] == -1.0
    assert not np.shares_memory(nodes.values, undulation)
    # no pole and no gap: every point, the values still a copy
    whole = DataNodes.from_sample(NodeSample(latitude[1:], longitude, np.ones((3, 5))), region)
    assert whole.values.size == 15 and whole.row.tolist() == [0] * 5 + [1] * 5 + [2] * 5
    whole.values[0] = 5.0
    assert whole.latitude[0] == -89.5 and whole.col.tolist() == list(range(5)) * 3
