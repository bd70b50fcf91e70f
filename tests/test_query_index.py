"""The query index folds the overlays: one level per point, the same sum as level by level.

:class:`geoidspline.bspline.index.BrickIndex` rewrites S_0 + … + S_ℓ on level ℓ's grid (B-spline
subdivision) near the sphere, and evaluates a point on the finest level that has a
brick there only. These tests compare it with a plain reference: the sum over levels
of the order³ B-splines touching each point, found by ``np.searchsorted`` in each
level's sorted keys and weighted with scipy's B-spline basis element.

Tolerances: 1e-9 m for values; for derivatives the same 1e-9 m over one cell of the
finest level (1e-9 / h_f per unit length, 1e-9 / h_f² per unit length squared), since
a gradient is a difference of coefficients divided by h.
"""

import numpy as np
import pytest
from scipy.interpolate import BSpline

from geoidspline._kernels import query as _kernels
from geoidspline._kernels.common import bspline_weights as compiled_bspline_weights
from geoidspline.bspline.basis import bspline_weights
from geoidspline.bspline.evaluate import evaluate_levels
from geoidspline.bspline.keys import pack_keys
from geoidspline.bspline.level import LevelSpline
from geoidspline.fitting.driver import fit_nodes
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.bspline.index import FOLD_BAND_CELLS
from geoidspline.sources.base import NodeSample
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region

# derivative multi-indices of the output columns: value, gradient, Hessian xx yy zz xy xz yz
_COLUMNS = [(0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1),
            (2, 0, 0), (0, 2, 0), (0, 0, 2), (1, 1, 0), (1, 0, 1), (0, 1, 1)]


def reference_evaluate(levels, points, nderiv=0):
    """Σ_ℓ Σ_k c_k B_k(x) (and derivatives), straight from each level's sorted keys."""
    width = {0: 1, 1: 4, 2: 10}[nderiv]
    out = np.zeros((points.shape[0], width))
    for lv in levels:
        if len(lv) == 0:
            continue
        n, h = lv.order, lv.h
        element = BSpline.basis_element(np.arange(n + 1), extrapolate=False)
        basis = [element] + [element.derivative(d) for d in range(1, nderiv + 1)]
        f = points / h
        cell = np.floor(f).astype(np.int64)
        t = f - cell
        j = np.arange(n)
        # weights[d][axis][:, j]: d-th derivative (per unit length) of B-spline k = a - n + 1 + j
        weights = [[np.nan_to_num(basis[d](t[:, axis, None] + n - 1 - j)) / h**d for axis in range(3)]
                   for d in range(nderiv + 1)]
        for p in range(n):
            for q in range(n):
                for r in range(n):
                    key = pack_keys(cell - n + 1 + np.array([p, q, r]))
                    pos = np.minimum(np.searchsorted(lv.keys, key), len(lv) - 1)
                    coef = np.where(lv.keys[pos] == key, lv.coefficients[pos], 0.0)
                    for col in range(width):
                        dx, dy, dz = _COLUMNS[col]
                        out[:, col] += coef * weights[dx][0][:, p] * weights[dy][1][:, q] * weights[dz][2][:, r]
    return out


def unit_vectors(rng, count):
    u = rng.normal(size=(count, 3))
    return u / np.linalg.norm(u, axis=1)[:, None]


def patch_keys(rng, h, order, centre, radius, keep=0.8, near_sphere=True):
    """B-splines whose support centre is within radius of centre (and near the sphere),
    a random fraction ``1 - keep`` of them dropped (holes)."""
    lo = np.floor((centre - radius) / h).astype(int) - order
    hi = np.ceil((centre + radius) / h).astype(int) + 1
    axes = [np.arange(a, b) for a, b in zip(lo, hi)]
    idx = np.array(np.meshgrid(*axes, indexing="ij")).reshape(3, -1).T
    mid = (idx + order / 2.0) * h
    sel = np.linalg.norm(mid - centre, axis=1) <= radius
    if near_sphere:
        sel &= np.abs(np.linalg.norm(mid, axis=1) - 1.0) <= order * h
    idx = idx[sel]
    return idx[rng.random(len(idx)) < keep]


def random_overlays(seed, order=4, h0=0.2, nlevels=4, inner=True):
    """A sparse level 0 over the sphere with holes and random patches on finer levels.

    Patches are placed independently, so finer levels exist both over coarser ones and
    where the coarser levels have nothing; ``inner`` adds a finest-level patch around
    a point at radius 0.6, far from the sphere (evaluated through the own tables).
    """
    rng = np.random.default_rng(seed)
    levels = []
    for ell in range(nlevels):
        h = h0 / 2**ell
        if ell == 0:
            idx = patch_keys(rng, h, order, np.zeros(3), 1.0 + order * h, keep=0.9)
        else:
            parts = [patch_keys(rng, h, order, c, rng.uniform(6, 14) * h) for c in unit_vectors(rng, 6)]
            if inner and ell == nlevels - 1:
                parts.append(patch_keys(rng, h, order, 0.6 * unit_vectors(rng, 1)[0], 5 * h, near_sphere=False))
            idx = np.unique(np.concatenate(parts), axis=0)
        levels.append(LevelSpline.from_indices(ell, h, order, idx, rng.normal(scale=10.0 / 2**ell, size=len(idx))))
    return levels


def point_sets(rng, levels, count=3000):
    """Points on the sphere, in thin and thick shells around it, and anywhere in the cube."""
    h0 = max(lv.h for lv in levels)
    hf = min(lv.h for lv in levels)
    u = unit_vectors(rng, count)
    faces = u.copy()
    brick = (1 << _kernels.BRICK_BITS) * hf  # on faces between bricks of the finest level
    axis = rng.integers(0, 3, count)
    faces[np.arange(count), axis] = np.round(faces[np.arange(count), axis] / brick) * brick
    return {
        "sphere": u,
        "0.999-1.001": u * rng.uniform(0.999, 1.001, (count, 1)),
        "1-1.5hf": u * (1 - 1.5 * hf),
        "1+1.5hf": u * (1 + 1.5 * hf),
        "shell 2h0": u * rng.uniform(1 - 2 * h0, 1 + 2 * h0, (count, 1)),
        "brick faces": faces,
        "cube": rng.uniform(-1.3, 1.3, (count, 3)),
    }


