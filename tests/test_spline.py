"""The B-spline kernels and the ambient spline: exact values and invariants."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.interpolate import BSpline

from geoidspline._kernels.common import bspline_weights as compiled_bspline_weights
from geoidspline.bspline.domain import supports_inside
from geoidspline.bspline.keys import pack_keys, unpack_keys
from geoidspline.bspline.level import LevelSpline
from geoidspline.errors import CoordinateError
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region


@pytest.mark.parametrize("order", [2, 3, 4, 5, 6])
@pytest.mark.parametrize("t", [0.0, 0.25, 0.6180339887, 0.999])
def test_weights_match_scipy_cardinal_bspline(order, t):
    out = np.zeros((3, order))
    nderiv = 2 if order >= 3 else 1
    compiled_bspline_weights(t, order, nderiv, out)
    element = BSpline.basis_element(np.arange(order + 1), extrapolate=False)
    x = t + order - 1 - np.arange(order)
    np.testing.assert_allclose(out[0], element(x), atol=1e-15)
    np.testing.assert_allclose(out[1], element.derivative(1)(x), atol=1e-14)
    if nderiv == 2:
        np.testing.assert_allclose(out[2], element.derivative(2)(x), atol=1e-13)
    # partition of unity and its derivatives
    assert out[0].sum() == pytest.approx(1.0, abs=1e-15)
    assert out[1].sum() == pytest.approx(0.0, abs=1e-14)


def test_cubic_weights_are_the_documented_formulas():
    t = 0.3
    out = np.zeros((3, 4))
    compiled_bspline_weights(t, 4, 0, out)
    expected = [(1 - t) ** 3 / 6, (3 * t**3 - 6 * t**2 + 4) / 6, (-3 * t**3 + 3 * t**2 + 3 * t + 1) / 6, t**3 / 6]
    np.testing.assert_allclose(out[0], expected, rtol=1e-14)


def test_key_packing_round_trip_and_order():
    idx = np.array([[-5, 3, 7], [0, 0, 0], [1000, -1000, 5], [-5, 3, 8]])
    keys = pack_keys(idx)
    np.testing.assert_array_equal(unpack_keys(keys), idx)
    # sorting keys sorts (i, j, k) lexicographically; z neighbours are consecutive keys
    assert keys[3] == keys[0] + 1
    assert np.all(np.argsort(keys) == np.lexsort(idx.T[::-1]))


def _full_block(h, order, lo=-1.3, hi=1.3):
    r = np.arange(int(np.floor(lo / h)) - order, int(np.ceil(hi / h)) + 1)
    return np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T


@pytest.mark.parametrize("order", [3, 4, 5])
def test_polynomial_reproduction_in_the_ambient_space(order):
    """Σ_k c_k B_k reproduces x (and constants) exactly: Marsden's identity."""
    h = 0.25
    idx = _full_block(h, order)
    # linear precision: x = Σ (k + order/2) h B_k(x)
    level = LevelSpline.from_indices(0, h, order, idx, (idx[:, 0] + order / 2.0) * h)
    points = np.random.default_rng(1).uniform(-1.0, 1.0, (200, 3))
    values = AmbientSpline([level]).evaluate_points(points, nderiv=2)
    np.testing.assert_allclose(values[:, 0], points[:, 0], atol=1e-13)
    np.testing.assert_allclose(values[:, 1], 1.0, atol=1e-12)
    np.testing.assert_allclose(values[:, 2:4], 0.0, atol=1e-12)
    np.testing.assert_allclose(values[:, 4:], 0.0, atol=1e-10)
    ones = LevelSpline.from_indices(0, h, order, idx, np.ones(len(idx)))
    np.testing.assert_allclose(AmbientSpline([ones]).evaluate_points(points), 1.0, atol=1e-14)


def test_derivatives_match_central_differences():
    """Analytic gradient and Hessian against central differences.

    The tolerance is the truncation error of the difference quotient: for a cubic
    spline |∂³S| ≤ 8 max|c| / h³ per axis (Σ|B'''| over the 4 weights = 1+3+3+1),
    so |error| ≤ ε²/6 · 8 max|c|/h³, plus rounding ~ 1e-15 max|S| / ε.
    """
    rng = np.random.default_rng(7)
    h = 0.2
    idx = _full_block(h, 4)
    coefs = rng.normal(size=len(idx))
    spline = AmbientSpline([LevelSpline.from_indices(0, h, 4, idx, coefs)])
    points = rng.uniform(-0.9, 0.9, (100, 3))
    eps = 1e-4
    analytic = spline.evaluate_points(points, nderiv=2)
    bound3 = 8 * np.abs(coefs).max() / h**3
    tol1 = eps**2 / 6 * bound3 + 1e-15 * 10 / eps
    hess_index = {(0, 0): 4, (1, 1): 5, (2, 2): 6, (0, 1): 7, (0, 2): 8, (1, 2): 9}
    for axis in range(3):
        step = np.zeros(3)
        step[axis] = eps
        plus = spline.evaluate_points(points + step, nderiv=1)
        minus = spline.evaluate_points(points - step, nderiv=1)
        np.testing.assert_allclose((plus[:, 0] - minus[:, 0]) / (2 * eps), analytic[:, 1 + axis], atol=tol1)
        # d/dx_axis of the gradient gives a Hessian column; its bound has one power of h less
        tol2 = eps**2 / 6 * bound3 * 8 / h + 1e-15 * 100 / eps
        for other in range(3):
            key = tuple(sorted((axis, other)))
            fd = (plus[:, 1 + other] - minus[:, 1 + other]) / (2 * eps)
            np.testing.assert_allclose(fd, analytic[:, hess_index[key]], atol=tol2)


