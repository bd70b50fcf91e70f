"""The linearly independent hierarchical B-splines of thesis §5.3: the theorems, then the fit.

Configurations are small 3-D hierarchies on three kinds of domain: a box of cells (all of
R³ there, Kraft's setting), the cells meeting a plane (a flat manifold: one layer of
cells per level, like the sphere's shell but small) and the cells meeting the unit
sphere over a region (the geoid's domain). Sites for the theorems are random points
filling whole leaf cells (n³ + 3 per cell: generic points are unisolvent for the n³
polynomials of a cell), so a full column rank of the collocation matrix is linear
independence on Ω = ∪ ω^ℓ.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import scipy.sparse as sp
from hypothesis import HealthCheck, Phase, assume, given, settings
from hypothesis import strategies as st

from geoidspline.bspline.basis import children, refinement_weights
from geoidspline.bspline.evaluate import evaluate_levels
from geoidspline.bspline.keys import pack_keys, touching_cell_keys, unpack_keys
from geoidspline.bspline.level import LevelSpline
from geoidspline.fitting.driver import fit_nodes
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.hierarchy.hierarchical import (
    Domain,
    HierarchicalBasis,
    coarsen_cells,
    design_matrix,
    down,
    initial_basis,
    level_expansion,
    marked_functions,
    normal_matrix,
    refine,
    up,
    violations_53,
)
from geoidspline.sources.base import NodeSample
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region

PLANE_Z = 0.3183098861837907  # 1/π: on no grid line of any level (in units of h0 = 1)


def box_domain(nx, ny, nz, h0=1.0):
    """Every cell inside nx x ny x nz level-0 cells, at every level (R³)."""
    r = [np.arange(n) for n in (nx, ny, nz)]
    cells = np.array(np.meshgrid(*r, indexing="ij")).reshape(3, -1).T
    return Domain(np.unique(pack_keys(cells)), h0, meets=lambda lo, hi: np.ones(lo.shape[0], bool))


def plane_domain(nx, ny, h0=1.0):
    """Cells meeting the plane z = PLANE_Z h0 over nx x ny level-0 cells."""
    r = [np.arange(nx), np.arange(ny), np.arange(1)]
    cells = np.array(np.meshgrid(*r, indexing="ij")).reshape(3, -1).T
    z = PLANE_Z * h0
    return Domain(np.unique(pack_keys(cells)), h0, meets=lambda lo, hi: (lo[:, 2] <= z) & (hi[:, 2] >= z))


def leaf_points(basis, per_cell, rng):
    """Random points filling every leaf cell (per_cell each), and their leaf level."""
    pts, lvl = [], []
    for lv, leaves in enumerate(basis.leaves):
        if leaves.size == 0:
            continue
        cells = unpack_keys(leaves)
        p = (cells[:, None, :] + rng.uniform(0, 1, (cells.shape[0], per_cell, 3))) * basis.spacing(lv)
        pts.append(p.reshape(-1, 3))
        lvl.append(np.full(cells.shape[0] * per_cell, lv))
    return np.concatenate(pts), np.concatenate(lvl)


def random_hierarchy(domain, order, steps, rng, per_step=2):
    """A hierarchy refined ``steps`` times at random active B-splines of random levels."""
    basis = initial_basis(domain, order)
    for _ in range(steps):
        marked = [np.empty(0, np.int64)] * basis.levels
        for _ in range(per_step):
            lv = int(rng.integers(basis.levels))
            if basis.active[lv].size:
                pick = rng.choice(basis.active[lv], size=1)
                marked[lv] = np.union1d(marked[lv], pick)
        basis = refine(basis, marked)
    return basis


def scaled_gram(a):
    g = (a.T @ a).toarray()
    d = 1.0 / np.sqrt(np.diag(g))
    return g * d[:, None] * d[None, :]


def condition(g):
    ev = np.linalg.eigvalsh(g)
    return ev[-1] / max(ev[0], 1e-300)


# ---------------------------------------------------------------------------------
# the refinement relation, up and down


@pytest.mark.parametrize("order", range(2, 9))
def test_refinement_relation_is_exact(order):
    """B^ℓ_k = Σ_m 2^{-(n-1)d} Π binom(n, m_d) B^{ℓ+1}_{2k+m}, to 1e-12 (3-D, at random points)."""
    rng = np.random.default_rng(order)
    h = 0.37
    keys = np.unique(pack_keys(rng.integers(-5, 5, (4, 3))))
    x = (unpack_keys(keys)[rng.integers(keys.size, size=3000)] + rng.uniform(-1, order + 1, (3000, 3))) * h
    coarse = LevelSpline(0, h, order, keys, rng.normal(size=keys.size))
    child, parent, weight = children(keys, order)
    fine_keys, inverse = np.unique(child, return_inverse=True)
    fine = LevelSpline(1, h / 2, order, fine_keys,
                       np.bincount(inverse, weights=weight * coarse.coefficients[parent], minlength=fine_keys.size))
    np.testing.assert_allclose(evaluate_levels([fine], x, 2), evaluate_levels([coarse], x, 2), rtol=0, atol=1e-12 / h**2)
    # the 1-D weights are 2^-(n-1) binom(n, m): cubic (1, 4, 6, 4, 1) / 8, and sum to 2
    assert refinement_weights(order).sum() == pytest.approx(2.0)
    if order == 4:
        np.testing.assert_array_equal(refinement_weights(4), np.array([1, 4, 6, 4, 1]) / 8)


def test_query_folding_shares_the_one_refinement_relation():
    import geoidspline.bspline.index as index

    assert index.refinement_weights is refinement_weights


def test_up_and_down_follow_figures_5_2_and_5_3():
    k = pack_keys(np.array([[3, -2, 7]]))
    assert up(k, 4).size == 5**3
    np.testing.assert_array_equal(down(up(k, 4), 4), k)  # Figure 5.2: down(up(k)) = k
    # Figure 5.3: two B-splines two apart also span the one between them
    two = pack_keys(np.array([[0, 0, 0], [2, 0, 0]]))
    np.testing.assert_array_equal(unpack_keys(down(up(two, 4), 4))[:, 0], [0, 1, 2])


@settings(max_examples=30, deadline=None)
@given(order=st.integers(2, 6), seed=st.integers(0, 2**31))
def test_down_of_up_contains_and_up_of_down_is_contained(order, seed):
    rng = np.random.default_rng(seed)
    keys = np.unique(pack_keys(rng.integers(-4, 4, (int(rng.integers(1, 12)), 3))))
    assert np.all(np.isin(keys, down(up(keys, order), order)))
    fine = np.unique(pack_keys(rng.integers(-6, 6, (400, 3))))
    assert np.all(np.isin(up(down(fine, order), order), fine))


# ---------------------------------------------------------------------------------
# the theorems on random hierarchies


def _check_hierarchy(basis, rng):
    order = basis.order
    # requirement 5.3, brute force over the support boxes (physical coordinates)
    boxes = []
    for lv, keys in enumerate(basis.active):
        lo = unpack_keys(keys) * basis.spacing(lv)
        boxes.append((lo, lo + order * basis.spacing(lv)))
    for lv in range(basis.levels):
        for other in range(lv + 2, basis.levels):
            (a0, a1), (b0, b1) = boxes[lv], boxes[other]
            if a0.size and b0.size:
                overlap = np.all((a0[:, None] < b1[None] - 1e-12) & (b0[None] < a1[:, None] - 1e-12), axis=2)
                assert not overlap.any(), f"levels {lv} and {other} overlap"
    assert violations_53(basis.active, basis.domain, order) == 0
    pts, lvl = leaf_points(basis, order**3 + 3, rng)
    # the leaves do not overlap: each point is in the leaf it was drawn in, only
    np.testing.assert_array_equal(basis.leaf_level(pts), lvl)
    a = design_matrix(basis, pts)
    # on a leaf of level ℓ only levels ℓ and ℓ - 1 are non-zero (Theorem 5.6: C1 = 2)
    col_level = np.repeat(np.arange(basis.levels), [k.size for k in basis.active])
    coo = a.tocoo()
    step = lvl[coo.row] - col_level[coo.col]
    assert set(np.unique(step)) <= {0, 1}
    sums = np.asarray(a.sum(axis=1)).ravel()
    assert sums.max() <= 2.0 + 1e-12
    # Theorem 5.3: linearly independent on Ω, i.e. the collocation matrix has full column
    # rank. Singular values of A itself (squaring it into AᵀA would square its condition,
    # about 1e6 for order 6 on a few cells, into the reach of rounding); a dependent
    # column set would give a ratio near 1e-16.
    dense = a.toarray()
    sv = np.linalg.svd(dense / np.linalg.norm(dense, axis=0), compute_uv=False)
    assert sv[-1] > 1e-9 * sv[0], (basis.coefficient_count, sv[-1] / sv[0])
    # the assembled normal equations (per-level kernel + refinement relation) equal AᵀA
    values = rng.normal(size=pts.shape[0])
    matrix, rhs = normal_matrix(basis, [(pts[lvl == lv], values[lvl == lv]) for lv in range(basis.levels)])
    direct = (a.T @ a).toarray()
    # the upper triangle, diagonal included (the matrix is symmetric)
    np.testing.assert_allclose(matrix.toarray(), np.triu(direct), rtol=0, atol=1e-12 * np.abs(direct).max())
    np.testing.assert_allclose(rhs, a.T @ values, rtol=0, atol=1e-12 * np.abs(rhs).max())
    return pts, lvl, a


@settings(max_examples=10, deadline=None, derandomize=True, phases=(Phase.explicit, Phase.generate),
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(order=st.integers(3, 6), seed=st.integers(0, 2**31), steps=st.integers(1, 2), plane=st.booleans())
def test_random_hierarchies_satisfy_theorems_5_3_and_5_6(order, seed, steps, plane):
    """Random refinements (random active B-splines of random levels) of small domains:
    requirement 5.3, leaves that partition Ω, at most two levels on any leaf (C1 = 2),
    full column rank (Theorem 5.3), and the assembled normal equations equal AᵀA."""
    rng = np.random.default_rng(seed)
    if plane:
        domain = plane_domain(3, 2) if order <= 4 else plane_domain(2, 1)
    else:
        domain = box_domain(2, 1, 1) if order <= 4 else box_domain(1, 1, 1)
    basis = random_hierarchy(domain, order, steps, rng, per_step=1)
    assume(basis.coefficient_count <= 450)  # a small dense SVD
    assert basis.levels >= 2
    _check_hierarchy(basis, rng)


def test_sphere_hierarchy_covers_the_region_once_and_is_independent():
    """The geoid's domain: leaves partition the sphere over the region; Theorem 5.3 there."""
    rng = np.random.default_rng(3)
    region = Region(-8, -8, 8, 8)
    basis = initial_basis(Domain.sphere(0.25, region), 3)
    for lat, lon in ((0.0, -3.0), (2.0, 3.0)):
        basis = refine(basis, marked_functions(basis, directions(lat, lon)[None], radius=0.5))
    assert basis.levels == 3
    lat = rng.uniform(region.south, region.north, 5000)
    lon = rng.uniform(region.west, region.east, 5000)
    assert np.all(basis.leaf_level(directions(lat, lon)) >= 0)
    _check_hierarchy(basis, rng)