def assert_matches_reference(spline, levels, points, label=""):
    """The compiled folded index and the numpy evaluator both equal the reference."""
    hf = min(lv.h for lv in levels)
    for nderiv in (0, 1, 2):
        want = reference_evaluate(levels, points, nderiv)
        folded = np.zeros_like(want)
        spline.index.add_to(points, folded, nderiv)
        folded[~np.isfinite(points).all(axis=1)] = np.nan
        by_numpy = evaluate_levels(spline.levels, points, nderiv)
        tol = np.array([1e-9] + [1e-9 / hf] * 3 + [1e-9 / hf**2] * 6)[:want.shape[1]]
        for name, got in (("folded", folded), ("numpy", by_numpy)):
            err = np.abs(got - want).max(axis=0)
            assert np.all(err <= tol), f"{label} {name} nderiv={nderiv}: max |error| {err} > {tol}"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_folded_evaluation_equals_the_level_by_level_sum(seed):
    levels = random_overlays(seed)
    spline = AmbientSpline(levels)
    assert [d for d in spline.index.depths] == [0, 1, 2, 3]
    for name, points in point_sets(np.random.default_rng(100 + seed), levels).items():
        assert_matches_reference(spline, levels, points, name)


@pytest.mark.parametrize("order", [3, 5, 6])
def test_other_orders_fold_exactly(order):
    levels = random_overlays(7, order=order, nlevels=3)
    spline = AmbientSpline(levels)
    for name, points in point_sets(np.random.default_rng(8), levels, count=1500).items():
        assert_matches_reference(spline, levels, points, f"order {order}, {name}")


def test_points_given_in_query_order_evaluate_to_the_bits_of_the_sorted_evaluation():
    """Many points (above the ordering threshold) already in ``query_order``'s order and
    evaluated as they come (``ordered``) give, put back, the bits of the evaluation that
    sorts them itself, values and derivatives."""
    levels = random_overlays(3)
    spline = AmbientSpline(levels)
    rng = np.random.default_rng(11)
    points = rng.normal(size=(40_000, 3))
    points /= np.linalg.norm(points, axis=1)[:, None]
    visit = _kernels.query_order(points)
    for nderiv in (0, 1):
        expected = spline.evaluate_points(points, nderiv, any_batch=True)
        back = np.zeros_like(expected)
        back[visit] += spline.evaluate_points(points[visit], nderiv, any_batch=True, ordered=True)
        np.testing.assert_array_equal(back, expected)
        assert np.abs(expected).max() > 0.0


def test_points_in_the_band_read_only_the_folded_tables():
    """On and near the sphere a point is evaluated on one level: with every own table
    emptied (the coarsest level's folded table is its own), the results do not change;
    far from the sphere they do, as there the own tables are summed level by level."""
    levels = random_overlays(3)
    spline = AmbientSpline(levels)
    rng = np.random.default_rng(4)
    hf = min(lv.h for lv in levels)
    u = unit_vectors(rng, 5000)
    near = u * rng.uniform(1 - FOLD_BAND_CELLS * hf, 1 + FOLD_BAND_CELLS * hf, (5000, 1))
    far = rng.uniform(-0.7, 0.7, (5000, 3))
    before_near = spline.evaluate_points(near, nderiv=2)
    before_far = spline.evaluate_points(far)
    spline.index.own_cols[:] = 0
    spline.index.own_full[:] = 0  # and its full-column map: every own column now reads as empty
    np.testing.assert_array_equal(spline.evaluate_points(near, nderiv=2), before_near)
    assert np.abs(spline.evaluate_points(far) - before_far).max() > 1e-3


def test_empty_duplicate_and_non_nested_levels():
    levels = random_overlays(5, nlevels=3, inner=False)
    rng = np.random.default_rng(6)
    # a second level on level 1's grid (summed with it), an empty level, and a level on
    # h0 / 3: not nested in the coarser ones, so it and every finer level stay unfolded
    extra = random_overlays(9, nlevels=2, inner=False)[1]
    empty = LevelSpline(7, 0.01, 4, np.zeros(0, np.int64), np.zeros(0))
    third_h = levels[0].h / 3
    third_idx = patch_keys(rng, third_h, 4, unit_vectors(rng, 1)[0], 8 * third_h)
    third = LevelSpline.from_indices(8, third_h, 4, third_idx, rng.normal(size=len(third_idx)))
    # (levels 0 and 2 only: level 2 folds through level 1's grid, which has no bricks)
    for case in ([extra] + levels + [empty], levels + [third], [levels[2]], [third, levels[1]], [levels[0], levels[2]]):
        spline = AmbientSpline(case)
        for name, points in point_sets(rng, [lv for lv in case if len(lv)], count=1000).items():
            assert_matches_reference(spline, case, points, name)
    assert AmbientSpline([extra] + levels).index.depths == (0, 1, 2)
    assert AmbientSpline([levels[2], levels[0]]).index.depths == (0, 2)
    # h0/3 sorts between h0/2 and h0/4: it and the finer h0/4 level are not folded
    assert AmbientSpline(levels + [third]).index.depths == (0, 1, None, None)


def test_nan_points_and_no_levels():
    levels = random_overlays(2, nlevels=2)
    points = np.array([[np.nan, 0.0, 1.0], [0.6, 0.0, 0.8]])
    values = AmbientSpline(levels).evaluate_points(points)
    assert np.isnan(values[0]) and values[1] == pytest.approx(reference_evaluate(levels, points[1:])[0, 0], abs=1e-9)
    assert AmbientSpline([]).evaluate_points(points[1:])[0] == 0.0


def test_many_points_are_ordered_without_changing_results():
    """From 20,000 points on, the index visits them in its own order (locality)."""
    levels = random_overlays(11)
    spline = AmbientSpline(levels)
    rng = np.random.default_rng(12)
    points = unit_vectors(rng, 60_000) * rng.uniform(0.95, 1.05, (60_000, 1))
    points[::997] = np.nan
    many = spline.evaluate_points(points, nderiv=1)
    few = np.concatenate([spline.evaluate_points(points[i:i + 5000], nderiv=1) for i in range(0, 60_000, 5000)])
    np.testing.assert_array_equal(many, few)
    order = _kernels.query_order(points)
    assert np.array_equal(np.sort(order), np.arange(60_000))


def test_fitted_spline_folds_exactly():
    """A real overlay fit (a narrow bump on a smooth field) against the reference."""
    def field(lat, lon):
        p, l = np.radians(lat), np.radians(lon)
        return (20 * np.sin(2 * p) * np.cos(l) + 10 * np.cos(p) ** 2 * np.sin(2 * l)
                + 2 * np.exp(-((lat - 5) ** 2 + (lon - 3) ** 2) / 4))

    lat = np.arange(-40, 40.01, 0.5)
    lon = np.arange(-40, 40.01, 0.5)
    sample = NodeSample(lat, lon, field(*np.meshgrid(lat, lon, indexing="ij")))
    result = fit_nodes(sample, Region(-10, -10, 20, 15), FitParameters(h0=0.1, max_level=4, tolerance_m=0.01))
    levels = list(result.spline.levels)
    assert len(levels) >= 3
    rng = np.random.default_rng(13)
    hf = levels[-1].h
    la = rng.uniform(-10, 20, 3000)
    lo = rng.uniform(-10, 15, 3000)
    u = directions(la, lo)
    sets = {"sphere": u, "0.999-1.001": u * rng.uniform(0.999, 1.001, (3000, 1)),
            "1-1.5hf": u * (1 - 1.5 * hf), "1+1.5hf": u * (1 + 1.5 * hf),
            "shell 2h0": u * rng.uniform(1 - 2 * levels[0].h, 1 + 2 * levels[0].h, (3000, 1))}
    for name, points in sets.items():
        assert_matches_reference(result.spline, levels, points, name)


