"""Derived quantities (geoidspline.query) and the CLI options built on them.

Deflections against finite differences and analytic fields, tile error bounds, CRS and
height conversions, grid export read back by PROJ and xarray, exact synthesis with
``geoid-query --model`` and ``geoid-info --check-against``. Stores are the session's
small store (conftest) and one tiny store fitted from a synthetic ICGEM model.
"""

from __future__ import annotations

import json
import math
import sys
from types import SimpleNamespace

import numpy as np
import pyproj
import pytest
from click.testing import CliRunner
from reference_data import REFERENCE_DATA

import geoidspline
from geoidspline import geodesy
from geoidspline.__main__ import main as geoidspline_main
from geoidspline.api import build_store
from geoidspline.cli.export import main as export_main
from geoidspline.cli.info import main as info_main
from geoidspline.cli.query import main as query_main
from geoidspline.errors import CoordinateError, GeoidSplineError, ParameterError
from geoidspline.fitting.parameters import FitParameters
from geoidspline.geodesy.ellipsoids import WGS84
from geoidspline.api import export, validation
from geoidspline.query import crs, derived
from geoidspline.store import error_bound
from geoidspline.sources.formats import read_grid
from geoidspline.sources.harmonics import GeoidSynthesis, presets, read_model
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region

DATA = REFERENCE_DATA / "egm96"
EGM96 = DATA / "egm96_to360.ascii.gz"
CORRCOEF = DATA / "CORRCOEF.gz"
DAC = DATA / "WW15MGH.DAC"
needs_egm96 = pytest.mark.skipif(
    not (EGM96.is_file() and CORRCOEF.is_file() and DAC.is_file()),
    reason=f"NGA EGM96 files (egm96_to360.ascii.gz, CORRCOEF.gz, WW15MGH.DAC) not found under {DATA}",
)


def invoke(command, args, input=None):
    return CliRunner().invoke(command, [str(a) for a in args], input=input)


def assert_user_error(result, code=1):
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert result.stderr.startswith("ERROR: "), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    assert isinstance(result.exception, SystemExit)


@pytest.fixture(scope="module")
def store(small_store):
    return geoidspline.open_store(small_store.path)


def query(small_store, *args, input=None):
    return invoke(query_main, ["--store", small_store.path, *args], input=input)


def interior_points(count, seed, region=(12.0, 22.0, 28.0, 38.0)):
    """Random points well inside the session store's region (10..30 N, 20..40 E)."""
    rng = np.random.default_rng(seed)
    s, w, n, e = region
    return rng.uniform(s, n, count), rng.uniform(w, e, count)


def surface_second_derivatives(spline, lat, lon):
    """N_φφ and N_λλ (metres per radian²) of the restriction N(φ, λ) = S(u(φ, λ)),
    from the spline's analytic gradient g and Hessian H:
    N_φφ = ê_nᵀHê_n − g·u,  N_λλ = cos²φ ê_eᵀHê_e − cos φ (g_x cos λ + g_y sin λ)."""
    phi, lam = np.radians(lat), np.radians(lon)
    u = directions(lat, lon)
    out = spline.evaluate_points(u, nderiv=2)
    g = out[:, 1:4]
    xx, yy, zz, xy, xz, yz = out[:, 4:].T
    H = np.stack([np.stack([xx, xy, xz], -1), np.stack([xy, yy, yz], -1), np.stack([xz, yz, zz], -1)], -2)
    e_n = np.stack([-np.sin(phi) * np.cos(lam), -np.sin(phi) * np.sin(lam), np.cos(phi)], -1)
    e_e = np.stack([-np.sin(lam), np.cos(lam), np.zeros_like(lam)], -1)
    n_pp = np.einsum("ni,nij,nj->n", e_n, H, e_n) - np.einsum("ni,ni->n", g, u)
    n_ll = np.cos(phi) ** 2 * np.einsum("ni,nij,nj->n", e_e, H, e_e) - np.cos(phi) * (
        g[:, 0] * np.cos(lam) + g[:, 1] * np.sin(lam))
    return n_pp, n_ll


# ----------------------------------------------------------------------------- deflection


def test_gaussian_mean_radius_is_sqrt_of_m_times_n():
    a, e2 = WGS84.a, WGS84.e2
    assert geodesy.gaussian_mean_radius(0.0) == pytest.approx(WGS84.b, rel=1e-15)  # a√(1−e²) = b
    assert geodesy.gaussian_mean_radius(90.0) == pytest.approx(a * a / WGS84.b, rel=1e-15)
    lat = np.array([-60.0, -12.5, 33.0, 71.0])
    w = np.sqrt(1 - e2 * np.sin(np.radians(lat)) ** 2)
    M, N = a * (1 - e2) / w**3, a / w
    np.testing.assert_allclose(geodesy.gaussian_mean_radius(lat), np.sqrt(M * N), rtol=1e-15)


def test_large_batches_equal_the_level_by_level_sum_and_are_nan_outside(store, small_store):
    """A store's large batch (the compiled path: two-pass sort, one folded table a point)
    gives at each point the value of the numpy level-by-level evaluator to 1e-12 m, dense
    (thousands of points a sort bucket) and sparse (a few) alike, and NaN outside the
    store's coverage or at NaN coordinates, never a number."""
    from geoidspline.bspline.evaluate import evaluate_levels
    from geoidspline.hierarchy.ambient import FOLDED_FROM_POINTS
    from geoidspline.sphere.coordinates import directions

    rng = np.random.default_rng(71)
    dense_lat, dense_lon = interior_points(40_000, 72, region=(15.0, 25.0, 17.0, 27.0))
    sparse_lat, sparse_lon = interior_points(4_000, 73)
    lat = np.concatenate([dense_lat, sparse_lat, rng.uniform(-89.0, 9.0, 500), [np.nan, 20.0]])
    lon = np.concatenate([dense_lon, sparse_lon, rng.uniform(-180.0, 180.0, 500), [30.0, np.nan]])
    assert lat.size >= FOLDED_FROM_POINTS
    got = store.undulation(lat, lon)
    inside = slice(0, dense_lat.size + sparse_lat.size)
    want = evaluate_levels(store.spline.levels, directions(lat[inside], lon[inside]), 0)[:, 0]
    assert np.abs(got[inside] - want).max() <= 1e-12
    assert np.abs(want).max() > 1.0  # real values, not zeros
    assert np.isnan(got[inside.stop:]).all()


