"""Quasi-interpolation of exact sources: prefilter algebra, kernels, convergence, poles."""

import math

import numpy as np
import pytest

from geoidspline.bspline.basis import centred_bspline_samples
from geoidspline.bspline.domain import active_cells
from geoidspline.bspline.keys import AXIS_STEPS, pack_keys, unpack_keys
from geoidspline.bspline.keys import touching_keys as _touching_keys
from geoidspline.bspline.level import LevelSpline
from geoidspline.errors import FitError
from geoidspline.fitting.check_points import check_points
from geoidspline.fitting.driver import fit_source
from geoidspline.fitting.interpolation import interpolate_level, prefilter_taps, sample_band
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.sphere.region import GLOBAL, Region


@pytest.mark.parametrize("order", [3, 4, 5, 6])
@pytest.mark.parametrize("terms", [0, 1, 4, 8])
def test_prefilter_inverts_the_symbol_up_to_the_truncation(order, terms):
    """taps * s = delta - (1 - s)^(J+1) as Laurent polynomials, and the taps sum to 1."""
    s = centred_bspline_samples(order)
    taps = prefilter_taps(order, terms)
    assert taps.size == 2 * terms * (s.size // 2) + 1
    assert math.isclose(taps.sum(), 1.0, rel_tol=0, abs_tol=1e-13)
    one_minus_s = -s
    one_minus_s[s.size // 2] += 1.0
    remainder = np.array([1.0])
    for _ in range(terms + 1):
        remainder = np.convolve(remainder, one_minus_s)
    product = np.convolve(taps, s)
    delta = np.zeros(product.size)
    delta[product.size // 2] = 1.0
    np.testing.assert_allclose(product, delta - remainder, rtol=0, atol=1e-13)


def test_centred_samples_are_the_known_ones():
    np.testing.assert_allclose(centred_bspline_samples(4), [1 / 6, 4 / 6, 1 / 6], rtol=1e-14)
    np.testing.assert_allclose(centred_bspline_samples(3), [1 / 8, 6 / 8, 1 / 8], rtol=1e-14)
    np.testing.assert_allclose(centred_bspline_samples(6), np.array([1, 26, 66, 26, 1]) / 120, rtol=1e-14)


def test_filter_axis_equals_a_dense_correlation():
    from scipy.ndimage import correlate1d

    from geoidspline._kernels.interpolation import filter_axis

    rng = np.random.default_rng(3)
    side, half = 14, 4
    cube = rng.normal(size=(side, side, side))
    taps = rng.normal(size=2 * half + 1)
    idx = np.stack(np.meshgrid(*[np.arange(-5, side - 5)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    keys = pack_keys(idx)
    order = np.argsort(keys)
    in_keys, in_values = keys[order], cube.reshape(-1)[order]
    for axis, step in enumerate(AXIS_STEPS):
        expected = correlate1d(cube, taps, axis=axis, mode="constant")
        inner = np.all((idx >= -5 + half) & (idx < side - 5 - half), axis=1)
        out_keys = np.sort(keys[inner])
        out = np.empty(out_keys.size)
        filter_axis(in_keys, in_values, out_keys, step, taps, out)
        where = unpack_keys(out_keys) + 5
        np.testing.assert_allclose(out, expected[where[:, 0], where[:, 1], where[:, 2]], rtol=1e-12, atol=1e-12)


def test_band_lookup_is_exact_to_the_lagrange_error_across_the_poles(toy24):
    """6x6 Lagrange lookups on the padded band equal the exact synthesis, also within a
    lattice step of either pole (rows reflected half a turn away) and across ±180."""
    step = 0.25
    lookup, band = sample_band(toy24, -90.0, 90.0, step)
    assert band.latitude[0] == -90.0 and band.latitude[-1] == 90.0
    rng = np.random.default_rng(5)
    lat = np.concatenate([rng.uniform(-90, 90, 500), rng.uniform(89.6, 90, 100), rng.uniform(-90, -89.6, 100),
                          [90.0, -90.0]])
    lon = np.concatenate([rng.uniform(-540, 540, 700), [17.0, -123.0]])
    got = np.empty(lat.size)
    lookup.at(lat, lon, got)
    # degree 24 at 0.25 deg: k delta = 0.105, Lagrange-6 error ~ (k delta)^6 / 6! * |N| ~ 1e-9 * |N|
    np.testing.assert_allclose(got, toy24.undulation(lat, lon), rtol=0, atol=1e-6)


def test_spline_interpolates_the_source_at_the_bspline_centres(toy24):
    """With many prefilter terms the quasi-interpolant is the interpolating spline: at
    B-spline centres near the sphere it equals the radially constant extension."""
    h, order = 0.02, 4
    region = Region(10, 10, 30, 40)
    keys = _touching_keys(active_cells(h, region), order)
    coefs, _, _ = interpolate_level(toy24, keys, h, order, spacing_deg=0.05, terms=16)
    spline = AmbientSpline([LevelSpline(0, h, order, keys, coefs)])
    centres = (unpack_keys(keys) + order / 2.0) * h
    radius = np.linalg.norm(centres, axis=1)
    lat = np.degrees(np.arcsin(centres[:, 2] / radius))
    lon = np.degrees(np.arctan2(centres[:, 1], centres[:, 0]))
    inner = (np.abs(radius - 1) < 0.3 * h) & Region(14, 14, 26, 36).contains(lat, lon)
    assert inner.sum() > 100
    values = spline.evaluate_points(centres[inner])
    # remainder ((1 - cos kh)/3)^17 with kh <= 0.5 and Lagrange error at 0.05 deg: << 1e-8 m
    np.testing.assert_allclose(values, toy24.undulation(lat[inner], lon[inner]), rtol=0, atol=1e-8)


@pytest.mark.parametrize("order, rate", [(4, 3.7), (6, 5.6)])
def test_error_converges_at_the_spline_order(toy24, order, rate):
    """Halving h divides the error by about 2^order (cubic 16, quintic 64)."""
    region = Region(10, 10, 30, 40)
    check = check_points(toy24, region, count=2000, seed=1)
    errors = []
    for h in (0.04, 0.02):
        params = FitParameters(h0=h, order=order, max_level=0, tolerance_m=1.0, method="interpolation")
        result = fit_source(toy24, region, params)
        errors.append(np.abs(check.truth - result.spline.undulation(check.latitude, check.longitude)).max())
    assert math.log2(errors[0] / errors[1]) > rate


def test_global_fit_has_no_pole_artefact_and_stops_at_the_tolerance(toy24):
    """A global cubic fit: the polar caps are as good as the rest, the node statistics
    of the result are honest (checked again at random points), overlays follow."""
    params = FitParameters(h0=0.04, order=4, max_level=0, tolerance_m=1.0, method="interpolation")
    result = fit_source(toy24, GLOBAL, params)
    assert result.converged and len(result.levels) == 1
    check = check_points(toy24, GLOBAL, count=5000, seed=2)
    err = np.abs(check.truth - result.spline.undulation(check.latitude, check.longitude))
    rng = np.random.default_rng(4)
    lat = np.concatenate([[90.0, -90.0], rng.uniform(89, 90, 200), rng.uniform(-90, -89, 200)])
    lon = np.concatenate([[0.0, 0.0], rng.uniform(-180, 180, 400)])
    pole_err = np.abs(toy24.undulation(lat, lon) - result.spline.undulation(lat, lon))
    assert err.max() < 0.05 and pole_err.max() <= err.max()
    assert abs(result.node_max_error_m - err.max()) < 0.5 * err.max()
    # a tolerance below the level's error adds least-squares overlays where it is violated
    strict = FitParameters(h0=0.04, order=4, max_level=1, tolerance_m=0.5 * err.max(), method="interpolation")
    refined = fit_source(toy24, Region(10, 10, 30, 40), strict)
    assert len(refined.levels) == 2 and refined.levels[1].coefficients > 0
    assert refined.levels[1].max_error_m < refined.levels[0].max_error_m


def test_interpolation_refuses_a_grid_source_and_unknown_methods():
    from geoidspline.sources.base import Provenance
    from geoidspline.sources.grid import GeoidGrid

    with pytest.raises(FitError, match="fit method must be one of"):
        FitParameters(method="kriging")
    lat = np.arange(-90, 90.1, 30.0)
    lon = np.arange(-180, 180, 30.0)
    grid = GeoidGrid(lat, lon, np.zeros((lat.size, lon.size)), Provenance(source="flat.gtx"))
    with pytest.raises(FitError, match="exact everywhere"):
        fit_source(grid, GLOBAL, FitParameters(method="interpolation"))


def _write_gfc(path, model):
    lines = ["synthetic model for geoidspline.fitting.interpolation", "begin_of_head ======",
             f"modelname {model.name}", f"earth_gravity_constant {model.gm!r}", f"radius {model.radius!r}",
             f"max_degree {model.max_degree}", "norm fully_normalized", "tide_system tide_free", "errors no",
             "key n m C S", "end_of_head ======"]
    for n in range(model.max_degree + 1):
        for m in range(n + 1):
            lines.append(f"gfc {n} {m} {model.C[n, m]:.15e} {model.S[n, m]:.15e}")
    path.write_text("\n".join(lines) + "\n")
    return path


def test_cli_fits_a_model_by_interpolation_and_refuses_a_grid(toy24, tmp_path):
    import json

    from click.testing import CliRunner

    from geoidspline.cli.fit import main as fit_main
    from geoidspline.cli.info import main as info_main
    from geoidspline.sources.base import Provenance
    from geoidspline.sources.formats import write_gtx
    from geoidspline.sources.grid import GeoidGrid

    model = _write_gfc(tmp_path / "toy24.gfc", toy24.model)
    store = tmp_path / "store"
    run = CliRunner().invoke(fit_main, [str(model), "--preset", "generic", "--method", "interpolation",
                                        "--region", "10", "10", "30", "40", "--h0", "0.02", "--max-level", "0",
                                        "--tolerance", "0.005", "--out", str(store), "--json", "-q"])
    assert run.exit_code == 0, run.output
    info = json.loads(run.stdout)
    assert info["converged"] and info["node_max_error_m"] <= 0.005 and info["max_error_m"] < 0.005
    check = CliRunner().invoke(info_main, [str(store), "--check-against", str(model), "--points", "3000", "--json"])
    assert check.exit_code == 0, check.output
    assert json.loads(check.stdout)["check_against"]["max_error_m"] < 0.005

    lat = np.arange(-90, 90.1, 30.0)
    lon = np.arange(-180, 180, 30.0)
    gtx = tmp_path / "flat.gtx"
    write_gtx(gtx, GeoidGrid(lat, lon, np.zeros((lat.size, lon.size)), Provenance(source="flat")))
    refused = CliRunner().invoke(fit_main, [str(gtx), "--method", "interpolation", "--out", str(tmp_path / "g")])
    assert refused.exit_code == 1 and refused.stderr.startswith("ERROR: ") and "exact everywhere" in refused.stderr
    assert "Traceback" not in refused.output and not (tmp_path / "g").exists()


def test_deflection_of_a_model_store_matches_differences_of_the_exact_synthesis(toy24):
    """ξ, η of a store fitted from a model agree with central differences of the exact
    synthesis, within the fit error turned into a slope: a spline error of at most ε on
    cells of size h R varies by at most 2 (n-1)² ε / (h R) per metre (Markov's
    inequality for degree n-1 polynomials on the cell), n the spline order."""
    from geoidspline.geodesy.ellipsoids import gaussian_mean_radius
    from geoidspline.query.derived import deflection

    h, order = 0.02, 4
    region = Region(10, 10, 30, 40)
    params = FitParameters(h0=h, order=order, max_level=0, tolerance_m=1.0, method="interpolation")
    spline = fit_source(toy24, region, params).spline
    check = check_points(toy24, region, count=3000, seed=5)
    eps = np.abs(check.truth - spline.undulation(check.latitude, check.longitude)).max()
    rng = np.random.default_rng(6)
    lat = rng.uniform(13, 27, 300)
    lon = rng.uniform(13, 37, 300)
    got = deflection(spline, lat, lon)
    radius = gaussian_mean_radius(lat)
    step = 1e-3  # degrees: truncation |N'''| step² / 6 is ~1e-12 m per m here
    dn_dphi = (toy24.undulation(lat + step, lon) - toy24.undulation(lat - step, lon)) / (2 * np.radians(step))
    dn_dlam = (toy24.undulation(lat, lon + step) - toy24.undulation(lat, lon - step)) / (2 * np.radians(step))
    xi = -np.degrees(dn_dphi / radius) * 3600
    eta = -np.degrees(dn_dlam / (radius * np.cos(np.radians(lat)))) * 3600
    slope_bound = 2 * (order - 1) ** 2 * eps / (h * 6_371_000.0)  # metres per metre
    bound_arcsec = np.degrees(slope_bound) * 3600
    assert 0 < eps < 2e-3
    assert np.abs(got.xi_arcsec - xi).max() < bound_arcsec
    assert np.abs(got.eta_arcsec - eta).max() < bound_arcsec
    # and the comparison is not vacuous: the deflections are far larger than the bound
    assert np.abs(xi).max() > 20 * bound_arcsec