def test_small_batches_use_numpy_and_agree_with_the_folded_index():
    """Below FOLDED_FROM_POINTS the numpy evaluator answers and no index is built; it
    equals the compiled folded index to 1e-9 m (values), 1e-9 m per finest cell
    (gradients, Hessians), on and off the sphere."""
    from geoidspline.hierarchy.ambient import FOLDED_FROM_POINTS

    rng = np.random.default_rng(21)
    h0, order = 0.2, 4
    levels = []
    for level in range(3):
        h = h0 / 2**level
        r = np.arange(int(-1.3 / h), int(1.3 / h))
        idx = np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T
        idx = idx[rng.random(len(idx)) < (1.0 if level == 0 else 0.3)]
        levels.append(LevelSpline.from_indices(level, h, order, idx, rng.normal(size=len(idx))))
    small = AmbientSpline(levels)
    u = rng.normal(size=(FOLDED_FROM_POINTS - 1, 3))
    u /= np.linalg.norm(u, axis=1)[:, None]
    u[:500] *= rng.uniform(0.9, 1.1, (500, 1))
    u[7] = np.nan
    plain = small.evaluate_points(u, nderiv=2)
    assert small._folded is None  # nothing built for a small batch
    np.testing.assert_array_equal(plain, evaluate_levels(levels, u, 2))
    folded = AmbientSpline(levels).evaluate_points(np.vstack([u, u[:1]]), nderiv=2)[:-1]
    hf = h0 / 4
    tol = np.array([1e-9] + [1e-9 / hf] * 3 + [1e-9 / hf**2] * 6)
    assert np.isnan(plain[7]).all() and np.isnan(folded[7]).all()
    ok = np.isfinite(u).all(axis=1)
    err = np.abs(plain[ok] - folded[ok]).max(axis=0)
    assert np.all(err <= tol), err
    assert np.abs(plain[ok, 0]).max() > 1.0  # real values, not zeros


@pytest.mark.parametrize("order", [2, 3, 4, 5, 6])
def test_numpy_weights_equal_the_compiled_ones(order):
    t = np.array([0.0, 0.25, 0.6180339887, 0.999])
    nderiv = 2 if order >= 3 else 1
    got = bspline_weights(t, order, nderiv)
    for i, ti in enumerate(t):
        want = np.zeros((3, order))
        compiled_bspline_weights(ti, order, nderiv, want)
        np.testing.assert_allclose(got[:, i, :], want[:nderiv + 1], rtol=0, atol=1e-15)
    np.testing.assert_allclose(got[0].sum(axis=1), 1.0, atol=1e-15)


def test_numpy_evaluator_far_points_and_empty_levels():
    levels = random_overlays(2, nlevels=2)
    points = np.array([[1e300, 0.0, 0.0], [0.0, -5e6, 0.0], [0.6, 0.0, 0.8], [np.inf, 0.0, 0.0]])
    out = evaluate_levels(levels, points, 1)
    np.testing.assert_array_equal(out[:2], 0.0)  # no B-spline out there
    np.testing.assert_allclose(out[2], reference_evaluate(levels, points[2:3], 1)[0], atol=1e-9 / levels[-1].h)
    assert np.isnan(out[3]).all()
    empty = LevelSpline(0, 0.1, 4, np.zeros(0, np.int64), np.zeros(0))
    np.testing.assert_array_equal(evaluate_levels([empty], points[:3], 2), 0.0)


@pytest.mark.parametrize("order", [4, 3, 6])
def test_latlon_batches_in_one_call_equal_directions_then_points(order):
    """AmbientSpline.undulation on a large batch (fused sort, directions and kernel) gives
    bitwise the values of evaluate_points at directions(), for any thread count and
    block split, and the reference sum to 1e-9 m; NaN gives NaN."""
    from geoidspline._kernels import _clib
    from geoidspline.hierarchy.ambient import FOLDED_FROM_POINTS

    levels = random_overlays(31, order=order, nlevels=4 if order == 4 else 3)
    spline = AmbientSpline(levels)
    rng = np.random.default_rng(32)
    count = 140_000 if order == 4 else 3 * FOLDED_FROM_POINTS  # 140,000: two blocks on two threads
    lat = np.degrees(np.arcsin(rng.uniform(-1, 1, count)))
    lon = rng.uniform(-540, 540, count)  # any longitude is wrapped
    lat[::101] = np.nan
    lon[::103] = np.nan
    lat[5], lat[6] = 90.0, -90.0
    want = spline.evaluate_points(directions(lat, lon))
    threads = _clib.threads()
    try:
        for n in sorted({1, 2, threads}):
            _clib.set_threads(n)
            np.testing.assert_array_equal(spline.undulation(lat, lon), want)
    finally:
        _clib.set_threads(threads)
    assert np.isnan(want[::101]).all() and np.isnan(want[::103]).all()
    ok = np.flatnonzero(np.isfinite(lat) & np.isfinite(lon))[:3000]
    ref = reference_evaluate(levels, directions(lat[ok], lon[ok]))[:, 0]
    np.testing.assert_allclose(want[ok], ref, rtol=0, atol=1e-9)
    assert np.abs(ref).max() > 1.0
    # broadcasting, and the small-batch (numpy) answer to the same points, to rounding
    grid = spline.undulation(lat[:64, None], lon[None, :64])
    assert grid.shape == (64, 64)
    np.testing.assert_array_equal(grid, spline.undulation(np.repeat(lat[:64], 64), np.tile(lon[:64], 64)).reshape(64, 64))
    np.testing.assert_allclose(spline.undulation(lat[ok[:100]], lon[ok[:100]]), want[ok[:100]], rtol=0, atol=1e-9)


def test_latlon_batches_refuse_bad_coordinates():
    from geoidspline.errors import CoordinateError
    from geoidspline.hierarchy.ambient import FOLDED_FROM_POINTS

    spline = AmbientSpline(random_overlays(2, nlevels=2))
    lat = np.zeros(FOLDED_FROM_POINTS)
    lon = np.zeros(FOLDED_FROM_POINTS)
    for bad_lat, bad_lon, words in ((90.5, 0.0, "latitude"), (np.inf, 0.0, "latitude"), (0.0, -np.inf, "longitude")):
        la, lo = lat.copy(), lon.copy()
        la[-1], lo[-1] = bad_lat, bad_lon
        with pytest.raises(CoordinateError, match=words):
            spline.undulation(la, lo)
    np.testing.assert_array_equal(AmbientSpline([]).undulation(lat, lon), 0.0)