def test_deflection_matches_finite_differences_of_the_store(store):
    """Central differences of store.undulation with step ε (radians of arc) along north
    and east have truncation error ≤ ε²/6 · max|N'''|; max|N'''| is estimated from the
    spline's analytic second derivatives at ±ε (the third derivative is what varies
    them), and the tolerance is twice that bound plus 1e-8 m/rad of rounding."""
    lat, lon = interior_points(300, seed=5)
    d = derived.deflection(store, lat, lon)
    R = geodesy.gaussian_mean_radius(lat)
    eps = 1e-4
    step = math.degrees(eps)
    dlon = step / np.cos(np.radians(lat))  # ε of arc along the parallel
    fd_north = (store.undulation(lat + step, lon) - store.undulation(lat - step, lon)) / (2 * eps)
    fd_east = (store.undulation(lat, lon + dlon) - store.undulation(lat, lon - dlon)) / (2 * eps)

    npp_hi, _ = surface_second_derivatives(store.spline, lat + step, lon)
    npp_lo, _ = surface_second_derivatives(store.spline, lat - step, lon)
    _, nll_hi = surface_second_derivatives(store.spline, lat, lon + dlon)
    _, nll_lo = surface_second_derivatives(store.spline, lat, lon - dlon)
    m3_north = np.max(np.abs(npp_hi - npp_lo)) / (2 * eps)  # m/rad³
    # along the parallel, per radian of arc: d/ds = (1/cos φ) d/dλ
    m3_east = np.max(np.abs(nll_hi - nll_lo) / (2 * np.radians(dlon)) / np.cos(np.radians(lat)) ** 3)
    tol_north = 2 * eps**2 * m3_north / 6 + 1e-8
    tol_east = 2 * eps**2 * m3_east / 6 + 1e-8
    assert tol_north < 1e-5 and tol_east < 1e-5  # the bound is meaningful against gradients of ~30 m/rad
    np.testing.assert_allclose(d.dn_dnorth * R, fd_north, rtol=0, atol=tol_north)
    np.testing.assert_allclose(d.dn_deast * R, fd_east, rtol=0, atol=tol_east)
    # the convention: ξ = −dN/dnorth, η = −dN/deast, radians → arcseconds
    np.testing.assert_allclose(d.xi_arcsec, -fd_north / R * 206264.80624709636, rtol=0, atol=tol_north / R.min() * 206265)
    np.testing.assert_allclose(d.eta_arcsec, -fd_east / R * 206264.80624709636, rtol=0, atol=tol_east / R.min() * 206265)


def test_deflection_follows_the_fitted_field(store, analytic):
    """The store fits N = 20 sin 2φ cos λ + 10 cos²φ sin 2λ + 5 to 2 mm at 2° nodes; its
    slope follows the field's to a few cm per radian (gradients reach ~32 m/rad)."""
    lat, lon = interior_points(400, seed=6)
    d = derived.deflection(store, lat, lon)
    R = geodesy.gaussian_mean_radius(lat)
    phi, lam = np.radians(lat), np.radians(lon)
    dn_dphi = 40 * np.cos(2 * phi) * np.cos(lam) - 10 * np.sin(2 * phi) * np.sin(2 * lam)
    dn_dlam = -20 * np.sin(2 * phi) * np.sin(lam) + 20 * np.cos(phi) ** 2 * np.cos(2 * lam)
    assert np.abs(d.dn_dnorth * R - dn_dphi).max() < 0.1
    assert np.abs(d.dn_deast * R - dn_dlam / np.cos(phi)).max() < 0.1


class RadialField:
    """An analytic ambient 'spline': S(x) = c·x/|x| (radially constant) or c·x (not)."""

    def __init__(self, c, radial_constant=True):
        self.c = np.asarray(c, dtype=float)
        self.radial_constant = radial_constant

    def evaluate_points(self, points, nderiv=0):
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        r = np.linalg.norm(points, axis=1)
        if self.radial_constant:
            value = points @ self.c / r
            grad = self.c[None, :] / r[:, None] - (points @ self.c)[:, None] * points / r[:, None] ** 3
        else:
            value = points @ self.c
            grad = np.broadcast_to(self.c, points.shape)
        assert nderiv == 1
        return np.column_stack([value, grad])