def _refined_patch(domain, order, levels, point):
    """Refine, level after level, the B-splines holding ``point``."""
    basis = initial_basis(domain, order)
    history = [basis]
    for _ in range(levels):
        basis = refine(basis, marked_functions(basis, np.asarray(point)[None]))
        history.append(basis)
    return history


def test_partition_of_unity_holds_on_one_level_and_is_lost_where_levels_overlap():
    """Thesis §5.3: 'the partition of unity gets lost in regions where two levels overlap'.
    Where only one level is non-zero and all its B-splines are active it holds; in the
    overlap the sum exceeds 1 (children of refined B-splines count once each, not with
    their weights), and never exceeds 2 (C1 = 2 of Theorem 5.6)."""
    rng = np.random.default_rng(5)
    basis = _refined_patch(box_domain(8, 8, 8), 4, 1, (4.1, 4.2, 3.9))[-1]
    pts, lvl = leaf_points(basis, 20, rng)
    a = design_matrix(basis, pts)
    sums = np.asarray(a.sum(axis=1)).ravel()
    col_level = np.repeat(np.arange(basis.levels), [k.size for k in basis.active])
    coo = a.tocoo()
    two_levels = np.zeros(pts.shape[0], bool)
    two_levels[coo.row[col_level[coo.col] != lvl[coo.row]]] = True
    one = ~two_levels
    assert one.sum() > 1000 and two_levels.sum() > 1000
    np.testing.assert_allclose(sums[one], 1.0, atol=1e-12)
    assert sums[two_levels].min() >= 1.0 - 1e-12
    assert sums[two_levels].max() > 1.05
    assert sums.max() <= 2.0