def test_latlon_kernel_counts_each_bad_coordinate_once():
    """The compiled batch counts invalid coordinates 4 points at a time: a batch whose
    length is not a multiple of 4 counts each bad point once (the last vector's spare
    lanes repeat the last point), NaN is not invalid, a longitude beyond the bound given is
    (and only then), and the good points' values are those of a batch without the bad
    ones."""
    spline = AmbientSpline(random_overlays(2, nlevels=2))
    rng = np.random.default_rng(7)
    for count in (4099, 4098, 4097):  # 1, 2 and 3 points in the last vector
        lat = rng.uniform(-80.0, 80.0, count)
        lon = rng.uniform(-180.0, 180.0, count)
        good, invalid = spline.index.undulation_latlon(lat, lon)
        assert invalid == 0
        bad = {0: (91.0, 0.0), 1000: (0.0, np.inf), count - 2: (-np.inf, 5.0), count - 1: (-90.5, -np.inf)}
        la, lo = lat.copy(), lon.copy()
        for at, (bad_lat, bad_lon) in bad.items():
            la[at], lo[at] = bad_lat, bad_lon
        la[7], lo[8] = np.nan, np.nan
        assert spline.index.undulation_latlon(la, lo)[1] == len(bad)
        lo[2000], lo[count - 3] = 1e6 + 0.5, -1e6  # beyond the bound, on it
        assert spline.index.undulation_latlon(la, lo)[1] == len(bad)
        assert spline.index.undulation_latlon(la, lo, 1e6)[1] == len(bad) + 1
        la, lo = lat.copy(), lon.copy()
        la[7], lo[8] = np.nan, np.nan
        values, invalid = spline.index.undulation_latlon(la, lo)
        assert invalid == 0 and np.isnan(values[7:9]).all()
        np.testing.assert_array_equal(np.delete(values, [7, 8]), np.delete(good, [7, 8]))
        assert np.abs(good).max() > 0.1


def threads_and_paths():
    """in_order False (sorted by cell) and True (as given), on one thread, two and all:
    the kernels' thread count is set while the loop's body runs and restored after."""
    from geoidspline._kernels import _clib

    threads = _clib.threads()
    try:
        for n in sorted({1, 2, threads}):
            _clib.set_threads(n)
            yield False
            yield True
    finally:
        _clib.set_threads(threads)


@pytest.mark.parametrize("order,h0,nlevels", [(4, 0.1, 2), (4, 0.05, 3), (6, 0.1, 2), (3, 0.1, 2)])
def test_latlon_batches_in_input_order_give_the_bits_of_sorted_ones(order, h0, nlevels, monkeypatch):
    """A batch evaluated in the order given (small tables, BrickIndex.IN_ORDER_MAX_BYTES)
    and the same batch sorted by cell give the same bits, and count the same invalid
    coordinates, on one thread and two: global and dense points, NaN, points where no
    brick lies (0), wrapped longitudes, the poles, and batches that are not a multiple of
    4 or of a task's 4,096 points; which path a batch takes follows the index's bytes."""
    from geoidspline.bspline import index as index_module

    # no level 0: the finer levels' patches leave most of the sphere without a brick
    spline = AmbientSpline(random_overlays(61, order=order, h0=h0, nlevels=nlevels + 1)[1:])
    idx = spline.index
    rng = np.random.default_rng(62)
    count = 3 * 4096 + 3
    lat = np.concatenate([np.degrees(np.arcsin(rng.uniform(-1, 1, count - 2000))), rng.uniform(40, 41, 2000)])
    lon = np.concatenate([rng.uniform(-540, 540, count - 2000), rng.uniform(10, 11, 2000)])
    lat[::89], lon[::97] = np.nan, np.nan
    lat[5], lat[6], lon[7] = 90.0, -90.0, -180.0
    want = spline.evaluate_points(directions(lat, lon))
    assert (want == 0.0).sum() > 1000 and np.nanmax(np.abs(want)) > 1.0  # holes (no brick) and values
    bad_lat, bad_lon = lat.copy(), lon.copy()
    bad_lat[[0, 4100, count - 1]] = [90.5, -np.inf, 1e300]
    bad_lon[[1, 8200, count - 2]] = [np.inf, 2e6, -1e6 - 1]
    for in_order in threads_and_paths():
        out = np.empty(count)
        assert _kernels.undulation_latlon(idx.spline, lat, lon, 3, out, 1e6, in_order=in_order) == 0
        np.testing.assert_array_equal(out, want)
        assert _kernels.undulation_latlon(idx.spline, bad_lat, bad_lon, 3, out, 1e6, in_order=in_order) == 6
        assert _kernels.undulation_latlon(idx.spline, bad_lat, bad_lon, 3, out, 3e6, in_order=in_order) == 4
    calls = []
    real = _kernels.undulation_latlon

    def spy(*args, **kwargs):
        calls.append(kwargs["in_order"])
        return real(*args, **kwargs)

    monkeypatch.setattr(_kernels, "undulation_latlon", spy)
    for limit in (idx.hot_bytes - 1, idx.hot_bytes):
        monkeypatch.setattr(index_module, "IN_ORDER_MAX_BYTES", limit)
        np.testing.assert_array_equal(idx.undulation_latlon(lat, lon)[0], want)
    assert calls == [False, True]


@pytest.mark.parametrize("order", [4, 6])
def test_bricks_prefetched_ahead_and_sparse_chunks_give_the_same_bits(order, monkeypatch):
    """Float64 tables beyond the caches (``PREFETCH_BRICKS_FROM_BYTES``, lowered here) give
    the kernels each brick's table size: a batch's chunks then prefetch the bricks ahead of
    their points (a dense global batch, hundreds of points a brick) or, with fewer than
    AHEAD_SPARSE points a brick (a sparse one), take the chain pipeline. Both give the bits
    of the plain evaluation, on one thread and two, with NaN among the points."""
    from geoidspline._kernels import _clib
    from geoidspline.bspline import index as index_module

    monkeypatch.setattr(index_module, "IN_ORDER_MAX_BYTES", -1)  # every batch sorted by cell
    levels = random_overlays(63, order=order, h0=0.05, nlevels=3)
    plain = AmbientSpline(levels).index
    monkeypatch.setattr(index_module, "PREFETCH_BRICKS_FROM_BYTES", 0)
    ahead = AmbientSpline(levels).index
    assert plain.fold_size is None and ahead.fold_size is not None
    # a brick's table ends where its furthest column run does: level 0's own tables lie
    # one after another, each up to the next one's start
    level0 = ahead.slots[ahead.slot_start[0]:ahead.slot_start[0] + ahead.slot_mask[0] + 1, 0]
    nb0 = int((level0 != -1).sum())
    assert nb0 > 10 and ahead.fold_size.shape == ahead.fold_base.shape
    np.testing.assert_array_equal(ahead.fold_size[:nb0 - 1], np.diff(ahead.fold_base[:nb0]))
    rng = np.random.default_rng(64)
    threads = _clib.threads()
    try:
        for count in (5000, 20 * 4096 + 1):  # about 13 points a finest brick; hundreds
            lat = np.degrees(np.arcsin(rng.uniform(-1, 1, count)))
            lon = rng.uniform(-180, 180, count)
            lat[::101] = np.nan
            want = plain.undulation_latlon(lat, lon)[0]
            assert np.isnan(want).sum() == len(lat[::101]) and np.nanmax(np.abs(want)) > 1.0
            for n in sorted({1, 2, threads}):
                _clib.set_threads(n)
                np.testing.assert_array_equal(ahead.undulation_latlon(lat, lon)[0], want)
    finally:
        _clib.set_threads(threads)