def test_c2_across_cell_faces():
    """Value, gradient and Hessian of a random cubic spline do not jump at cell faces."""
    rng = np.random.default_rng(3)
    h = 0.2
    idx = _full_block(h, 4)
    spline = AmbientSpline([LevelSpline.from_indices(0, h, 4, idx, rng.normal(size=len(idx)))])
    base = rng.uniform(-0.8, 0.8, (50, 3))
    for axis in range(3):
        face = base.copy()
        face[:, axis] = np.round(face[:, axis] / h) * h  # on a cell face
        for delta in (1e-6, 1e-8):
            step = np.zeros(3)
            step[axis] = delta
            left = spline.evaluate_points(face - step, nderiv=2)
            right = spline.evaluate_points(face + step, nderiv=2)
            # continuous derivatives change by O(delta) across the face, not O(1)
            scale = np.array([1] + [1 / h] * 3 + [1 / h**2] * 6) * 10
            assert np.all(np.abs(right - left) <= scale * 2 * delta * 8 / h + 1e-9)


def test_level_spline_checks_its_invariants():
    with pytest.raises(ValueError, match="strictly increasing"):
        LevelSpline(0, 0.1, 4, np.array([3, 2]), np.array([1.0, 2.0]))
    with pytest.raises(ValueError, match="finite"):
        LevelSpline(0, 0.1, 4, np.array([1, 2]), np.array([1.0, np.nan]))
    with pytest.raises(ValueError, match="order"):
        LevelSpline(0, 0.1, 1, np.array([1]), np.array([1.0]))


def test_undulation_scalars_nan_and_range():
    h = 0.25
    idx = _full_block(h, 4)
    spline = AmbientSpline([LevelSpline.from_indices(0, h, 4, idx, np.full(len(idx), 2.5))])
    value = spline.undulation(10.0, 20.0)
    assert np.ndim(value) == 0 and value == pytest.approx(2.5, abs=1e-13)
    out = spline.undulation(np.array([[0.0, np.nan], [45.0, -90.0]]), 370.0)
    assert out.shape == (2, 2) and np.isnan(out[0, 1])
    np.testing.assert_allclose(out[~np.isnan(out)], 2.5, atol=1e-13)
    with pytest.raises(CoordinateError, match="latitude"):
        spline.undulation(90.5, 0.0)


def test_directions_are_unit_vectors_with_the_documented_convention():
    u = directions(np.array([0.0, 90.0, 0.0, -45.0]), np.array([0.0, 0.0, 90.0, 180.0]))
    np.testing.assert_allclose(u[0], [1, 0, 0], atol=1e-15)
    np.testing.assert_allclose(u[1], [0, 0, 1], atol=1e-15)
    np.testing.assert_allclose(u[2], [0, 1, 0], atol=1e-15)
    np.testing.assert_allclose(u[3], [-np.sqrt(0.5), 0, -np.sqrt(0.5)], atol=1e-15)


@settings(max_examples=60, deadline=None)
@given(south=st.floats(-85, 60), west=st.floats(-180, 179), height=st.floats(2, 25), width=st.floats(2, 60),
       log2_h=st.floats(-8, -3), order=st.integers(3, 6), seed=st.integers(0, 2**31))
def test_supports_inside_a_region_are_zero_outside_it(south, west, height, width, log2_h, order, seed):
    """Every B-spline ``supports_inside`` keeps is 0 at every point of the sphere outside
    the region: its support cube meets the sphere only inside (checked at points of the
    sphere drawn inside the cube), and it keeps the B-splines well inside the region."""
    region = Region(south, west, min(south + height, 90.0), west + width)
    h = 2.0 ** log2_h
    rng = np.random.default_rng(seed)
    # candidate B-splines around the region: those touching cells of random points near it
    lat = rng.uniform(max(-90.0, region.south - 5), min(90.0, region.north + 5), 400)
    lon = rng.uniform(region.west - 5, region.east + 5, 400)
    cells = np.floor(directions(lat, lon) / h).astype(np.int64)
    keys = np.unique(pack_keys(cells[:, None, :] - rng.integers(0, order, (400, 4, 3))))
    inside = supports_inside(keys, h, order, region)
    lo = unpack_keys(keys[inside]) * h
    for corner in lo[:50]:
        # points of the sphere inside the support cube [lo, lo + order h]³
        centre = corner + 0.5 * order * h
        probe = centre / np.linalg.norm(centre) + rng.uniform(-order * h, order * h, (4000, 3))
        probe /= np.linalg.norm(probe, axis=1)[:, None]
        in_cube = np.all((probe >= corner) & (probe <= corner + order * h), axis=1)
        plat = np.degrees(np.arcsin(probe[in_cube, 2]))
        plon = np.degrees(np.arctan2(probe[in_cube, 1], probe[in_cube, 0]))
        assert region.contains(plat, plon).all()
    # the B-spline around the region's centre is kept when the region is wider than
    # twice its support
    margin = np.degrees(2 * order * h)
    lat0, lon0 = 0.5 * (region.south + region.north), region.west + 0.5 * region.longitude_span
    widest = max(abs(region.south), abs(region.north))
    if region.north - region.south > 2 * margin and widest < 60 and \
            region.longitude_span * np.cos(np.radians(widest)) > 2 * margin:
        key = pack_keys(np.floor(directions(lat0, lon0) / h).astype(np.int64) - order // 2)
        assert supports_inside(np.array([key]), h, order, region)[0]