@pytest.mark.parametrize("plane", [False, True])
def test_hierarchical_space_reproduces_polynomials(plane):
    """Lemma 5.5a: the hierarchical quasi-interpolant reproduces Π_n on Ω, so the span of
    the selected B-splines contains them: a least-squares fit of a cubic is exact."""
    rng = np.random.default_rng(11)
    domain = plane_domain(4, 4) if plane else box_domain(3, 3, 2)
    basis = random_hierarchy(domain, 4, 2, rng)
    coef = rng.normal(size=(4, 4, 4))

    def poly(x):
        return np.einsum("ijk,mi,mj,mk->m", coef, *(np.power.outer(x[:, d], np.arange(4)) for d in range(3)))

    pts, lvl = leaf_points(basis, 4**3 + 6, rng)
    matrix, rhs = normal_matrix(basis, [(pts[lvl == lv], poly(pts[lvl == lv])) for lv in range(basis.levels)])
    upper = matrix.toarray()
    b = np.linalg.solve(upper + np.triu(upper, 1).T, rhs)
    check, _ = leaf_points(basis, 5, rng)
    s = AmbientSpline(basis.level_splines(b))
    np.testing.assert_allclose(s.evaluate_points(check), poly(check), rtol=0, atol=1e-8 * np.abs(poly(check)).max())