def test_points_near_the_edges_of_finer_bricks_end_where_the_descent_would():
    """A batch's points inside the finest-level brick where the last point's descent
    started (latlon_locate's box) skip the descent: where a finer level's bricks begin and
    end among dense points, and on the planes between bricks (the equator z = 0 and the
    prime meridian y = 0 exactly, -0.0 among them), every point gets the bits of the
    descent (evaluate_points), sorted by cell and in input order, on one thread and two."""
    rng = np.random.default_rng(66)
    order, h0 = 4, 0.1
    # level 0 about (1, 0, 0); level 1 only in bricks above y = 0 and z = 0, level 2 only
    # in bricks below y = 0 and above z = 0 (bricks of 16 cells: the planes through 0 part them)
    patches = [((1.0, 0.0, 0.0), 0.5), ((1.0, 0.15, 0.15), 0.1), ((1.0, -0.15, 0.15), 0.1)]
    levels = []
    for ell, (centre, radius) in enumerate(patches):
        h = h0 / 2**ell
        centre = np.asarray(centre) / np.linalg.norm(centre)
        idx = patch_keys(rng, h, order, centre, radius, keep=0.9)
        levels.append(LevelSpline.from_indices(ell, h, order, idx, rng.normal(scale=10.0 / 2**ell, size=len(idx))))
    spline = AmbientSpline(levels)
    index = spline.index
    count = 60_001
    lat = rng.uniform(-4.0, 4.0, count)  # +-0.07 about (1, 0, 0): the three levels' bricks meet
    lon = rng.uniform(-4.0, 4.0, count)
    lat[::7], lon[1::7] = 0.0, 0.0  # on the planes z = 0 and y = 0 between bricks
    lat[::21], lon[2::21] = -0.0, -0.0
    lat[3::11] = rng.choice([1e-300, -1e-300, 1e-15, -1e-15], len(lat[3::11]))
    f = directions(lat, lon)
    want = spline.evaluate_points(f)
    assert np.isfinite(want).all() and np.abs(want).max() > 1.0
    # the level each point's descent ends on: every level ends thousands of them
    ends = np.full(count, -1)
    for lev in range(index.inv_hs.size - 1, -1, -1):
        slots = index.slots[index.slot_start[lev]:index.slot_start[lev] + index.slot_mask[lev] + 1, 0]
        cells = np.floor(f * index.inv_hs[lev]).astype(np.int64) >> _kernels.BRICK_BITS
        here = (ends < 0) & np.isin(pack_keys(cells), slots[slots != -1])
        ends[here] = lev
    assert [int((ends == lev).sum()) > 2000 for lev in range(3)] == [True] * 3
    for in_order in threads_and_paths():
        out = np.empty(count)
        assert _kernels.undulation_latlon(index.spline, lat, lon, 3, out, 1e6, in_order=in_order) == 0
        np.testing.assert_array_equal(out, want)


def _sin_cos_degrees(degrees):
    """sin and cos of an angle in degrees (a float within +-180, taken exactly) to 50
    digits, as Decimals (the zeros exact): Taylor's series, 60 terms (pi^60/60! < 1e-52),
    pi from Newton's series of pi/6 = asin(1/2) (100 terms, each a quarter of the one
    before)."""
    from decimal import Decimal, localcontext

    with localcontext() as ctx:
        ctx.prec = 50
        if not hasattr(_sin_cos_degrees, "pi"):
            pi, term = Decimal(3), Decimal(3)
            for k in range(1, 100):
                term = term * (2 * k - 1) ** 2 / (8 * k * (2 * k + 1))
                pi += term
            _sin_cos_degrees.pi = pi
        x = Decimal(degrees) * _sin_cos_degrees.pi / 180
        terms, term = [], Decimal(1)
        for n in range(60):  # x^n / n!
            terms.append(term)
            term = term * x / (n + 1)
        sin = sum(terms[1::4]) - sum(terms[3::4])
        cos = sum(terms[0::4]) - sum(terms[2::4])
        return (Decimal(0) if degrees % 180 == 0 else sin), (Decimal(0) if degrees % 180 == 90 else cos)


def test_compiled_directions_are_the_sines_and_cosines_of_the_degrees_given():
    """Large batches compute directions with their own sin/cos of the angle in degrees (a
    table of whole degrees and short polynomials, no rounding of the angle in radians):
    each sine and cosine within 1.12e-16 of the true one (half a unit in the last place of
    the table's value and of the result), so z within that and x, y within 2.8e-16 (two
    such factors and the product's rounding); whole degrees exactly the correctly rounded
    sine and cosine (the axes exact: cos 90 is 0); any longitude wrapped."""
    rng = np.random.default_rng(41)
    n = 3000
    lat = np.degrees(np.arcsin(rng.uniform(-1, 1, n)))
    lon = rng.uniform(-180, 180, n)
    lat[:8] = [0, 0, 0, 0, 90, -90, 45, -45]
    lon[:8] = [0, 90, -180, -90, 0, 0, 135, -45]
    lat[8:16] = [0.5, -0.5, 89.5, 1.5, 0.25, -89.75, 1e-300, -0.0]  # halfway: rounded to even
    lon[8:16] = [179.5, -179.5, -0.5, 2.5, 179.999999, -180.0, 1e-300, -0.0]
    got = np.empty((n, 3))
    _kernels.unit_vectors(lat, lon, got)  # the compiled formula of every large batch
    true = np.array([[float(c1 * c2), float(c1 * s2), float(s1)] for (s1, c1), (s2, c2) in
                     zip(map(_sin_cos_degrees, lat), map(_sin_cos_degrees, lon))])  # rounded once
    error = np.abs(got - true).max(axis=0)
    assert error[0] <= 2.8e-16 and error[1] <= 2.8e-16 and error[2] <= 1.12e-16, error
    assert np.abs(np.linalg.norm(got, axis=1) - 1.0).max() <= 4.5e-16
    axes = [[1, 0, 0], [0, 1, 0], [-1, 0, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]]
    np.testing.assert_array_equal(got[:6], axes)
    assert np.signbit(got[15, 2]) and got[14, 2] == 1e-300 * (np.pi / 180)  # sin keeps a zero's sign

    whole = np.arange(-180.0, 180.0)
    for lat_w, lon_w, sin_col, cos_col in ((np.clip(whole, -90, 90), np.zeros_like(whole), 2, 0),
                                           (np.zeros_like(whole), whole, 1, 0)):
        out = np.empty((whole.size, 3))
        _kernels.unit_vectors(lat_w, lon_w, out)
        angle = lat_w if sin_col == 2 else lon_w
        want = np.array([[float(v) for v in _sin_cos_degrees(a)] for a in angle])  # correctly rounded
        np.testing.assert_array_equal(out[:, sin_col], want[:, 0])
        np.testing.assert_array_equal(out[:, cos_col], want[:, 1])

    wrapped = np.empty((n, 3))
    _kernels.unit_vectors(lat, lon + 360.0 * rng.integers(-3, 4, n), wrapped)
    assert np.abs(wrapped - got).max() <= 1e-13  # the wrap rounds the longitude, not the formula

    # no range check here: huge angles wrap inexactly (the first three to -184, -256 and
    # -1.2e285 degrees: taken as 180, never read outside the table), NaN stays NaN
    lat_huge = np.array([4.2850653715770296e16, 9.900395701806764e17, 7.929227585702643e300, 540.0, -900.0, -1e300,
                         1e300, np.inf, np.nan, 0.0])
    lon_huge = np.array([7.929227585702643e300, -4.2850653715770296e16, 9.900395701806764e17, -900.0, 540.0, 7e299,
                         np.nan, 0.0, 0.0, -np.inf])
    out = np.empty((lat_huge.size, 3))
    _kernels.unit_vectors(lat_huge, lon_huge, out)
    np.testing.assert_allclose(np.linalg.norm(out[:6], axis=1), 1.0, rtol=0, atol=4.5e-16)
    assert np.isnan(out[6:]).any(axis=1).all()


