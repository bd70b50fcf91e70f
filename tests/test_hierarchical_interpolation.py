"""The hierarchical quasi-interpolant of thesis §5.3.1 (Definition 5.4, Lemma 5.5), then the fit.

Lemma 5.5 on random hierarchical configurations (the small domains of
test_hierarchical.py: a box of cells, where Ω is all of R³, and the cells meeting a
plane, a flat manifold), for both local functionals: (a) polynomials of coordinate order
n are reproduced, (b, c) a spline of the space is its own quasi-interpolant (a
projector), and locality: a coefficient does not see the function beyond the cells its
functional and those of the coarser levels read. Then a fit of a small harmonic model.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st
from test_hierarchical import PLANE_Z, box_domain, leaf_points, plane_domain, random_hierarchy

from geoidspline.bspline.basis import bspline_weights
from geoidspline.bspline.keys import unpack_keys
from geoidspline.fitting.hierarchical_interpolation import (
    PATCH_MARGIN_ORDERS,
    PATCH_ORDERS,
    dual_functional,
    functional_cells,
    functional_norms,
    quasi_interpolate,
)
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.hierarchy.hierarchical import Domain, initial_basis, violations_53
from geoidspline.sphere.region import Region

THEOREM = settings(max_examples=8, deadline=None, derandomize=True, phases=(Phase.explicit, Phase.generate),
                   suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])


def _configuration(order, seed, steps, plane):
    rng = np.random.default_rng(seed)
    if plane:
        domain = plane_domain(4, 3) if order <= 4 else plane_domain(3, 2)
    else:
        domain = box_domain(2, 2, 1) if order <= 4 else box_domain(2, 1, 1)
    basis = random_hierarchy(domain, order, steps, rng, per_step=1)
    assert basis.levels >= 2
    return basis, rng


def _polynomial(order, rng, scale):
    """A random polynomial of coordinate order n (degree n - 1 in each coordinate)."""
    coef = rng.normal(size=(order,) * 3)

    def poly(x):
        powers = [np.power.outer(x[:, d] / scale, np.arange(order)) for d in range(3)]
        return np.einsum("ijk,mi,mj,mk->m", coef, *powers)

    return poly


def _tolerance(functional, order, plane):
    """Rounding, amplified by the functional's norm: the one-cell functional's is
    36.7 per axis for cubics at best and 56,000 at the end offsets for order 6
    (functional_norms); the patch's least squares is far better conditioned, but
    order 5-6 B-splines on the one or two cells of these small domains are not."""
    if functional == "patch":
        return 1e-10 * 10.0 ** max(0, order - 3)
    return 1e-13 * float(functional_norms(order).max()) ** 3 * (10 if plane else 1)


def test_one_cell_functional_is_dual_to_the_bsplines_of_its_cell():
    """λ_j(B_k) = δ_jk on a cell, for every order: D times the collocation matrix is I."""
    for order in range(2, 9):
        t, dual = dual_functional(order)
        np.testing.assert_allclose(dual @ bspline_weights(t, order, 0)[0], np.eye(order),
                                   atol=1e-14 * functional_norms(order).max())
    # the norms that make it unusable for fitting: cubic 36.7 per axis at the centre
    np.testing.assert_allclose(functional_norms(4), [146.0, 36.6667, 36.6667, 146.0], rtol=1e-4)


@THEOREM
@given(order=st.integers(3, 6), seed=st.integers(0, 2**31), steps=st.integers(1, 2), plane=st.booleans(),
       functional=st.sampled_from(["patch", "cell"]))
def test_lemma_5_5a_reproduces_polynomials_of_coordinate_order_n(order, seed, steps, plane, functional):
    """Q^L π = π on Ω^L for every π of coordinate order n, at random points of every leaf."""
    if functional == "cell" and order > 4:
        order = 4  # order 5-6 one-cell functionals at end offsets: norms 1e10-1e14 in 3-D
    basis, rng = _configuration(order, seed, steps, plane)
    extent = 3.0
    poly = _polynomial(order, rng, extent)
    coefs, _, _ = quasi_interpolate(basis, poly, functional, ridge=0.0)
    points, _ = leaf_points(basis, 30, rng)
    spline = AmbientSpline(basis.level_splines(coefs))
    truth = poly(points)
    error = np.abs(spline.evaluate_points(points) - truth).max()
    assert error <= _tolerance(functional, order, plane) * np.abs(truth).max(), (basis.coefficient_count, error)


@THEOREM
@given(order=st.integers(3, 6), seed=st.integers(0, 2**31), steps=st.integers(1, 2), plane=st.booleans(),
       functional=st.sampled_from(["patch", "cell"]))
def test_lemma_5_5bc_is_a_projector_onto_the_hierarchical_space(order, seed, steps, plane, functional):
    """Q^ℓ_k S = b^ℓ_k for S = Σ b B in the space (so Q^L Q^L G = Q^L G); with S one
    B-spline: Q^ℓ_k B^ℓ̃_m = δ."""
    if functional == "cell" and order > 4:
        order = 4
    basis, rng = _configuration(order, seed, steps, plane)
    # coefficients are recovered to rounding times the conditioning of the B-splines on
    # the leaves they reach (a patch's Cholesky is used down to rcond PATCH_RCOND = 1e-9:
    # eps / rcond ~ 1e-7); order 5-6 B-splines reaching into one corner cell of these
    # small domains are determined to ~1e-5 (their values on Ω to ~1e-8)
    if functional == "cell":
        atol = _tolerance(functional, order, plane) * 10
    else:
        atol = 1e-6 if order <= 4 else 1e-3
    points, _ = leaf_points(basis, 20, rng)
    b = rng.normal(size=basis.coefficient_count)
    spline = AmbientSpline(basis.level_splines(b))
    coefs, _, _ = quasi_interpolate(basis, spline.evaluate_points, functional, ridge=0.0)
    np.testing.assert_allclose(coefs, b, rtol=0, atol=atol)
    again = AmbientSpline(basis.level_splines(coefs)).evaluate_points(points)
    truth = spline.evaluate_points(points)
    assert np.abs(again - truth).max() <= _tolerance(functional, order, plane) * 10 * np.abs(truth).max()
    # one B-spline of the finest level
    unit = np.zeros(basis.coefficient_count)
    m = basis.offsets()[-2] + int(rng.integers(basis.active[-1].size))
    unit[m] = 1.0
    single = AmbientSpline(basis.level_splines(unit))
    coefs, _, _ = quasi_interpolate(basis, single.evaluate_points, functional, ridge=0.0)
    np.testing.assert_allclose(coefs, unit, rtol=0, atol=atol)


def _reach(basis, functional):
    """Per level, how far (unit-sphere lengths, per axis) from a B-spline's support
    centre its coefficient can read the function: its own functional (one cell of the
    support, or the patch grown by n/2 cells), and through the residual every coarser
    B-spline non-zero there, with its own reach."""
    n = basis.order
    grow = max(n // 2, math.ceil(PATCH_MARGIN_ORDERS * n))
    own = (PATCH_ORDERS * n + grow + 1) if functional == "patch" else n / 2.0
    reach = []
    for lv in range(basis.levels):
        h = basis.spacing(lv)
        below = reach[-1] + n / 2.0 * basis.spacing(lv - 1) if lv else 0.0
        reach.append(own * h + below)
    return reach


@pytest.mark.parametrize("functional", ["patch", "cell"])
def test_coefficients_are_local(functional):
    """Changing G beyond a B-spline's reach (its functional's cells and the coarser
    levels' before it) leaves its coefficient bitwise unchanged; those whose functional
    reads the change do change."""
    rng = np.random.default_rng(21)
    basis = random_hierarchy(plane_domain(24, 3), 4, 2, rng, per_step=3)
    assert basis.levels >= 3

    def smooth(x):
        return np.sin(0.7 * x[:, 0]) + np.cos(0.5 * x[:, 1]) * (1 + x[:, 2])

    cut = 18.0  # G changes only where x > cut (h0 = 1: 24 cells across)

    def changed(x):
        return smooth(x) + np.where(x[:, 0] > cut, 1.0 + x[:, 1] ** 2, 0.0)

    before, _, _ = quasi_interpolate(basis, smooth, functional, ridge=0.0)
    after, _, _ = quasi_interpolate(basis, changed, functional, ridge=0.0)
    reach = _reach(basis, functional)
    at = basis.offsets()
    untouched = touched = 0
    for lv, keys in enumerate(basis.active):
        centre = (unpack_keys(keys)[:, 0] + basis.order / 2.0) * basis.spacing(lv)
        far = centre + reach[lv] < cut
        np.testing.assert_array_equal(after[at[lv]:at[lv + 1]][far], before[at[lv]:at[lv + 1]][far])
        untouched += int(far.sum())
        touched += int(np.sum(after[at[lv]:at[lv + 1]][~far] != before[at[lv]:at[lv + 1]][~far]))
    assert untouched > 50 and touched > 50, (untouched, touched)


def test_one_cell_functional_reads_the_central_leaf_of_the_support():
    rng = np.random.default_rng(2)
    basis = random_hierarchy(box_domain(3, 3, 2), 4, 1, rng)
    for lv in range(basis.levels):
        cells, offsets = functional_cells(basis, lv)
        assert np.isin(cells, basis.leaves[lv]).all()
        assert np.all((offsets >= 0) & (offsets < 4))
    # in a box every support cell is a leaf of level 0 away from the refined part: the centre
    cells, offsets = functional_cells(initial_basis(box_domain(6, 6, 6), 4), 0)
    inner = np.all((unpack_keys(cells) >= 1) & (unpack_keys(cells) <= 4), axis=1)
    assert np.all(np.isin(offsets[inner], [1, 2]))


def test_thin_basis_gives_up_reproduction_on_the_manifold():
    """Why the quasi-interpolant uses the thesis's Ω basis: on the thin basis (two
    B-splines across the plane where a cubic has four non-zero) even the constant 1 is
    not reproduced on the plane, on the Ω basis it is."""
    rng = np.random.default_rng(6)
    cells = plane_domain(5, 5)
    pts = np.column_stack([rng.uniform(1, 4, 400), rng.uniform(1, 4, 400), np.full(400, PLANE_Z)])
    errors = {}
    for shell in (None, 1.0):
        domain = Domain(cells.root, cells.h0, meets=cells.meets, shell=shell)
        basis = initial_basis(domain, 4)
        coefs, _, _ = quasi_interpolate(basis, lambda x: np.ones(x.shape[0]), ridge=0.0)
        errors[shell] = np.abs(AmbientSpline(basis.level_splines(coefs)).evaluate_points(pts) - 1.0).max()
    assert errors[None] < 1e-10 and errors[1.0] > 1e-2, errors


# ---------------------------------------------------------------------------------
# the fit


def test_fit_of_a_model_reaches_the_tolerance_by_quasi_interpolation(toy24):
    """geoid-fit MODEL --method interpolation --refinement hierarchical, as a library call:
    the tolerance holds at every node and about as well between them, over a basis that
    satisfies requirement 5.3, with no linear solve of more than a patch."""
    from geoidspline.fitting.check_points import check_points
    from geoidspline.fitting.driver import fit_source

    region = Region(10, 10, 30, 40)
    params = FitParameters(h0=0.1, tolerance_m=0.02, max_level=4, method="interpolation",
                           refinement="hierarchical", sample_spacing_deg=0.25)
    result = fit_source(toy24, region, params)
    assert result.converged and result.node_max_error_m <= 0.02
    assert len(result.levels) >= 2 and result.levels[0].max_error_m > 0.02  # it refined
    basis = result.basis
    assert violations_53(basis.active, basis.domain, basis.order) == 0
    assert basis.domain.shell is None and all(r.blocks_solved == 0 for r in result.levels)
    check = check_points(toy24, region, count=3000, seed=3)
    between = np.abs(check.truth - result.spline.undulation(check.latitude, check.longitude)).max()
    assert between < 0.04


def test_cli_fits_a_model_by_hierarchical_quasi_interpolation(toy24, tmp_path):
    from click.testing import CliRunner
    from test_interpolation import _write_gfc

    from geoidspline.cli.fit import main as fit_main

    model = _write_gfc(tmp_path / "toy24.gfc", toy24.model)
    run = CliRunner().invoke(fit_main, [str(model), "--preset", "generic", "--method", "interpolation",
                                        "--refinement", "hierarchical", "--region", "10", "10", "30", "40",
                                        "--h0", "0.1", "--max-level", "4", "--sample-spacing", "0.25",
                                        "--tolerance", "0.02", "--store", str(tmp_path / "s"), "--json", "-q"])
    assert run.exit_code == 0, run.output
    info = json.loads(run.stdout)
    assert info["converged"] and info["node_max_error_m"] <= 0.02 and math.isfinite(info["max_error_m"])
    assert info["max_error_m"] < 0.04