def _overlay_design(history, pts):
    """Collocation matrix of overlays with the same patches: level ℓ holds every B-spline
    of level ℓ touching the area refined to level ℓ or finer, on top of the coarser ones."""
    basis = history[-1]
    levels = []
    for lv in range(basis.levels):
        area = [coarsen_cells(basis.leaves[f], f - lv) for f in range(lv, basis.levels) if basis.leaves[f].size]
        keys = touching_cell_keys(np.unique(np.concatenate(area)), basis.order)
        levels.append(keys)
    stacked = HierarchicalBasis(basis.domain, basis.order, tuple(levels), basis.leaves)
    return design_matrix(stacked, pts)


def test_condition_stays_bounded_as_levels_are_added_and_grows_for_overlays():
    """Theorem 5.6: the hierarchical basis is stable with constants independent of the
    number of levels, so the (diagonally scaled) normal matrix keeps its condition
    number as levels are added. The same patches as stacked overlay levels are not a
    basis at all: their normal matrix is singular to rounding from the second level on."""
    rng = np.random.default_rng(2)
    history = _refined_patch(plane_domain(5, 5), 3, 3, (2.55, 2.45, PLANE_Z))
    hier, over = [], []
    for levels, basis in enumerate(history):
        pts, _ = leaf_points(basis, 3**3 + 3, rng)
        hier.append(condition(scaled_gram(design_matrix(basis, pts))))
        over.append(condition(scaled_gram(_overlay_design(history[:levels + 1], pts))))
    assert max(hier) < 10.0 * hier[0], hier  # bounded by the one-level basis's, whatever L
    assert over[0] == pytest.approx(hier[0], rel=1e-9)  # one level: the same basis
    assert all(o > 1e10 for o in over[2:]), over


def test_spline_is_c2_across_level_boundaries():
    """Value, gradient and Hessian are continuous across the faces between leaves of
    different levels (every B-spline is C², and so is their sum)."""
    rng = np.random.default_rng(8)
    basis = _refined_patch(box_domain(8, 8, 8), 4, 2, (4.1, 4.2, 3.9))[-1]
    s = AmbientSpline(basis.level_splines(rng.normal(size=basis.coefficient_count)))
    # faces x = const between a leaf of level ℓ and a leaf of level ℓ + 1
    faces = []
    for lv in range(basis.levels - 1):
        h = basis.spacing(lv)
        cells = unpack_keys(basis.leaves[lv])
        for step in (-1, 1):
            nb = cells.copy()
            nb[:, 0] += step
            finer = np.isin(pack_keys(nb), coarsen_cells(basis.leaves[lv + 1], 1))
            x = (cells[finer, 0] + (step > 0)) * h
            yz = (cells[finer, 1:] + rng.uniform(0.1, 0.9, (finer.sum(), 2))) * h
            faces.append(np.column_stack([x, yz]))
    faces = np.concatenate(faces)
    assert faces.shape[0] > 50
    eps = 1e-7
    left = s.evaluate_points(faces - [eps, 0, 0], nderiv=2)
    right = s.evaluate_points(faces + [eps, 0, 0], nderiv=2)
    jump = np.abs(right - left).max(axis=0)
    scale = np.abs(left).max(axis=0)
    assert np.all(jump < 1e-4 * scale), jump / scale