def test_dense_latlon_batches_equal_directions_then_points():
    """A dense regional batch (thousands of points per 5.6° sort bucket: the buckets are
    sorted by counting on the low bits of their cells' Morton codes) gives bitwise the values of evaluate_points
    at directions(), on one thread and two."""
    from geoidspline._kernels import _clib

    spline = AmbientSpline(random_overlays(51, nlevels=3))
    rng = np.random.default_rng(52)
    lat = rng.uniform(10.0, 12.5, 50_003)  # not a multiple of 4: the vector passes' last points
    lon = rng.uniform(-181.0, -178.0, 50_003)  # across the antimeridian
    lat[::97] = np.nan
    want = spline.evaluate_points(directions(lat, lon))
    threads = _clib.threads()
    try:
        for n in (1, 2):
            _clib.set_threads(n)
            np.testing.assert_array_equal(spline.undulation(lat, lon), want)
    finally:
        _clib.set_threads(threads)
    assert np.isnan(want[::97]).all() and np.isfinite(want[1::97]).all()


def test_a_pickled_index_evaluates_the_same():
    """The kernels' record holds this process's addresses: a pickled index rebuilds it."""
    import pickle

    spline = AmbientSpline(random_overlays(61, nlevels=2))
    rng = np.random.default_rng(62)
    points = unit_vectors(rng, 30_000)
    want = spline.evaluate_points(points, nderiv=2)
    copy = pickle.loads(pickle.dumps(spline.index))
    out = np.zeros((points.shape[0], 10))
    copy.add_to(points, out, nderiv=2)
    np.testing.assert_array_equal(out, want)
    with pytest.raises(TypeError, match="values"):
        _kernels.Spline.of(4, copy.inv_hs, copy.band_lo2, copy.band_hi2, copy.presence, copy.slots,
                           copy.slot_start, copy.slot_mask, copy.fold_base, copy.fold_cols, copy.own_base,
                           copy.own_cols, copy.values.astype(np.float32), copy.fold_offs, copy.fold_full,
                           copy.own_offs, copy.own_full)


def full_columns_by_definition(cols, order):
    """numpy reference of _kernels.full_columns: per column (run offset - first k), and per
    cell column of a brick the lz whose order² columns all hold k = lz .. lz + order - 1."""
    cells = 1 << _kernels.BRICK_BITS
    length = cols & ((1 << _kernels.COL_KBITS) - 1)
    k0 = (cols >> _kernels.COL_KBITS) & ((1 << _kernels.COL_KBITS) - 1)
    offs = np.where(length > 0, (cols >> _kernels.COL_SHIFT) - k0, 0)
    full = np.zeros((cols.shape[0], cells, cells), np.uint16)
    for lz in range(cells):
        holds = (length > 0) & (k0 <= lz) & (lz + order <= k0 + length)  # (B, side, side)
        every = np.ones((cols.shape[0], cells, cells), bool)
        for p in range(order):
            for q in range(order):
                every &= holds[:, p:p + cells, q:q + cells]
        full |= (every.astype(np.uint16) << lz)
    return offs, full


@pytest.mark.parametrize("order", [4, 6, 3])
def test_full_column_maps_follow_their_definition(order):
    index = AmbientSpline(random_overlays(71, order=order, nlevels=3)).index
    for cols, offs, full in ((index.fold_cols, index.fold_offs, index.fold_full),
                             (index.own_cols, index.own_offs, index.own_full)):
        want_offs, want_full = full_columns_by_definition(cols, order)
        np.testing.assert_array_equal(offs, want_offs)
        np.testing.assert_array_equal(full, want_full)
        offs16, full16 = _kernels.full_columns(cols, order, np.int16)  # the quantised tables' offsets
        assert offs16.dtype == np.int16
        np.testing.assert_array_equal(offs16, want_offs)
        np.testing.assert_array_equal(full16, want_full)
        assert 0 < np.count_nonzero(full) < full.size  # both paths occur


@pytest.mark.parametrize("order", [4, 6])
def test_full_columns_give_the_bits_of_decoded_columns(order):
    """The evaluation reads a cell's columns through the full-column map where it allows
    (no decoding), else decodes each column entry: with the maps emptied every point takes
    the decoding path, and every value, gradient and Hessian is bitwise the same, on and
    off the sphere and in latitude/longitude batches."""
    levels = random_overlays(72, order=order, nlevels=3)
    spline = AmbientSpline(levels)
    rng = np.random.default_rng(73)
    points = np.concatenate(list(point_sets(rng, levels, count=2000).values()))
    lat = np.degrees(np.arcsin(rng.uniform(-1, 1, 60_000)))
    lon = rng.uniform(-180, 180, 60_000)
    fast = [spline.evaluate_points(points, nderiv=d) for d in (0, 1, 2)] + [spline.undulation(lat, lon)]
    spline.index.fold_full[:] = 0
    spline.index.own_full[:] = 0
    decoded = [spline.evaluate_points(points, nderiv=d) for d in (0, 1, 2)] + [spline.undulation(lat, lon)]
    for a, b in zip(fast, decoded):
        np.testing.assert_array_equal(a, b)
    assert np.abs(fast[3]).max() > 1.0