@pytest.mark.parametrize("a", [7.0, -3.0])
@pytest.mark.parametrize("radial_constant", [True, False], ids=["ray-constant", "linear"])
def test_deflection_sign_convention_on_analytic_fields(a, radial_constant):
    """N = a sin φ (S = a z): ∂N/∂φ = a cos φ, so ξ = −a cos φ / R (sign of −a cos φ)
    and η = 0; N = a cos φ sin λ (S = a y): (1/cos φ) ∂N/∂λ = a cos λ, η = −a cos λ / R.
    A radial gradient component (the linear field) does not change anything."""
    lat = np.array([-75.0, -30.0, 0.0, 15.0, 60.0, 89.0])
    lon = np.array([-170.0, -45.0, 0.0, 30.0, 100.0, 179.0])
    R = geodesy.gaussian_mean_radius(lat)
    arcsec = 180 / math.pi * 3600
    phi, lam = np.radians(lat), np.radians(lon)

    d = derived.deflection(RadialField([0, 0, a], radial_constant), lat, lon)
    np.testing.assert_allclose(d.dn_dnorth, a * np.cos(phi) / R, rtol=1e-12)
    np.testing.assert_allclose(d.xi_arcsec, -a * np.cos(phi) / R * arcsec, rtol=1e-12)
    assert np.all(np.sign(d.xi_arcsec) == np.sign(-a * np.cos(phi)))
    np.testing.assert_allclose(d.eta_arcsec, 0.0, atol=1e-12)

    d = derived.deflection(RadialField([0, a, 0], radial_constant), lat, lon)
    np.testing.assert_allclose(d.dn_deast, a * np.cos(lam) / R, rtol=1e-12, atol=1e-20)
    np.testing.assert_allclose(d.eta_arcsec, -a * np.cos(lam) / R * arcsec, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(d.dn_dnorth, -a * np.sin(phi) * np.sin(lam) / R, rtol=1e-12, atol=1e-20)


def test_deflection_at_the_poles_is_relative_to_the_given_meridian():
    """N = a cos φ cos λ (S = a x) tilts the geoid towards +x at the north pole: along
    the meridian λ = 0 'north' runs to −x, along λ = 90° east is −x."""
    a = 5.0
    field = RadialField([a, 0, 0])
    R = geodesy.gaussian_mean_radius(90.0)
    d = derived.deflection(field, [90.0, 90.0, 90.0], [0.0, 90.0, 180.0])
    np.testing.assert_allclose(d.dn_dnorth * R, [-a, 0.0, a], atol=1e-12)
    np.testing.assert_allclose(d.dn_deast * R, [0.0, -a, 0.0], atol=1e-12)
    assert np.all(np.isfinite(d.xi_arcsec)) and np.all(np.isfinite(d.eta_arcsec))


def test_deflection_scalars_nan_shapes_and_errors(store):
    d = derived.deflection(store, 20.0, 30.0)
    assert all(isinstance(v, np.floating) and np.ndim(v) == 0 for v in d)
    assert d == tuple(derived.deflection(store.spline, 20.0, 30.0))  # a spline works as well
    arr = derived.deflection(store, [20.0, np.nan, 21.0], [30.0, 31.0, np.nan])
    assert all(v.shape == (3,) for v in arr)
    assert np.isfinite(arr.xi_arcsec[0]) and np.isnan(arr.xi_arcsec[1:]).all() and np.isnan(arr.dn_deast[1:]).all()
    assert arr.xi_arcsec[0] == d.xi_arcsec
    grid = derived.deflection(store, np.array([[15.0], [25.0]]), np.array([25.0, 30.0, 35.0]))
    assert grid.eta_arcsec.shape == (2, 3)
    assert derived.deflection(store, [], []).xi_arcsec.shape == (0,)
    with pytest.raises(CoordinateError, match="latitude"):
        derived.deflection(store, 95.0, 30.0)
    with pytest.raises(TypeError):
        derived.deflection(object(), 20.0, 30.0)


def test_query_deflection_columns(small_store, store, tmp_path):
    lat, lon = interior_points(5, seed=8)
    lat, lon = np.round(lat, 4), np.round(lon, 4)
    csv = tmp_path / "in.csv"
    csv.write_text("lat,lon,id\n" + "".join(f"{a},{b},p{i}\n" for i, (a, b) in enumerate(zip(lat, lon))))
    result = query(small_store, "--input", csv, "--deflection", "--precision", "6")
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == "lat,lon,id,undulation_m,xi_arcsec,eta_arcsec,dNdn_m_per_m,dNde_m_per_m"
    d = derived.deflection(store, lat, lon)
    n = store.undulation(lat, lon)
    for i, line in enumerate(lines[1:]):
        assert line == (f"{lat[i]},{lon[i]},p{i},{n[i]:.6f},{d.xi_arcsec[i]:.6f},{d.eta_arcsec[i]:.6f},"
                        f"{d.dn_dnorth[i]:.6e},{d.dn_deast[i]:.6e}")
    single = query(small_store, "--deflection", lat[0], lon[0])
    assert single.exit_code == 0, single.output
    assert single.stdout.strip() == (f"{n[0]:.4f},{d.xi_arcsec[0]:.4f},{d.eta_arcsec[0]:.4f},"
                                     f"{d.dn_dnorth[0]:.4e},{d.dn_deast[0]:.4e}")


# ----------------------------------------------------------------------------- tile error bounds


def nearby_by_scan(store, lat, lon):
    """The bound's parts by a plain scan: for each point, over the tiles whose cube meets
    u ± order·h0/2 (h0 the coarsest spacing), the largest of max_error_m and
    node_max_error_m (the store's overall figure where none has any), and the largest
    excess max(0, max_error_m - node_max_error_m)."""
    meta = store.manifest["spline"]
    size = meta["tile_size"]
    reach = meta["order"] * max([meta["h0"]] + [lv["h"] for lv in meta["levels"]]) / 2
    figures, excesses = {}, {}
    for e in store.manifest["tiles"]:
        known = [v for v in (e["max_error_m"], e["node_max_error_m"]) if v is not None]
        if known:
            figures[tuple(e["tile"])] = max(known)
        if len(known) == 2:
            excesses[tuple(e["tile"])] = max(0.0, e["max_error_m"] - e["node_max_error_m"])
    acc = store.manifest["accuracy"]
    overall = max(acc["max_error_m"], acc["node_max_error_m"])
    nearby, excess = [], []
    for u in directions(np.asarray(lat, float), np.asarray(lon, float)):
        lo = np.floor((u - reach) / size).astype(int)
        hi = np.floor((u + reach) / size).astype(int)
        near = [(i, j, k) for i in range(lo[0], hi[0] + 1) for j in range(lo[1], hi[1] + 1)
                for k in range(lo[2], hi[2] + 1)]
        nearby.append(max([figures[t] for t in near if t in figures], default=overall))
        excess.append(max([excesses[t] for t in near if t in excesses],
                          default=max(0.0, acc["max_error_m"] - acc["node_max_error_m"])))
    return np.array(nearby), np.array(excess)


def test_tile_error_bound_is_the_factor_times_the_largest_error_measured_nearby_plus_the_grid_term(store):
    lat, lon = interior_points(200, seed=9, region=(10.0, 20.0, 30.0, 40.0))
    nearby, excess = nearby_by_scan(store, lat, lon)
    np.testing.assert_array_equal(error_bound.nearby_measured_error(store, lat, lon), nearby)
    np.testing.assert_array_equal(error_bound.grid_interpolation_uncertainty(store, lat, lon), excess)
    assert store.manifest["provenance"]["kind"] == "grid" and excess.max() > 0  # the grid term is in use
    bound = error_bound.tile_error_bound(store, lat, lon)
    np.testing.assert_array_equal(bound, error_bound.ERROR_BOUND_FACTOR * nearby + excess)
    assert np.isfinite(bound).all()  # every point inside the coverage has a bound
    acc = store.manifest["accuracy"]
    assert np.all(nearby <= max(acc["max_error_m"], acc["node_max_error_m"]))
    assert np.all(nearby >= min(acc["max_error_m"], acc["node_max_error_m"]) / 10)  # not vacuous
    # outside the coverage and for NaN: no bound
    out = error_bound.tile_error_bound(store, [45.0, -20.0, np.nan], [30.0, 30.0, 30.0])
    assert np.isnan(out).all()
    assert np.ndim(error_bound.tile_error_bound(store, 20.0, 30.0)) == 0
    assert store.error_bound(20.0, 30.0) == error_bound.tile_error_bound(store, 20.0, 30.0)


def test_a_model_store_has_no_grid_term(model_store):
    store = geoidspline.open_store(model_store)
    lat, lon = interior_points(50, seed=4, region=MODEL_REGION)
    assert np.all(error_bound.grid_interpolation_uncertainty(store, lat, lon) == 0.0)
    np.testing.assert_array_equal(error_bound.tile_error_bound(store, lat, lon),
                                  error_bound.ERROR_BOUND_FACTOR * error_bound.nearby_measured_error(store, lat, lon))


def test_tile_error_bound_falls_back_to_the_store_figure_for_tiles_without_figures(store):
    """A store whose tiles carry no figures (a tile rewritten by an update has only
    node figures; here none at all) still bounds every covered point, by its overall
    figures."""
    bare = SimpleNamespace(manifest={**store.manifest, "tiles": [
        {**e, "max_error_m": None, "node_max_error_m": None} for e in store.manifest["tiles"]]},
        covers=store.covers)
    acc = store.manifest["accuracy"]
    bound = error_bound.tile_error_bound(bare, [20.0, 12.5], [30.0, 39.0])
    overall = max(acc["max_error_m"], acc["node_max_error_m"])
    excess = max(0.0, acc["max_error_m"] - acc["node_max_error_m"])
    np.testing.assert_array_equal(bound, error_bound.ERROR_BOUND_FACTOR * overall + excess)


def test_tile_error_bound_holds_against_the_analytic_field(store, analytic, small_store):
    """The session store was fitted from a 2° grid of an analytic field: against the
    grid's nodes and its bicubic interpolation at the cell centres (the truth the bound
    is defined against) it holds everywhere; against the analytic field itself, which
    the grid only samples, at the random points too (the field is smooth)."""
    grid = small_store.grid
    lat = np.arange(10.0, 30.01, 2.0)
    lon = np.arange(20.0, 40.01, 2.0)
    nodes = np.meshgrid(lat, lon, indexing="ij")
    centres = np.meshgrid(lat[:-1] + 1.0, lon[:-1] + 1.0, indexing="ij")
    for la, lo in (nodes, centres):
        la, lo = la.ravel(), lo.ravel()
        error = np.abs(store.undulation(la, lo) - grid.undulation(la, lo))
        assert np.all(error <= store.error_bound(la, lo))
    la, lo = interior_points(5000, seed=21, region=(10.0, 20.0, 30.0, 40.0))
    error = np.abs(store.undulation(la, lo) - analytic(la, lo))
    held = np.mean(error <= store.error_bound(la, lo))
    assert held >= 0.999, held


def test_query_with_error_column(small_store, store, tmp_path):
    lat, lon = interior_points(6, seed=10)
    lat, lon = np.round(lat, 3), np.round(lon, 3)
    expected = error_bound.tile_error_bound(store, lat, lon)
    assert np.isfinite(expected).all()
    rows = "".join(f"{a},{b}\n" for a, b in zip(lat, lon)) + "45,30\n"
    result = query(small_store, "--input", "-", "--with-error", "--precision", "10", input=rows)
    assert result.exit_code == 1, result.output  # 45 N is outside the store's coverage
    lines = result.stdout.splitlines()
    for i, line in enumerate(lines[:-1]):
        assert line.split(",")[-1] == f"{expected[i]:.10f}"
    assert lines[-1] == "ERROR: line 7: outside the store's coverage (outside its region S 10 W 20 N 30 E 40)"
    single = query(small_store, "--with-error", "--precision", "10", lat[0], lon[0])
    assert single.stdout.strip().split(",") == [f"{store.undulation(lat[0], lon[0]):.10f}", f"{expected[0]:.10f}"]
    opted = query(small_store, "--input", "-", "--with-error", "--outside", "nan", input="45,30\n")
    assert opted.exit_code == 0 and opted.stdout == "45,30,nan,nan\n"


# ----------------------------------------------------------------------------- CRS and heights


def geocentric(lat, lon, h):
    """WGS84 geodetic → ECEF by the closed formula (independent of PROJ)."""
    phi, lam = math.radians(lat), math.radians(lon)
    n = WGS84.a / math.sqrt(1 - WGS84.e2 * math.sin(phi) ** 2)
    return ((n + h) * math.cos(phi) * math.cos(lam), (n + h) * math.cos(phi) * math.sin(lam),
            (n * (1 - WGS84.e2) + h) * math.sin(phi))


@pytest.mark.parametrize("point", [(48.8583701, 2.2944813, 330.0), (-33.856784, 151.215297, 12.5),
                                   (21.5, 33.25, -40.0), (89.9, -120.0, 0.0)])
def test_to_geodetic_from_geocentric(point):
    lat, lon, h = point
    x, y, z = geocentric(lat, lon, h)
    la, lo, hh = crs.to_geodetic(x, y, z, crs="EPSG:4978")
    assert abs(la - lat) < 1e-9 and abs(lo - lon) < 1e-9
    assert abs(hh - h) < 1e-6
    assert np.ndim(la) == 0


def test_to_geodetic_from_utm():
    # the central meridian of zone 33N (15° E) at the equator is E 500000, N 0
    la, lo, h = crs.to_geodetic(500000.0, 0.0, crs="EPSG:32633")
    assert abs(la) < 1e-9 and abs(lo - 15.0) < 1e-9 and np.isnan(h)
    # and any point: back through PROJ's forward projection
    lat = np.array([10.5, 45.25, 71.0])
    lon = np.array([13.0, 16.9, 12.1])
    fwd = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32633", always_xy=True)
    e, n = fwd.transform(lon, lat)
    la, lo, _ = crs.to_geodetic(e, n, crs="EPSG:32633")
    np.testing.assert_allclose(la, lat, atol=1e-9)
    np.testing.assert_allclose(lo, lon, atol=1e-9)


def test_to_geodetic_geographic_axis_order_and_heights():
    la, lo, h = crs.to_geodetic(30.0, 20.0)  # EPSG:4326, always_xy: x = longitude
    assert (la, lo) == (20.0, 30.0) and np.isnan(h)
    la, lo, h = crs.to_geodetic([30.0, 200.0], [20.0, -10.0], [15.0, 7.0], crs="EPSG:4979")
    np.testing.assert_allclose(la, [20.0, -10.0])
    np.testing.assert_allclose(lo, [30.0, -160.0])  # wrapped to [-180, 180]
    np.testing.assert_allclose(h, [15.0, 7.0])
    la, lo, h = crs.to_geodetic(30.0, 95.0)  # not a latitude
    assert np.isnan(la) and np.isnan(lo)
    assert crs.crs_info("EPSG:4978") == ("geocentric", 3)
    assert crs.crs_info("EPSG:32633") == ("projected", 2)
    assert crs.crs_info("EPSG:4326") == ("geographic", 2)


@pytest.mark.parametrize("given, words", [("EPSG:999999", "unknown CRS"), ("not a crs", "unknown CRS"),
                                          ("EPSG:5773", "not supported"), ("EPSG:4326+5773", "not supported")])
def test_to_geodetic_rejects_unknown_or_unsupported_crs(given, words):
    with pytest.raises(CoordinateError, match=words):
        crs.to_geodetic(1.0, 2.0, crs=given)


def test_to_geodetic_geocentric_needs_z():
    with pytest.raises(CoordinateError, match="geocentric"):
        crs.to_geodetic(6378137.0, 0.0, crs="EPSG:4978")


def test_convert_height_both_ways():
    n = np.array([23.5, -10.25, np.nan])
    h = np.array([100.0, 50.0, 1.0])
    H = derived.convert_height(n, h, "ellipsoidal")
    np.testing.assert_array_equal(H[:2], [76.5, 60.25])
    assert np.isnan(H[2])
    np.testing.assert_array_equal(derived.convert_height(n, H, "orthometric")[:2], h[:2])
    assert derived.convert_height(20.0, 120.0, "orthometric") == 140.0
    assert isinstance(derived.convert_height(20.0, 120.0, "ellipsoidal"), float)
    with pytest.raises(CoordinateError, match="ellipsoidal"):
        derived.convert_height(1.0, 2.0, "normal")


def test_query_height_conversion_both_ways(small_store, store, tmp_path):
    n1, n2 = store.undulation(20.0, 30.0), store.undulation(21.5, 31.25)
    csv = tmp_path / "h.csv"
    csv.write_text("lat,lon,h,name\n20,30,100.5,a\n21.5,31.25,-3,b\n22,32,high,c\n")
    result = query(small_store, "--input", csv, "--height-in", "ellipsoidal")
    assert result.exit_code == 1
    assert result.stdout.splitlines() == [
        "lat,lon,h,name,undulation_m,orthometric_height_m",
        f"20,30,100.5,a,{n1:.4f},{100.5 - n1:.4f}",
        f"21.5,31.25,-3,b,{n2:.4f},{-3 - n2:.4f}",
        "ERROR: line 4: ellipsoidal height (column 2) is not a number: 'high'",
    ]
    csv.write_text("lat,lon,x,H\n20,30,0,80\n")
    result = query(small_store, "--input", csv, "--height-in", "orthometric", "--height-column", "3")
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == ["lat,lon,x,H,undulation_m,ellipsoidal_height_m",
                                          f"20,30,0,80,{n1:.4f},{80 + n1:.4f}"]
    single = query(small_store, "--height-in", "orthometric", "20", "30", "80")
    assert single.stdout.strip() == f"{n1:.4f},{80 + n1:.4f}"


def test_query_crs_utm_input(small_store, store, tmp_path):
    lat = np.array([12.5, 20.0, 27.75])
    lon = np.array([25.0, 27.0, 29.5])
    fwd = pyproj.Transformer.from_crs("EPSG:4326", "EPSG:32635", always_xy=True)
    e, n = fwd.transform(lon, lat)
    csv = tmp_path / "utm.csv"
    csv.write_text("easting,northing,id\n" + "".join(f"{float(a)!r},{float(b)!r},p{i}\n" for i, (a, b) in enumerate(zip(e, n))))
    result = query(small_store, "--input", csv, "--crs", "EPSG:32635", "--precision", "6")
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    assert lines[0] == "easting,northing,id,latitude_deg,longitude_deg,undulation_m"
    for i, line in enumerate(lines[1:]):
        fields = line.split(",")
        assert abs(float(fields[3]) - lat[i]) < 1e-9 and abs(float(fields[4]) - lon[i]) < 1e-9
        la, lo = float(fields[3]), float(fields[4])
        assert fields[5] == f"{store.undulation(la, lo):.6f}"


def test_query_crs_geocentric_with_ellipsoidal_height(small_store, store):
    x, y, z = geocentric(20.0, 30.0, 250.0)
    result = query(small_store, "--crs", "EPSG:4978", "--height-in", "ellipsoidal", "--precision", "6", x, y, z)
    assert result.exit_code == 0, result.output
    la, lo, n, H = (float(v) for v in result.stdout.strip().split(","))
    assert abs(la - 20.0) < 1e-9 and abs(lo - 30.0) < 1e-9
    N = store.undulation(20.0, 30.0)
    assert abs(n - N) < 1e-6 and abs(H - (250.0 - N)) < 2e-6
    # a 3D CRS gives the ellipsoidal height itself: --height-column and orthometric input make no sense
    for extra in (["--height-column", "2"], []):
        bad = query(small_store, "--crs", "EPSG:4978", "--height-in",
                    "ellipsoidal" if extra else "orthometric", *extra, x, y, z)
        assert bad.exit_code == 2 and "3D" in bad.stderr


def test_query_unknown_crs_is_a_user_error(small_store):
    result = query(small_store, "--crs", "EPSG:999999", "1", "2")
    assert_user_error(result)
    assert "EPSG:999999" in result.stderr


# ----------------------------------------------------------------------------- jsonl


def test_query_jsonl_has_stable_keys(small_store, store, tmp_path):
    csv = tmp_path / "in.csv"
    csv.write_text("lat,lon,h\n20,30,100\nabc,30,1\n21.5,31.25,7\n95,0,0\n")
    args = ["--input", csv, "--format", "jsonl", "--deflection", "--with-error", "--height-in", "ellipsoidal"]
    result = query(small_store, *args)
    assert result.exit_code == 1  # two bad rows
    records = [json.loads(line) for line in result.stdout.splitlines()]
    keys = ["line", "fields", "latitude_deg", "longitude_deg", "undulation_m", "xi_arcsec", "eta_arcsec",
            "dNdn_m_per_m", "dNde_m_per_m", "orthometric_height_m", "error_bound_m", "error"]
    assert [list(r) for r in records] == [keys] * 4
    good, bad1, good2, bad2 = records
    assert good["line"] == 2 and good["fields"] == ["20", "30", "100"] and good["error"] is None
    assert (good["latitude_deg"], good["longitude_deg"]) == (20.0, 30.0)
    n = store.undulation(20.0, 30.0)
    d = derived.deflection(store, 20.0, 30.0)
    assert good["undulation_m"] == round(float(n), 4)
    assert good["orthometric_height_m"] == float(f"{100 - n:.4f}")
    assert good["xi_arcsec"] == float(f"{d.xi_arcsec:.4f}") and good["dNde_m_per_m"] == float(f"{d.dn_deast:.4e}")
    assert good["error_bound_m"] == float(f"{error_bound.tile_error_bound(store, 20.0, 30.0):.4f}")
    assert good2["line"] == 4
    assert bad1["line"] == 3 and bad1["error"].startswith("line 3: ") and "not numbers" in bad1["error"]
    assert bad1["undulation_m"] is None and bad1["fields"] == ["abc", "30", "1"]
    assert bad2["error"] == "line 5: latitude 95 is outside [-90, 90] degrees"
    # one point on the command line gives the same object with line null
    single = query(small_store, "--format", "jsonl", "20", "30")
    record = json.loads(single.stdout)
    assert list(record) == ["line", "fields", "latitude_deg", "longitude_deg", "undulation_m", "error"]
    assert record["line"] is None and record["undulation_m"] == round(float(n), 4)


@pytest.mark.parametrize("source, args, words", [
    ("model", ["--deflection", "20", "30"], "--store"),
    ("model", ["--with-error", "20", "30"], "--store"),
    ("store", ["--height-column", "3", "20", "30"], "--height-in"),
    ("store", ["--correction", "x", "20", "30"], "--model"),
    ("store", ["--preset", "generic", "20", "30"], "--model"),
    ("store", ["20", "30", "40"], "expected 2"),
    ("store", ["--height-in", "ellipsoidal", "20", "30"], "expected 3"),
], ids=["deflection-model", "error-model", "height-column", "correction-store", "preset-store", "three",
        "no-height"])
def test_query_new_usage_errors(small_store, model_file, source, args, words):
    given = ["--model", model_file] if source == "model" else ["--store", small_store.path]
    result = invoke(query_main, [*given, *args])
    assert result.exit_code == 2, result.output
    assert result.stderr.startswith("ERROR: ") and words in result.stderr
    assert "Traceback" not in result.output


def test_query_needs_exactly_one_source(small_store, tmp_path):
    result = invoke(query_main, ["20", "30"])
    assert result.exit_code == 2 and "--store" in result.stderr and "--model" in result.stderr
    model = tmp_path / "m.gfc"
    model.write_text(gfc_text())
    result = invoke(query_main, ["--store", small_store.path, "--model", model, "20", "30"])
    assert result.exit_code == 2


# ----------------------------------------------------------------------------- export


def test_export_gtx_is_read_by_proj_vgridshift(store, tmp_path):
    """PROJ's vgridshift interpolates the exported GTX bilinearly: it must agree with
    our own bilinear interpolation of the written nodes (float32) and with the store to
    the bilinear error bound ½[t(1−t)Δφ² |N_φφ| + s(1−s)Δλ² |N_λλ|] (cell maximum of
    the spline's analytic second derivatives, +25 %) plus float32 rounding."""
    spacing = 0.5
    path = tmp_path / "qexport_a.gtx"
    grid = export.export_grid(store, path, spacing)
    assert grid.shape == (41, 41)
    assert (grid.latitude[0], grid.latitude[-1], grid.longitude[0], grid.longitude[-1]) == (10.0, 30.0, 20.0, 40.0)
    back = read_grid(path)
    lat2, lon2 = np.meshgrid(back.latitude, back.longitude, indexing="ij")
    np.testing.assert_allclose(back.values, store.undulation(lat2, lon2), rtol=0, atol=4e-6)  # float32

    pyproj.datadir.append_data_dir(str(tmp_path))
    shift = pyproj.Transformer.from_pipeline(f"+proj=vgridshift +grids={path.name} +multiplier=1")
    rng = np.random.default_rng(11)
    lat = rng.uniform(10.0, 30.0, 400)
    lon = rng.uniform(20.0, 40.0, 400)
    _, _, proj_n = shift.transform(lon, lat, np.zeros(lat.size))
    assert np.isfinite(proj_n).all()
    np.testing.assert_allclose(proj_n, back.undulation(lat, lon, method="bilinear"), rtol=0, atol=1e-9)

    i = np.minimum(np.floor((lat - 10.0) / spacing), 39)
    j = np.minimum(np.floor((lon - 20.0) / spacing), 39)
    t = (lat - 10.0) / spacing - i
    s = (lon - 20.0) / spacing - j
    h = math.radians(spacing)
    worst_pp = np.zeros(lat.size)
    worst_ll = np.zeros(lat.size)
    for da, db in [(0, 0), (0, 1), (1, 0), (1, 1), (None, None)]:
        la = lat if da is None else 10.0 + (i + da) * spacing
        lo = lon if db is None else 20.0 + (j + db) * spacing
        npp, nll = surface_second_derivatives(store.spline, la, lo)
        worst_pp = np.maximum(worst_pp, np.abs(npp))
        worst_ll = np.maximum(worst_ll, np.abs(nll))
    bound = 0.5 * (t * (1 - t) * h**2 * worst_pp + s * (1 - s) * h**2 * worst_ll) * 1.25 + 4e-6
    error = np.abs(proj_n - store.undulation(lat, lon))
    assert np.all(error <= bound), (error.max(), bound[np.argmax(error - bound)])
    assert 1e-4 < error.max() < 0.002  # measured 1.0 mm at 0.5°: the test is not vacuous


def test_export_netcdf_reads_back_through_xarray(store, tmp_path):
    xr = pytest.importorskip("xarray")
    path = tmp_path / "grid.nc"
    export.export_grid(store, path, 0.25, Region.from_bounds(12, 22, 18, 27))
    with xr.open_dataset(path) as ds:
        lat = ds["latitude"].values
        lon = ds["longitude"].values
        values = ds["geoid_height"].values
        assert ds["geoid_height"].attrs["units"] == "m"
    np.testing.assert_allclose(lat, np.arange(12.0, 18.0001, 0.25), atol=1e-12)
    np.testing.assert_allclose(lon, np.arange(22.0, 27.0001, 0.25), atol=1e-12)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    np.testing.assert_allclose(values, store.undulation(lat2, lon2), rtol=0, atol=1e-12)
    grid = read_grid(path)  # and our own reader takes it
    assert grid.shape == (25, 21)


def test_export_lattice_rules(store):
    lat, lon, _ = export.export_lattice(store, 0.3)  # 10..30 by 0.3: last node 29.8
    assert lat[0] == 10.0 and abs(lat[-1] - 29.8) < 1e-9 and lat.size == 67
    fake = SimpleNamespace(manifest={"region": [-90.0, -180.0, 90.0, 180.0]})
    lat, lon, _ = export.export_lattice(fake, 2.5)
    assert (lat[0], lat[-1], lat.size) == (-90.0, 90.0, 73)
    assert (lon[0], lon[-1], lon.size) == (-180.0, 177.5, 144)  # periodic: no repeated column
    with pytest.raises(CoordinateError, match="divides 360"):
        export.export_lattice(fake, 0.7)
    with pytest.raises(CoordinateError, match="not inside"):
        export.export_lattice(store, 0.5, Region.from_bounds(5, 20, 15, 30))
    with pytest.raises(CoordinateError, match="not inside"):
        export.export_lattice(store, 0.5, Region.from_bounds(12, 35, 15, 45))
    with pytest.raises(ParameterError, match=r"spacing_deg must be a finite number in \[1e-06, 180\] degrees"):
        export.export_lattice(store, 0.0)
    with pytest.raises(CoordinateError, match="2 x 2"):
        export.export_lattice(store, 30.0)


def test_export_geotiff_without_rasterio_is_a_clear_error(store, tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "rasterio", None)  # import rasterio -> ImportError
    with pytest.raises(GeoidSplineError, match="rasterio"):
        export.export_grid(store, tmp_path / "g.tif", 0.5)
    assert not (tmp_path / "g.tif").exists()
    result = invoke(export_main, [store.path, "--out", tmp_path / "g.tif", "--spacing", "0.5"])
    assert_user_error(result)
    assert "pip install rasterio" in result.stderr


def test_export_geotiff_with_rasterio(store, tmp_path):
    rasterio = pytest.importorskip("rasterio", reason="rasterio not installed (GeoTIFF export is optional)")
    path = tmp_path / "g.tif"
    grid = export.export_grid(store, path, 0.5)
    with rasterio.open(path) as ds:
        data = ds.read(1)
        x, y = ds.xy(0, 0)  # centre of the north-west pixel: the node there
    assert (x, y) == pytest.approx((20.0, 30.0))
    np.testing.assert_allclose(data, grid.values[::-1], atol=4e-6)


def test_export_cli(small_store, store, tmp_path):
    out = tmp_path / "cli.gtx"
    result = invoke(export_main, [small_store.path, "--out", out, "--spacing", "1", "--region", 12, 22, 20, 30])
    assert result.exit_code == 0, result.output
    assert result.stdout.startswith(f"wrote {out}: 9 x 9 nodes every 1 degrees")
    grid = read_grid(out)
    np.testing.assert_allclose(grid.values, store.undulation(*np.meshgrid(grid.latitude, grid.longitude, indexing="ij")),
                               atol=4e-6)
    as_json = invoke(export_main, [small_store.path, "--out", tmp_path / "cli.nc", "--spacing", "2", "--json"])
    assert json.loads(as_json.stdout)["rows"] == 11
    bad = invoke(export_main, [small_store.path, "--out", tmp_path / "x.csv", "--spacing", "1"])
    assert_user_error(bad)
    assert ".gtx" in bad.stderr
    outside = invoke(export_main, [small_store.path, "--out", out, "--spacing", "1", "--region", 0, 0, 5, 5])
    assert_user_error(outside)
    assert "not inside" in outside.stderr
    grouped = CliRunner().invoke(geoidspline_main, ["export", "--help"])
    assert grouped.exit_code == 0 and "--spacing" in grouped.stdout


# ----------------------------------------------------------------------------- harmonic models

GFC_NMAX = 10


def gfc_text(nmax=GFC_NMAX, seed=7):
    """A tiny ICGEM model: C̄20 near the normal field's, the rest random with a decaying
    degree variance (a few metres of undulation per degree)."""
    rng = np.random.default_rng(seed)
    lines = ["synthetic test model for geoidspline.query", "begin_of_head ======",
             "product_type gravity_field", "modelname TINYSYN", "earth_gravity_constant 3.986004415E+14",
             "radius 6378136.3", f"max_degree {nmax}", "norm fully_normalized", "tide_system tide_free",
             "errors no", "key n m C S", "end_of_head ======"]
    for n in range(2, nmax + 1):
        for m in range(n + 1):
            sigma = 2e-6 / n**1.5
            c = -0.484165e-3 if (n, m) == (2, 0) else rng.normal(0.0, sigma)
            s = 0.0 if m == 0 else rng.normal(0.0, sigma)
            lines.append(f"gfc {n} {m} {c:.12e} {s:.12e}")
    return "\n".join(lines) + "\n"


@pytest.fixture(scope="module")
def model_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("model") / "tiny.gfc"
    path.write_text(gfc_text())
    return path


MODEL_REGION = (-5.0, 10.0, 5.0, 20.0)


@pytest.fixture(scope="module")
def model_store(tmp_path_factory, model_file):
    """A tiny store fitted from the synthetic model (preset generic) over MODEL_REGION."""
    path = tmp_path_factory.mktemp("model_store") / "store"
    synthesis = GeoidSynthesis(read_model(model_file), preset="generic")
    build_store(synthesis, path, Region.from_bounds(*MODEL_REGION),
                FitParameters(h0=0.2, max_level=1, tolerance_m=0.05), check_count=500)
    return path


def test_query_model_mode_matches_geoid_synthesis(model_file, tmp_path):
    model = read_model(model_file)
    rng = np.random.default_rng(12)
    lat = np.round(rng.uniform(-89, 89, 6), 4)
    lon = np.round(rng.uniform(-180, 360, 6), 4)
    csv = tmp_path / "pts.csv"
    csv.write_text("lat,lon\n" + "".join(f"{a},{b}\n" for a, b in zip(lat, lon)))
    for preset in (None, "generic", "nga-hsynth"):
        args = ["--model", model_file, "--input", csv, "--precision", "9"] + (["--preset", preset] if preset else [])
        result = invoke(query_main, args)
        assert result.exit_code == 0, result.output
        expected = GeoidSynthesis(model, preset=preset or "nga-f477").undulation(lat, lon)
        got = np.array([float(line.split(",")[-1]) for line in result.stdout.splitlines()[1:]])
        np.testing.assert_allclose(got, expected, rtol=0, atol=1e-9)
    single = invoke(query_main, ["--model", model_file, "--preset", "generic", "--precision", "9", lat[0], lon[0]])
    assert single.stdout.strip() == f"{GeoidSynthesis(model, preset='generic').undulation(lat[0], lon[0]):.9f}"
    # heights and jsonl work with a model too
    both = invoke(query_main, ["--model", model_file, "--format", "jsonl", "--height-in", "orthometric",
                               lat[0], lon[0], 10.0])
    record = json.loads(both.stdout)
    n = GeoidSynthesis(model).undulation(lat[0], lon[0])
    assert record["undulation_m"] == round(n, 4) and record["ellipsoidal_height_m"] == round(10.0 + n, 4)


def test_default_preset_rules(model_file):
    model = read_model(model_file)
    assert presets.default_preset(model) == "nga-f477"  # geoidspline.sources.harmonics' default
    assert presets.default_preset(SimpleNamespace(name="EGM2008")) == "nga-hsynth"
    assert presets.default_preset(SimpleNamespace(name="EGM96"), correction=object()) == "nga-f477"
    assert presets.default_preset(SimpleNamespace(name="EGM2008"), correction=object()) == "nga-f477"


def test_query_model_errors(tmp_path):
    result = invoke(query_main, ["--model", tmp_path / "none.gfc", "20", "30"])
    assert_user_error(result)
    assert "none.gfc" in result.stderr
    bad = tmp_path / "bad.gfc"
    bad.write_text(gfc_text().replace("gfc 3 1", "gfc 3 x"))
    result = invoke(query_main, ["--model", bad, "20", "30"])
    assert_user_error(result)
    assert "bad.gfc" in result.stderr and "line" in result.stderr


@pytest.fixture(scope="module")
def egm96():
    if not (EGM96.is_file() and CORRCOEF.is_file() and DAC.is_file()):
        pytest.skip(f"NGA EGM96 files not found under {DATA}")
    return np.fromfile(DAC, dtype=">i2").reshape(721, 1440)


@needs_egm96
def test_query_model_reproduces_nga_f477_egm96(egm96, tmp_path):
    """WW15MGH.DAC holds F477's 15' grid in cm (from mm-rounded values): every node
    agrees to 5.5 mm. No --preset: the default must be F477's."""
    rows = np.array([0, 100, 208, 360, 361, 555, 700, 720])
    cols = np.array([0, 1439, 37, 720, 1000, 250, 1200, 5])
    lat = 90.0 - rows * 0.25
    lon = cols * 0.25
    csv = tmp_path / "nodes.csv"
    csv.write_text("".join(f"{a},{b}\n" for a, b in zip(lat, lon)))
    result = invoke(query_main, ["--model", EGM96, "--correction", CORRCOEF, "--input", csv, "--precision", "6"])
    assert result.exit_code == 0, result.output
    got = np.array([float(line.split(",")[-1]) for line in result.stdout.splitlines()])
    assert np.abs(got - egm96[rows, cols] / 100.0).max() <= 0.0055 + 5e-6
    # the README's node 38 N 360 E: 49.156 m (printed to mm)
    single = invoke(query_main, ["--model", EGM96, "--correction", CORRCOEF, "--precision", "3", "38", "360"])
    assert single.exit_code == 0, single.output
    assert abs(float(single.stdout) - 49.156) <= 0.0005 + 1e-9


def test_info_check_against_a_synthetic_model(model_store, model_file):
    """|store − model| at 2,000 random points uniform in area over the store's region
    (seed 1; 10 a random latitude), recomputed here independently of
    geoidspline.fitting.check_points.check_points."""
    points = 2000
    result = invoke(info_main, [model_store, "--check-against", model_file, "--points", points, "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    check = data["check_against"]
    assert check["points"] == points and check["seed"] == validation.CHECK_SEED
    assert check["preset"] == "generic"  # taken from the store, which was fitted from this file
    assert check["same_source"] is True and check["region"] == list(MODEL_REGION)

    s, w, n, e = MODEL_REGION
    rng = np.random.default_rng(validation.CHECK_SEED)
    rings = points // 10
    lat = np.repeat(np.degrees(np.arcsin(rng.uniform(math.sin(math.radians(s)), math.sin(math.radians(n)), rings))),
                    10)
    lon = w + rng.uniform(0.0, e - w, points)
    store = geoidspline.open_store(model_store)
    synthesis = GeoidSynthesis(read_model(model_file), preset="generic")
    err = np.abs(store.undulation(lat, lon) - synthesis.undulation(lat, lon))
    assert check["max_error_m"] == pytest.approx(err.max(), rel=1e-12)
    assert check["rms_error_m"] == pytest.approx(math.sqrt(np.mean(err**2)), rel=1e-12)
    assert check["p99_error_m"] == pytest.approx(np.percentile(err, 99), rel=1e-12)
    assert check["p99_error_m"] <= check["max_error_m"]
    # the same statistics as the store's own check points (500 others, seed 0)
    accuracy = store.manifest["accuracy"]
    assert 0.5 * accuracy["max_error_m"] <= check["max_error_m"] <= 2.0 * accuracy["max_error_m"]
    assert 0.75 * accuracy["rms_error_m"] <= check["rms_error_m"] <= 1.33 * accuracy["rms_error_m"]

    text = invoke(info_main, [model_store, "--check-against", model_file, "--points", points])
    assert text.exit_code == 0, text.output
    assert f"max {check['max_error_m']:.4f} m, RMS {check['rms_error_m']:.4f} m" in text.stdout
    assert "2,000 random points" in text.stdout

    # F477's conventions add N0 = −0.53 m to the model (the other constants hardly
    # differ): at the same points the store is then 0.53 m further above it
    f477 = invoke(info_main, [model_store, "--check-against", model_file, "--points", points, "--preset",
                              "nga-f477", "--json"])
    other = json.loads(f477.stdout)["check_against"]
    assert other["preset"] == "nga-f477"
    assert abs(other["mean_error_m"] - check["mean_error_m"] - 0.53) < 0.005


def test_info_check_against_usage_errors(model_store, tmp_path):
    result = invoke(info_main, [model_store, "--correction", tmp_path / "c.gz"])
    assert result.exit_code == 2 and "--check-against" in result.stderr
    result = invoke(info_main, [model_store, "--check-against", tmp_path / "missing.gfc"])
    assert_user_error(result)
    assert "missing.gfc" in result.stderr