# ---------------------------------------------------------------------------------
# the fit


def _bumpy(lat, lon):
    p, l = np.radians(lat), np.radians(lon)
    return 20 * np.sin(2 * p) * np.cos(l) + 10 * np.cos(p) ** 2 * np.sin(2 * l) \
        + 2 * np.exp(-((lat - 5) ** 2 + (lon - 3) ** 2) / 4)


@pytest.fixture(scope="module")
def bumpy_sample():
    lat = np.arange(-70, 70.01, 0.5)
    lon = np.arange(-90, 90, 0.5)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    return NodeSample(lat, lon, _bumpy(lat2, lon2))


def test_hierarchical_fit_meets_the_tolerance_with_one_basis(bumpy_sample):
    region = Region(-15, -20, 20, 25)
    params = FitParameters(h0=0.2, tolerance_m=0.05, max_level=4, refinement="hierarchical")
    result = fit_nodes(bumpy_sample, region, params)
    assert result.converged and result.node_max_error_m <= 0.05
    basis = result.basis
    assert basis.levels >= 3 and violations_53(basis.active, basis.domain, basis.order) == 0
    # the store's levels are the basis: each active B-spline one coefficient of its level
    assert [len(lv) for lv in result.spline.levels] == [k.size for k in basis.active if k.size]
    assert result.spline.coefficient_count == basis.coefficient_count
    rng = np.random.default_rng(0)
    lat, lon = rng.uniform(-10, 15, 500), rng.uniform(-15, 20, 500)
    assert np.abs(result.spline.undulation(lat, lon) - _bumpy(lat, lon)).max() < 0.1


def test_local_problems_as_preconditioner_reach_the_whole_problems_fit():
    """Thesis §5.3.3's local problems, as the preconditioner of conjugate gradients on
    the whole problem, give the whole problem's least-squares fit (to the stopping
    rule, a hundredth of the tolerance RMS at the sites), from zero or from a start."""
    from geoidspline.fitting.hierarchical import SOLVE_FRACTION, solve_basis

    rng = np.random.default_rng(4)
    basis = random_hierarchy(plane_domain(10, 10, h0=0.125), 4, 2, rng, per_step=3)
    pts, lvl = leaf_points(basis, 25, rng)
    values = np.sin(3 * pts[:, 0]) * np.cos(2 * pts[:, 1]) + pts[:, 2]
    points = [pts[lvl == lv] for lv in range(basis.levels)]
    data = [values[lvl == lv] for lv in range(basis.levels)]
    params = FitParameters(h0=0.125, tile_size=0.5, tolerance_m=0.01)
    whole, one = solve_basis(basis, points, data, params)
    iterated, many = solve_basis(basis, points, data, params, force_tiles=True)
    assert one == 1 and many >= 8

    def spline_at_sites(coefficients):
        return AmbientSpline(basis.level_splines(coefficients)).evaluate_points(pts)

    assert np.abs(spline_at_sites(whole) - values).max() < 1e-3  # the fit itself is close
    difference = spline_at_sites(iterated - whole)
    assert np.sqrt(np.mean(difference ** 2)) <= SOLVE_FRACTION * params.tolerance_m
    assert np.abs(difference).max() < 10 * SOLVE_FRACTION * params.tolerance_m
    # started at the answer, nothing is left to do
    again, _ = solve_basis(basis, points, data, params, force_tiles=True, start=whole)
    assert np.abs(spline_at_sites(again - whole)).max() < SOLVE_FRACTION * params.tolerance_m