@pytest.mark.parametrize("order", [4, 6])
def test_own_tables_from_keys_equal_those_from_brick_entries(order):
    """own_table_fill builds a row of bricks' own table straight from the keys: the same
    bricks, column entries and values as listing the (brick, coefficient) pairs first."""
    from geoidspline.bspline.index import _Slab, _brick_rows, _row_span

    side = (1 << _kernels.BRICK_BITS) + order - 1
    rows_seen = 0
    for lv in random_overlays(81, order=order, nlevels=3):
        for row in _brick_rows(lv, order):
            lo, hi = _row_span(lv, order, row)
            slab = _Slab(lv, order, row)
            if lo == hi:
                assert slab.brick_keys.size == 0
                continue
            want_base, want_cols, want_values = _kernels.own_table_row(slab.brick_start, slab.local, slab.coef_index,
                                                                       lv.coefficients, side)
            none = (np.empty(0, np.int64), np.empty(0, np.int64), np.zeros((0, side, side), np.int32), np.zeros(0))
            nb, total, written = _kernels.own_table_fill(lv.keys[lo:hi], lv.coefficients[lo:hi], order, row, *none)
            assert not written and nb > 0  # sizes only: nothing fits
            keys, base = np.empty(nb, np.int64), np.empty(nb, np.int64)
            cols, values = np.zeros((nb, side, side), np.int32), np.zeros(total)
            assert _kernels.own_table_fill(lv.keys[lo:hi], lv.coefficients[lo:hi], order, row, keys, base, cols,
                                           values) == (nb, total, True)
            np.testing.assert_array_equal(keys, slab.brick_keys)
            np.testing.assert_array_equal(base, want_base)
            np.testing.assert_array_equal(cols, want_cols)
            np.testing.assert_array_equal(values, want_values)
            rows_seen += nb > 0
    assert rows_seen >= 5


def _quantised_level(seed, order, step, spread_steps):
    """One level over the sphere whose coefficients are multiples of step / 4, as a store
    read back holds them (its tiles quantised with a fraction of the manifest's step).
    spread_steps "limits": every brick spans exactly 65,535 steps (its int16 values reach
    -32768 and +32767) around -2**30 steps."""
    rng = np.random.default_rng(seed)
    h = 0.15
    # "limits": the whole ball, no gaps in the runs (a gap holds 0, 2**30 steps away)
    limits = spread_steps == "limits"
    idx = patch_keys(rng, h, order, np.zeros(3), 1.0 + order * h, keep=1.0 if limits else 0.95, near_sphere=not limits)
    if limits:
        q = rng.choice(np.array([-32768, 32767, -1, 0, 1, 12345], np.int64), len(idx)) - 2**30
    elif spread_steps == "mixed":  # bricks beyond int16 (where x > 0.5) beside bricks within it
        q = rng.integers(-1000, 1000, len(idx)) + np.where(idx[:, 0] * h > 0.5, rng.integers(-10**6, 10**6, len(idx)), 0)
    else:
        q = rng.integers(-spread_steps, spread_steps, len(idx)).astype(np.int32)
    return LevelSpline.from_indices(0, h, order, idx, q * (step / 4))


def _assert_near(got, want, level, ulps=16):
    """got within ulps units in the last place of the level's largest coefficient (its
    derivatives: over h per order; columns: value, gradient, Hessian as add_to fills them)
    of want: how far a quantised table's full-column sums (w q summed, the brick's base
    added once) may round away from the decoder's coefficients summed."""
    scale = np.abs(level.coefficients).max() * np.array([1.0] + [1 / level.h] * 3 + [1 / level.h**2] * 6)
    bound = ulps * np.finfo(float).eps * (scale[: want.shape[1]] if want.ndim == 2 else scale[0])
    assert np.all(np.abs(got - want) <= bound), f"{np.max(np.abs(got - want) / bound):.3g} x the bound"


@pytest.mark.parametrize("order,spread_steps,wide", [(4, 1000, "none"), (6, 1000, "none"), (6, "limits", "none"),
                                                     (4, 10**6, "all"), (6, 10**6, "all"), (6, "mixed", "some"),
                                                     (4, "mixed", "some")])
def test_quantised_tables_give_the_values_of_float_tables(order, spread_steps, wide):
    """Tables holding a store's integers (int16 with a base per brick, or int32 in two
    int16 slots where a brick spans more than 65,535 steps; bricks spanning the whole
    int16 range around a base of -2**30 steps) give every value, gradient and Hessian as
    the float64 tables do, on and off the sphere and in latitude/longitude batches (sparse
    and dense points: both of the batch kernel's pipelines), in less memory (int16 column
    offsets too): bitwise through the decoding path, within 16 units in the last place of
    the largest coefficient through the full-column sums (below 1e-13 m for a geoid's
    +-110 m), and bitwise the same from every build of those sums (target clones, AVX2,
    AVX-512DQ, as far as the CPU has them)."""
    from geoidspline.bspline.index import BrickIndex

    step = 0.01
    level = _quantised_level(91, order, step, spread_steps)
    plain = BrickIndex([level], order)
    quantised = BrickIndex([level], order, value_step=step, quantise=True)
    assert plain.qvalues is None and quantised.qvalues.dtype == np.int16
    assert quantised.value_step == step / 4 and quantised.values.size == 0
    is_wide = quantised.qbase == _kernels.QBASE_WIDE
    assert {"none": not is_wide.any(), "all": is_wide.all(), "some": 0 < is_wide.mean() < 0.9}[wide]
    assert plain.own_offs.dtype == np.int32 and quantised.own_offs.dtype == np.int16
    assert quantised.fold_offs is quantised.own_offs
    np.testing.assert_array_equal(quantised.own_offs, plain.own_offs)
    # a value in one int16 slot, or two in a wide brick
    values_per_brick = np.diff(np.r_[plain.own_base, plain.values.size])
    assert quantised.qvalues.size == plain.values.size + values_per_brick[is_wide].sum()
    assert quantised.nbytes == (plain.nbytes - plain.values.nbytes + quantised.qvalues.nbytes
                                + quantised.qbase.nbytes - plain.own_offs.nbytes // 2)
    if spread_steps == "limits":  # the int16 values' extremes, around a large base
        assert quantised.qvalues.min() == -32768 and quantised.qvalues.max() == 32767
        assert quantised.qbase.min() < -2**29
    rng = np.random.default_rng(92)
    points = np.concatenate(list(point_sets(rng, [level], count=1500).values()))
    # global points (sparse: the kernel's chain pipeline) and a 1 degree box (dense)
    lat = np.concatenate([np.degrees(np.arcsin(rng.uniform(-1, 1, 50_000))), rng.uniform(40, 41, 20_000)])
    lon = np.concatenate([rng.uniform(-180, 180, 50_000), rng.uniform(10, 11, 20_000)])

    def results(index):
        out = []
        for nderiv in (0, 1, 2):
            values = np.zeros((points.shape[0], {0: 1, 1: 4, 2: 10}[nderiv]))
            index.add_to(points, values, nderiv)
            out.append(values)
        return out + [index.undulation_latlon(lat, lon)[0]]

    want = results(plain)
    assert np.abs(want[3]).max() > 1.0
    full = quantised.fold_full.copy()
    assert 0 < np.count_nonzero(full)
    previous = _kernels.quantised_sums_level()
    builds = []
    try:
        for build in (0, 1, 2):
            assert _kernels.quantised_sums_level(build) >= 0
            assert _kernels.quantised_sums_level() == min(build, _widest_sums_level())
            quantised.fold_full[:] = full
            builds.append(results(quantised))
            for got, expected in zip(builds[-1], want):
                _assert_near(got, expected, level)
            quantised.fold_full[:] = 0  # every point through the decoding path
            for got, expected in zip(results(quantised), want):
                np.testing.assert_array_equal(got, expected)
    finally:
        _kernels.quantised_sums_level(previous)
    for other in builds[1:]:
        for got, expected in zip(other, builds[0]):
            np.testing.assert_array_equal(got, expected)


def _widest_sums_level():
    """The widest build of the quantised sums this CPU runs (Linux's /proc/cpuinfo;
    elsewhere assumed none): 2 with AVX-512DQ and VL, 1 with AVX2, else 0."""
    try:
        with open("/proc/cpuinfo") as fh:
            flags = next((set(line.split()) for line in fh if line.startswith("flags")), set())
    except OSError:
        return 0
    if {"avx2", "avx512dq", "avx512vl"} <= flags:
        return 2
    return 1 if "avx2" in flags else 0


@pytest.mark.parametrize("mixed", [False, True])
def test_int16_bricks_hold_their_integers_about_their_middle(mixed):
    """quantise_table / quantise_mixed give back every value bitwise as (qbase + q) step,
    each int16 brick's q centred on 0 (from -(span + 1) // 2 to span // 2: the base is
    about the brick's mean, so the full-column sums round with the values, not with an
    offset of 32,768 steps), int32 bricks with base 0."""
    rng = np.random.default_rng(98)
    step = 0.001
    spans = [0, 1, 2, 999, 65_534, 65_535] + ([65_536, 10**6] if mixed else [])
    sizes = rng.integers(1, 300, len(spans))
    lows = rng.integers(-2**30, 2**30, len(spans))
    q_true = [lo + np.r_[0, span, rng.integers(0, span + 1, n)] for lo, span, n in zip(lows, spans, sizes)]
    values = np.concatenate(q_true).astype(np.float64) * step
    base = np.cumsum([0] + [len(q) for q in q_true[:-1]])
    if mixed:
        q, qbase, starts = _kernels.quantise_mixed(values, base, step)
    else:
        q, qbase = _kernels.quantise_table(values, base, step, np.int16)
        starts = base
    for b, (truth, span) in enumerate(zip(q_true, spans)):
        if qbase[b] == _kernels.QBASE_WIDE:
            assert span > 65_535
            held = q[starts[b]:starts[b] + 2 * truth.size].view(np.int32)
            np.testing.assert_array_equal(held, truth)
            continue
        held = q[starts[b]:starts[b] + truth.size].astype(np.int64)
        assert span <= 65_535
        np.testing.assert_array_equal((qbase[b] + held) * step, truth * step)
        assert held.min() == -((span + 1) // 2) and held.max() == span // 2


def test_tables_of_one_width_for_older_kernels(monkeypatch):
    """MIXED_WIDTHS off: int32 throughout once a brick spans more than int16 holds (the
    tables kernel libraries before int16 slots read), the same values."""
    from geoidspline.bspline import index as index_module

    level = _quantised_level(96, 6, 0.01, "mixed")
    mixed = index_module.BrickIndex([level], 6, value_step=0.01, quantise=True)
    monkeypatch.setattr(index_module, "MIXED_WIDTHS", False)
    uniform = index_module.BrickIndex([level], 6, value_step=0.01, quantise=True)
    assert mixed.qvalues.dtype == np.int16 and (mixed.qbase == _kernels.QBASE_WIDE).any()
    assert uniform.qvalues.dtype == np.int32 and (uniform.qbase == 0).all()
    points = unit_vectors(np.random.default_rng(97), 20_000)
    got = [np.zeros((points.shape[0], 4)) for _ in range(2)]
    mixed.add_to(points, got[0], 1)
    uniform.add_to(points, got[1], 1)
    _assert_near(got[0], got[1], level)  # int16 bricks sum about their base, int32 ones about 0
    assert np.abs(got[0][:, 0]).max() > 1.0


def test_tables_stay_float_unless_every_coefficient_is_a_multiple_of_the_step():
    """A value step the coefficients do not follow (or a folded index: its values are
    sums) leaves the float64 tables; a store read back states its step."""
    from geoidspline.bspline.index import BrickIndex

    level = _quantised_level(93, 4, 0.01, 1000)
    off = LevelSpline(0, level.h, 4, level.keys, level.coefficients + 1e-7)
    assert BrickIndex([off], 4, value_step=0.01, quantise=True).qvalues is None
    assert BrickIndex(random_overlays(94, nlevels=3), 4, value_step=0.01, quantise=True).qvalues is None
    assert BrickIndex([level], 4, value_step=0.01).qvalues is None  # small: float64 is faster


def test_a_store_read_back_states_its_value_step(small_store):
    import json

    from geoidspline.store.reader import TileStore

    step = json.loads((small_store.path / "manifest.json").read_text())["spline"]["value_step_m"]
    assert TileStore.open(small_store.path).spline.full.value_step == step


def test_own_tables_grow_beyond_their_first_capacity(monkeypatch):
    """The own tables start with room for what single-level stores need and grow when a
    row needs more: the same index either way, quantised or not."""
    from geoidspline.bspline import index as index_module

    levels = [_quantised_level(95, 4, 0.01, 1000)]
    want = [index_module.BrickIndex(levels, 4, value_step=0.01, quantise=q) for q in (False, True)]
    monkeypatch.setattr(index_module, "_BRICKS_PER_COEFFICIENT", 0.0)
    monkeypatch.setattr(index_module, "_VALUES_PER_COEFFICIENT", 0.0)
    got = [index_module.BrickIndex(levels, 4, value_step=0.01, quantise=q) for q in (False, True)]
    for a, b in zip(want, got):
        for name in ("slots", "own_base", "own_cols", "own_offs", "own_full", "values", "qvalues", "qbase"):
            np.testing.assert_array_equal(getattr(b, name), getattr(a, name), err_msg=name)
    assert got[1].qvalues is not None and got[0].values.size > 0