def test_a_step_beyond_the_memory_available_is_refused_before_it_is_built(monkeypatch):
    """The whole problem is held at once: a step that would not fit in the memory the
    system has left is refused with the numbers (a FitError), not killed by the OOM killer."""
    import geoidspline.fitting.hierarchical as fitting_hierarchical
    from geoidspline.errors import FitError

    assert issubclass(fitting_hierarchical.BasisTooLarge, FitError)
    rng = np.random.default_rng(4)
    basis = random_hierarchy(plane_domain(10, 10, h0=0.125), 4, 2, rng, per_step=3)
    pts, lvl = leaf_points(basis, 25, rng)
    points = [pts[lvl == lv] for lv in range(basis.levels)]
    data = [np.ones(p.shape[0]) for p in points]
    monkeypatch.setattr(fitting_hierarchical, "available_bytes",
                        lambda: 0.5 * basis.coefficient_count * fitting_hierarchical.BYTES_PER_UNKNOWN)
    with pytest.raises(fitting_hierarchical.BasisTooLarge, match=r"GB are available; overlays"):
        fitting_hierarchical.solve_basis(basis, points, data, FitParameters(h0=0.125), force_tiles=True)


def test_carry_over_keeps_the_spline_through_refinement():
    """The start of a refinement step is the previous step's spline in the new basis:
    a refined B-spline's coefficient passes to its children by the refinement relation,
    so where those children are all active the spline is unchanged."""
    from geoidspline.fitting.hierarchical import carry_over

    rng = np.random.default_rng(7)
    domain = plane_domain(8, 8, h0=0.125)
    coarse = initial_basis(domain, 4)
    coefficients = rng.normal(size=coarse.coefficient_count)
    marked = [coarse.active[0][rng.choice(coarse.active[0].size, 3, replace=False)]]
    fine = refine(coarse, [np.sort(m) for m in marked])
    assert fine.coefficient_count > coarse.coefficient_count
    start = carry_over(coarse, coefficients, fine)
    pts, _ = leaf_points(fine, 10, rng)
    before = AmbientSpline(coarse.level_splines(coefficients)).evaluate_points(pts)
    after = AmbientSpline(fine.level_splines(start)).evaluate_points(pts)
    np.testing.assert_allclose(after, before, atol=1e-12)


@pytest.mark.parametrize("refinement", ["overlays", "hierarchical"])
def test_stores_of_either_refinement_fit_query_update_verify_and_export(synthetic_gtx, tmp_path, analytic,
                                                                         refinement):
    """A store of either method is a normal store: geoid-fit --refinement, then
    geoid-query, a regional update (geoid-update), geoid-info --verify and geoid-export,
    with the same outcomes."""
    import json

    from click.testing import CliRunner

    from geoidspline.cli.export import main as export_main
    from geoidspline.cli.fit import main as fit_main
    from geoidspline.cli.info import main as info_main
    from geoidspline.cli.query import main as query_main
    from geoidspline.cli.update import main as update_main
    from geoidspline.sources.formats import read_grid
    from geoidspline.store.reader import TileStore

    store = tmp_path / "store"
    run = CliRunner().invoke(fit_main, [str(synthetic_gtx), "--store", str(store), "--region", "10", "20", "30", "40",
                                        "--h0", "0.2", "--max-level", "2", "--tolerance", "0.002",
                                        "--refinement", refinement, "--json", "-q"])
    assert run.exit_code == 0, run.output
    info = json.loads(run.stdout)
    manifest = json.loads((store / "manifest.json").read_text())
    assert manifest["fit"]["parameters"]["refinement"] == refinement
    assert manifest["fit"]["choices"]["reasons"]["refinement"] == "given"
    assert info["levels"][-1]["level"] >= 1 and info["node_max_error_m"] <= 0.002
    query = CliRunner().invoke(query_main, ["--store", str(store), "20.5", "30.25"])
    assert query.exit_code == 0
    assert float(query.stdout) == pytest.approx(analytic(20.5, 30.25), abs=0.005)
    before = TileStore.open(store).undulation(12.0, 22.0)
    update = CliRunner().invoke(update_main, [str(synthetic_gtx), "--store", str(store), "--region", "18", "28", "22",
                                              "32", "--blend-width", "200", "--json", "-q"])
    assert update.exit_code == 0, update.output
    assert json.loads((store / "manifest.json").read_text())["store_version"] == 2
    assert TileStore.open(store).undulation(12.0, 22.0) == pytest.approx(before, abs=1e-9)
    verify = CliRunner().invoke(info_main, ["--store", str(store), "--verify"])
    assert verify.exit_code == 0 and "every tile matches" in verify.stdout
    grid = tmp_path / "out.gtx"
    export = CliRunner().invoke(export_main, ["--store", str(store), "--out", str(grid), "--spacing", "1",
                                              "--region", "15", "25", "25", "35"])
    assert export.exit_code == 0, export.output
    exported = read_grid(grid)
    lat2, lon2 = np.meshgrid(exported.latitude, exported.longitude, indexing="ij")
    # the grid's nodes are 2° apart: between them the field is matched to a few cm
    np.testing.assert_allclose(exported.values, analytic(lat2, lon2), atol=0.03)
    np.testing.assert_allclose(exported.values, TileStore.open(store).undulation(lat2, lon2), atol=1e-6)


def test_refinement_is_checked_where_parameters_are(synthetic_gtx, tmp_path):
    """An unknown refinement, or the hierarchical basis quasi-interpolating a grid, is a
    user's mistake: one ERROR line, exit status 1 (click refuses an unknown name: 2)."""
    from click.testing import CliRunner

    from geoidspline.cli.fit import main as fit_main
    from geoidspline.errors import FitError

    with pytest.raises(FitError, match="refinement must be one of"):
        FitParameters(refinement="octree")
    FitParameters(refinement="hierarchical", method="interpolation")  # for exact sources (§5.3.1)
    args = [str(synthetic_gtx), "--store", str(tmp_path / "s"), "--region", "10", "20", "30", "40"]
    run = CliRunner().invoke(fit_main, args + ["--refinement", "hierarchical", "--method", "interpolation"])
    assert run.exit_code == 1 and run.stderr.startswith("ERROR:") and "exact everywhere" in run.stderr
    assert CliRunner().invoke(fit_main, args + ["--refinement", "octree"]).exit_code == 2


def test_normal_matrix_in_slices_is_the_one_of_a_whole_table(monkeypatch):
    """The normal equations are built a slice of the table and a slice of the product's
    columns at a time (bounded memory): slices of a few B-splines give the same matrix,
    the table's sums bit for bit, and the right-hand side bit for bit."""
    import geoidspline.hierarchy.hierarchical as hierarchy

    rng = np.random.default_rng(7)
    basis = random_hierarchy(plane_domain(8, 8, h0=0.125), 4, 2, rng, per_step=3)
    pts, lvl = leaf_points(basis, 20, rng)
    values = rng.normal(size=pts.shape[0])
    sites = [(pts[lvl == lv], values[lvl == lv]) for lv in range(basis.levels)]
    whole, whole_rhs = normal_matrix(basis, sites)
    level = basis.levels - 1
    x, _ = level_expansion(basis, level)
    table, table_rhs = hierarchy.level_normal_matrix(*sites[level], basis.spacing(level), basis.order, x)
    monkeypatch.setattr(hierarchy, "NORMAL_TABLE_BYTES", 8 * 7 ** 3 * 5)  # five B-splines a slice
    monkeypatch.setattr(hierarchy, "PRODUCT_COLUMNS", 7)
    sliced, sliced_rhs = normal_matrix(basis, sites)
    sliced_table, sliced_table_rhs = hierarchy.level_normal_matrix(*sites[level], basis.spacing(level),
                                                                   basis.order, x)
    assert x.size > 5 * 10 and basis.coefficient_count > 7 * 10  # many slices
    np.testing.assert_array_equal(sliced_table.toarray(), table.toarray())
    np.testing.assert_array_equal(sliced_table_rhs, table_rhs)
    np.testing.assert_array_equal(sliced_rhs, whole_rhs)
    np.testing.assert_allclose(sliced.toarray(), whole.toarray(), rtol=0, atol=1e-14 * abs(whole).max())
    assert sliced.nnz == whole.nnz


def _blocks_of_a_random_system(rng, n=60):
    a = rng.normal(size=(n, n)) * (rng.uniform(size=(n, n)) < 0.2)
    whole = a @ a.T + n * np.eye(n)
    blocks = [np.arange(0, 25), np.arange(20, 45), np.sort(rng.choice(n, 30, replace=False)), np.arange(59, 60)]
    return whole, blocks


def test_schwarz_preconditioner_solves_each_block_and_sums():
    """The packed Cholesky factors, held in float32 and applied in one call, give
    Σ_b R_bᵀ (L̃_b L̃_bᵀ)⁻¹ R_b r for the rounded factors L̃_b (numpy's triangular solves
    in float64 on the same rounded factors), which is S_bb⁻¹ to float32's rounding."""
    from scipy.linalg import cholesky, solve_triangular

    from geoidspline.fitting.hierarchical import SchwarzPreconditioner, SymmetricMatrix

    rng = np.random.default_rng(3)
    whole, blocks = _blocks_of_a_random_system(rng)
    n = whole.shape[0]
    system = SymmetricMatrix(sp.csr_matrix(np.triu(whole)))
    np.testing.assert_allclose(system @ np.arange(n, dtype=float), whole @ np.arange(n), rtol=1e-13)
    precondition = SchwarzPreconditioner(system, blocks)
    assert precondition.factors.dtype == np.float32
    r = rng.normal(size=n)
    rounded_factors, exact = np.zeros(n), np.zeros(n)
    for idx in blocks:
        factor = cholesky(whole[np.ix_(idx, idx)], lower=True).astype(np.float32).astype(np.float64)
        y = solve_triangular(factor, r[idx], lower=True)
        rounded_factors[idx] += solve_triangular(factor.T, y, lower=False)
        exact[idx] += np.linalg.solve(whole[np.ix_(idx, idx)], r[idx])
    z = precondition(r)
    np.testing.assert_allclose(z, rounded_factors, rtol=1e-12, atol=1e-15)
    assert 1e-9 < np.abs(z - exact).max() / np.abs(exact).max() < 1e-5  # float32's rounding, no more


def test_float32_factors_reach_the_solution_of_exact_local_solves():
    """Conjugate gradients preconditioned by the float32 factors stop within their
    tolerance of the solution, as with exact (float64) local solves, in about as many
    iterations, on a system whose blocks are ill-conditioned (a ridge of 1e-8)."""
    from geoidspline.fitting.hierarchical import SchwarzPreconditioner, SymmetricMatrix, conjugate_gradients

    rng = np.random.default_rng(11)
    n = 400
    # a 1-D chain of overlapping supports: banded and nearly singular, as B-splines' AᵀA
    sites = rng.uniform(0, 100, size=3000)
    a = np.maximum(0.0, 1.0 - np.abs(sites[:, None] / 0.25 - np.arange(n)[None, :]) / 2.0)
    whole = a.T @ a + 1e-8 * np.eye(n)
    system = SymmetricMatrix(sp.csr_matrix(np.triu(whole)))
    rhs = a.T @ np.sin(sites / 7.0)
    blocks = [np.arange(s, min(n, s + 60)) for s in range(0, n, 50)]

    def exact_local_solves(r):
        z = np.zeros_like(r)
        for idx in blocks:
            z[idx] += np.linalg.solve(whole[np.ix_(idx, idx)], r[idx])
        return z

    solution = np.linalg.solve(whole, rhs)
    tolerance = 1e-6
    x32, it32, reached32 = conjugate_gradients(system, rhs, SchwarzPreconditioner(system, blocks), np.zeros(n),
                                               tolerance)
    x64, it64, reached64 = conjugate_gradients(system, rhs, exact_local_solves, np.zeros(n), tolerance)
    assert reached32 <= tolerance and reached64 <= tolerance
    assert it64 > 5 and it32 <= it64 + 2
    for x in (x32, x64):  # the energy norm of the error: what the stopping rule bounds
        error = x - solution
        assert math.sqrt(error @ whole @ error) < 10 * tolerance
    np.testing.assert_allclose(a @ x32, a @ x64, atol=1e-6)  # the fitted values at the sites


def test_a_block_that_is_not_positive_definite_is_factorised_shifted():
    """Rounding can leave a principal block semidefinite: its factor is that of the block
    with a small relative shift of the diagonal (the preconditioner need not be exact)."""
    from geoidspline.fitting.hierarchical import _cholesky

    block = np.array([[4.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 3.0]])  # rank 2
    packed = np.empty(6)
    _cholesky(block, packed)
    factor = np.zeros((3, 3))
    factor[np.tril_indices(3)] = packed
    shifted = factor @ factor.T - block
    assert np.all(np.isfinite(packed)) and factor[1, 1] > 0
    np.testing.assert_allclose(shifted - np.diag(np.diag(shifted)), 0, atol=1e-12)
    assert 0 < shifted[0, 0] <= 1e-3 * 4.0
    np.testing.assert_allclose(np.diag(shifted), shifted[0, 0], rtol=1e-3)  # one shift for all rows
