"""Tests of geoidspline.sources.harmonics and geoidspline.geodesy.

Independent references: closed forms (normal field, P̄nm of low degree, T of one-term
models), Gauss-Legendre quadrature, pyshtools (P̄nm and point synthesis; tests only),
pyproj (ellipsoid geometry), and NGA's own products in /work/shared/data (skipped when
absent).
"""

from __future__ import annotations

import gzip
import hashlib
import math
import re
import warnings
from pathlib import Path

import numpy as np
import pyproj
import pytest
from reference_data import REFERENCE_DATA

from geoidspline._kernels import legendre
from geoidspline.errors import CoordinateError, InputFileError
from geoidspline.geodesy.ellipsoids import GRS80, PERMANENT_TIDE, WGS84
from geoidspline.sources.base import GeoidSource, NodeSample
from geoidspline.sources.harmonics import (
    CorrectionModel,
    GeoidSynthesis,
    HarmonicModel,
    TideSystemWarning,
    read_icgem,
    read_model,
    read_nga,
    read_nga_correction,
)
from geoidspline.sources.harmonics.synthesis import NGA_WGS84_J
from geoidspline.sphere.region import GLOBAL, Region

DATA = REFERENCE_DATA
EGM96 = DATA / "egm96" / "egm96_to360.ascii.gz"
CORRCOEF = DATA / "egm96" / "CORRCOEF.gz"
DAC = DATA / "egm96" / "WW15MGH.DAC"
GFC2008 = DATA / "egm2008" / "EGM2008_120.gfc"
NGA2008 = DATA / "egm2008" / "EGM2008_to2190_TideFree_first30.ascii.gz"

needs_egm96 = pytest.mark.skipif(
    not (EGM96.is_file() and CORRCOEF.is_file()),
    reason=f"NGA EGM96 files not found under {DATA} (shared reference data absent)",
)
needs_dac = pytest.mark.skipif(not DAC.is_file(), reason=f"{DAC} not found (shared reference data absent)")
needs_egm2008 = pytest.mark.skipif(
    not (GFC2008.is_file() and NGA2008.is_file()),
    reason=f"EGM2008 excerpts not found under {DATA} (shared reference data absent)",
)

# EGM2008's C̄20 (NGA EGM2008 page; IERS Conventions 2010 Table 6.2 rounds them to
# -0.48416531e-3 tide free and -0.48416948e-3 zero tide).
C20_2008_TIDE_FREE = -0.484165143790815e-3
C20_2008_ZERO_TIDE = -0.484169317366974e-3


# ----------------------------------------------------------------------------- helpers


def ecef_geometry(lat, lon, ellps="WGS84"):
    """Geocentric radius (m) and latitude ψ (rad) of ellipsoid points, via PROJ."""
    crs = pyproj.CRS.from_proj4(f"+proj=longlat +ellps={ellps} +no_defs")
    ecef = pyproj.CRS.from_proj4(f"+proj=geocent +ellps={ellps} +no_defs")
    tr = pyproj.Transformer.from_crs(crs, ecef, always_xy=True)
    lat = np.atleast_1d(np.asarray(lat, float))
    lon = np.atleast_1d(np.asarray(lon, float))
    x, y, z = tr.transform(lon, lat, np.zeros(lat.shape))
    return np.sqrt(x * x + y * y + z * z), np.arctan2(z, np.hypot(x, y))


def small_model(nmax, coeffs, gm=3.986004415e14, radius=6378136.3, tide="tide_free", name="synthetic"):
    C = np.zeros((nmax + 1, nmax + 1))
    S = np.zeros((nmax + 1, nmax + 1))
    for (n, m), (c, s) in coeffs.items():
        C[n, m] = c
        S[n, m] = s
    return HarmonicModel(name=name, gm=gm, radius=radius, max_degree=nmax, tide_system=tide, C=C, S=S)


def write(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


GFC_HEADER = """free text before the header
begin_of_head ======
product_type     gravity_field
modelname        TESTMODEL
earth_gravity_constant  3.986004415E+14
radius           6378136.3
max_degree       3
norm             fully_normalized
tide_system      tide_free
errors           formal
key  L  M  C  S  sigmaC sigmaS
end_of_head ======
"""
GFC_LINES = [
    "gfc 0 0 1.0 0.0 0.0 0.0",
    "gfc 2 0 -0.484165E-03 0.0 1e-11 0.0",
    "gfc 2 1 -0.2D-09 0.13D-08 1e-11 1e-11",
    "gfc 2 2 0.24D-05 -0.14D-05 1e-11 1e-11",
    "gfc 3 0 0.95E-06 0.0 1e-11 0.0",
    "gfc 3 1 0.20E-05 0.25E-06 1e-11 1e-11",
    "gfc 3 2 0.90E-06 -0.62E-06 1e-11 1e-11",
    "gfc 3 3 0.72E-06 0.14E-05 1e-11 1e-11",
]
FIRST_DATA_LINE = GFC_HEADER.count("\n") + 1  # line number of GFC_LINES[0]


def gfc_text(lines=GFC_LINES, header=GFC_HEADER):
    return header + "\n".join(lines) + "\n"


# ----------------------------------------------------------------------------- constants


def test_wgs84_normal_field_reproduces_published_values():
    # geometry straight from PROJ
    geod = pyproj.Geod(ellps="WGS84")
    assert (WGS84.a, WGS84.f) == (geod.a, geod.f)
    assert WGS84.gm == 3.986004418e14 and WGS84.omega == 7.292115e-5
    # NIMA TR8350.2 / NGA F477: J2, C̄20, γe, k, e²
    assert WGS84.J(2) == pytest.approx(0.108262982131e-2, rel=1e-11)
    assert WGS84.zonal_cbar(2) == pytest.approx(-0.484166774985e-3, rel=1e-12)
    assert WGS84.gamma_e == pytest.approx(9.7803253359, abs=1e-10)
    assert WGS84.gamma_p == pytest.approx(9.8321849378, abs=1e-10)
    assert WGS84.k == pytest.approx(0.00193185265246, abs=5e-15)  # printed to 14 decimals
    assert WGS84.e2 == pytest.approx(0.00669437999013, abs=2e-14)  # NGA truncated it to 14 decimals
    # F477's literal J4..J10 (printed to 12 digits)
    for n in (4, 6, 8, 10):
        assert WGS84.J(n) == pytest.approx(NGA_WGS84_J[n], rel=1e-10)
    assert WGS84.zonal_cbar(3) == 0.0
    # Somigliana: equator and pole values
    assert WGS84.normal_gravity(0.0) == pytest.approx(WGS84.gamma_e, rel=1e-15)
    assert WGS84.normal_gravity(1.0) == pytest.approx(WGS84.gamma_p, rel=1e-14)


def test_grs80_normal_field_reproduces_moritz_2000():
    assert (GRS80.a, GRS80.f) == (pyproj.Geod(ellps="GRS80").a, pyproj.Geod(ellps="GRS80").f)
    assert GRS80.J(2) == pytest.approx(108263e-8, rel=1e-9)  # defining constant
    assert GRS80.gamma_e == pytest.approx(9.7803267715, abs=1e-10)
    assert GRS80.gamma_p == pytest.approx(9.8321863685, abs=1e-10)
    assert GRS80.k == pytest.approx(0.001931851353, abs=1e-12)
    assert GRS80.u0 == pytest.approx(62636860.850, abs=1e-3)


def test_permanent_tide_conversion_reproduces_egm2008_pair():
    zt = PERMANENT_TIDE.convert_c20(C20_2008_TIDE_FREE, "tide_free", "zero_tide")
    assert zt == pytest.approx(C20_2008_ZERO_TIDE, abs=1e-14)
    assert PERMANENT_TIDE.convert_c20(zt, "zero_tide", "tide_free") == pytest.approx(C20_2008_TIDE_FREE, abs=1e-18)
    # the zero-tide (and more so the mean-tide) Earth is the more flattened one
    mt = PERMANENT_TIDE.convert_c20(C20_2008_TIDE_FREE, "tide_free", "mean_tide")
    assert mt < zt < C20_2008_TIDE_FREE
    assert mt - zt == pytest.approx(-1.39119e-8, rel=1e-12)


def test_harmonic_model_tide_conversion_changes_only_c20():
    model = small_model(3, {(2, 0): (C20_2008_TIDE_FREE, 0.0), (3, 1): (1e-6, 2e-6)})
    zt = model.with_tide_system("zero_tide")
    assert zt.tide_system == "zero_tide"
    assert zt.C[2, 0] == pytest.approx(C20_2008_ZERO_TIDE, abs=1e-14)
    changed = np.argwhere(zt.C != model.C)
    assert changed.tolist() == [[2, 0]]
    assert np.array_equal(zt.S, model.S)
    back = zt.with_tide_system("mean_tide").with_tide_system("tide_free")
    assert back.C[2, 0] == pytest.approx(model.C[2, 0], abs=1e-18)
    assert model.with_tide_system("tide_free") is model
    with pytest.raises(ValueError):
        model.with_tide_system("no_tide")
    with pytest.raises(ValueError):
        HarmonicModel("x", 1.0, 1.0, 2, None, np.zeros((3, 3)), np.zeros((3, 3))).with_tide_system("zero_tide")
    with pytest.raises(ValueError):  # frozen arrays
        model.C[2, 0] = 0.0


# ----------------------------------------------------------------------------- Legendre


def plm(nmax, lat_deg, u_from_t=True):
    AT, BT = legendre.recursion_tables(nmax)
    out = np.zeros((nmax + 1, nmax + 1))
    t = math.sin(math.radians(lat_deg))
    # pyshtools derives u from t; near the poles that costs digits, so the closed-form
    # test passes cos(latitude) instead
    u = math.sqrt((1.0 - t) * (1.0 + t)) if u_from_t else math.cos(math.radians(lat_deg))
    legendre.plm_bar(nmax, t, u, AT, BT, out)
    return out


@pytest.mark.parametrize("sets", [1, 2])
def test_legendre_sums_are_those_of_one_latitude_whatever_the_thread_count(sets):
    """row_sums and point_sums run rows and points on several threads: each row is
    column_sums of its latitude, bit for bit, with 1 thread or 3 (more than the rows of
    the last point batch), so fits do not depend on the machine."""
    from geoidspline._kernels import _clib

    nmax = 120
    rng = np.random.default_rng(5)
    AT, BT = legendre.recursion_tables(nmax)
    n = np.arange(nmax + 1)
    CT = np.triu(rng.standard_normal((sets, nmax + 1, nmax + 1)) / (n + 1.0) ** 2)
    ST = np.triu(rng.standard_normal((sets, nmax + 1, nmax + 1)) / (n + 1.0) ** 2)
    radial = np.array([True, False][:sets])
    lat = np.radians(np.array([-90.0, -89.99, -45.0, 0.0, 12.5, 60.0, 89.9, 90.0]))
    t, u = np.sin(lat), np.cos(lat)
    u[[0, -1]] = 0.0
    q = 1.0 - 0.01 * rng.random(lat.size)
    scale = 0.5 + rng.random((lat.size, sets))
    lam = rng.uniform(0.0, 2.0 * np.pi, lat.size)
    A1, B1 = np.empty((lat.size, nmax + 1)), np.empty((lat.size, nmax + 1))
    w = np.empty((sets, nmax + 1))
    for i in range(lat.size):
        legendre.column_sums(nmax, t[i], u[i], q[i], scale[i], radial, CT, ST, AT, BT, A1[i], B1[i], w)
    cos_sin = np.cos(np.outer(lam, n)), np.sin(np.outer(lam, n))
    previous = _clib.threads()
    try:
        for count in (1, 3):
            _clib.set_threads(count)
            A, B = np.empty_like(A1), np.empty_like(B1)
            legendre.row_sums(nmax, t, u, q, scale, radial, CT, ST, AT, BT, A, B)
            assert np.array_equal(A, A1) and np.array_equal(B, B1)
            out = np.empty(lat.size)
            legendre.point_sums(nmax, t, u, q, lam, scale, radial, CT, ST, AT, BT, out)
            np.testing.assert_allclose(out, (A1 * cos_sin[0] + B1 * cos_sin[1]).sum(axis=1), rtol=1e-12, atol=1e-12)
            if count == 1:
                serial = out
            assert np.array_equal(out, serial)
    finally:
        _clib.set_threads(previous)


@pytest.mark.parametrize("lat", [-73.2, -5.0, 0.0, 31.7, 88.0])
def test_legendre_low_degree_closed_forms(lat):
    p = plm(3, lat, u_from_t=False)
    x = math.sin(math.radians(lat))
    c = math.cos(math.radians(lat))
    expected = {
        (0, 0): 1.0,
        (1, 0): math.sqrt(3) * x,
        (1, 1): math.sqrt(3) * c,
        (2, 0): math.sqrt(5) * (3 * x * x - 1) / 2,
        (2, 1): math.sqrt(15) * x * c,
        (2, 2): math.sqrt(15 / 4) * c * c,
        (3, 0): math.sqrt(7) * (5 * x**3 - 3 * x) / 2,
        (3, 3): math.sqrt(35 / 8) * c**3,
    }
    for (n, m), value in expected.items():
        assert p[n, m] == pytest.approx(value, rel=1e-14, abs=1e-15), (n, m)


def test_legendre_orthonormality_by_quadrature():
    nmax = 60
    x, w = np.polynomial.legendre.leggauss(nmax + 2)  # exact for polynomials of degree 2·nmax+3
    AT, BT = legendre.recursion_tables(nmax)
    table = np.zeros((x.size, nmax + 1, nmax + 1))
    for i, t in enumerate(x):
        legendre.plm_bar(nmax, t, math.sqrt((1 - t) * (1 + t)), AT, BT, table[i])
    for m in range(0, nmax + 1, 7):
        block = table[:, m:, m]  # P̄nm for n = m..nmax
        gram = block.T @ (w[:, None] * block)
        expected = 2.0 * (2.0 - (m == 0)) * np.eye(nmax + 1 - m)
        np.testing.assert_allclose(gram, expected, atol=2e-12)


@pytest.mark.parametrize("lat", [0.0, 45.0, 80.0, 89.0, 89.9, 89.9999, 90.0, -89.99])
def test_legendre_degree_2190_stable_and_equal_to_pyshtools(lat):
    pyshtools = pytest.importorskip("pyshtools")
    nmax = 2190
    ours = plm(nmax, lat)
    assert np.isfinite(ours).all()
    n_idx, m_idx = np.tril_indices(nmax + 1)
    theirs = pyshtools.legendre.PlmBar(nmax, math.sin(math.radians(lat)), csphase=1)  # csphase=1: no CS phase
    mine = ours[n_idx, m_idx]
    scale = np.sqrt(2.0 * (2 * n_idx + 1))  # |P̄nm| ≤ √(2(2n+1))
    assert np.all(np.abs(mine) <= scale * (1 + 1e-12))
    # pyshtools flushes values below ~1e-280 to zero; compare everything else
    np.testing.assert_array_less(np.abs(mine - theirs) / scale, 1e-10)
    big = np.abs(theirs) > 0.1
    np.testing.assert_array_less(np.abs(mine[big] - theirs[big]) / np.abs(theirs[big]), 1e-9)
    # sectoral values: cos(ψ)^2190 is representable only near the equator
    if lat == 0.0:
        assert ours[nmax, nmax] == pytest.approx(theirs[-1], rel=1e-12) and ours[nmax, nmax] > 1.0


def test_fold_to_circle_handles_aliasing():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(2, 13))
    B = rng.normal(size=(2, 13))
    for L in (7, 8, 24, 25):
        lam = 2 * np.pi * np.arange(L) / L
        m = np.arange(13)[:, None]
        direct = A @ np.cos(m * lam) + B @ np.sin(m * lam)
        np.testing.assert_allclose(legendre.fold_to_circle(A, B, L), direct, atol=1e-12)


# ----------------------------------------------------------------------------- synthesis, closed forms


def test_one_term_models_match_closed_form_potential():
    """Generic preset, GRS80: T of a degree-2 model whose C̄20 differs from the rescaled
    normal C̄20 by δ, plus C̄21/S̄21/C̄22/S̄22."""
    gm, radius = 3.986004415e14, 6378136.3
    ell = GRS80
    c20_normal = (ell.gm / gm) * (ell.a / radius) ** 2 * ell.zonal_cbar(2)
    d20, c21, s21, c22, s22 = 3.1e-7, -2.0e-9, 1.4e-9, 2.43914e-6, -1.40017e-6
    model = small_model(2, {(2, 0): (c20_normal + d20, 0.0), (2, 1): (c21, s21), (2, 2): (c22, s22)}, gm, radius)
    syn = GeoidSynthesis(model, ellipsoid=ell, preset="generic", zero_degree_term_m=0.25)
    rng = np.random.default_rng(11)
    lat = np.r_[rng.uniform(-90, 90, 40), 90.0, -90.0, 0.0]
    lon = np.r_[rng.uniform(-180, 540, 40), 0.0, 123.0, -180.0]
    r, psi = ecef_geometry(lat, lon, "GRS80")
    x, c = np.sin(psi), np.cos(psi)
    lam = np.radians(lon)
    p20 = math.sqrt(5) * (3 * x * x - 1) / 2
    p21 = math.sqrt(15) * x * c
    p22 = math.sqrt(15 / 4) * c * c
    expected_T = gm / r * (radius / r) ** 2 * (
        d20 * p20 + p21 * (c21 * np.cos(lam) + s21 * np.sin(lam)) + p22 * (c22 * np.cos(2 * lam) + s22 * np.sin(2 * lam))
    )
    T = syn.disturbing_potential(lat, lon)
    np.testing.assert_allclose(T, expected_T, rtol=1e-12, atol=1e-12 * np.abs(expected_T).max())
    gamma = ell.normal_gravity(np.sin(np.radians(lat)) ** 2)
    np.testing.assert_allclose(syn.height_anomaly(lat, lon), expected_T / gamma, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(syn.undulation(lat, lon), expected_T / gamma + 0.25, rtol=1e-12, atol=1e-14)


def test_model_equal_to_normal_field_has_no_disturbing_potential():
    # a model (with EGM96's GM and a) that is the WGS84 normal field rescaled to them
    nmax, gm, radius = 20, 3.986004415e14, 6378136.3
    coeffs = {(n, 0): ((WGS84.gm / gm) * (WGS84.a / radius) ** n * WGS84.zonal_cbar(n), 0.0) for n in range(2, nmax + 1, 2)}
    model = small_model(nmax, coeffs, gm=gm, radius=radius)
    syn = GeoidSynthesis(model, preset="generic")
    lat = np.linspace(-90, 90, 37)
    T = syn.disturbing_potential(lat, 17.0)
    assert np.abs(T).max() < 1e-9  # m²/s²: normal zonals to 1e-12 of 0.3·GM/a
    assert np.abs(syn.undulation(lat, 17.0)).max() < 1e-10


def test_f477_scales_by_wgs84_and_hsynth_by_the_model():
    gm, radius = 3.986004415e14, 6378136.3
    c22 = 2.4e-6
    model = small_model(2, {(2, 2): (c22, 0.0)}, gm, radius)
    lat, lon = 33.0, 21.0
    r, psi = ecef_geometry(lat, lon)
    r, psi = float(r[0]), float(psi[0])
    p20 = math.sqrt(5) * (3 * math.sin(psi) ** 2 - 1) / 2
    p22 = math.sqrt(15 / 4) * math.cos(psi) ** 2
    j2term = NGA_WGS84_J[2] / math.sqrt(5)  # C̄20 of the model is 0: T = −normal C̄20 term
    gm84, a84 = 3.986004418e14, 6378137.0
    f477 = GeoidSynthesis(model, preset="nga-f477").disturbing_potential(lat, lon)
    expected = gm84 / r * (a84 / r) ** 2 * (j2term * p20 + c22 * p22 * math.cos(2 * math.radians(lon)))
    assert f477 == pytest.approx(expected, rel=1e-12)
    hsynth = GeoidSynthesis(model, preset="nga-hsynth").disturbing_potential(lat, lon)
    rescaled = (gm84 / gm) * (a84 / radius) ** 2 * j2term
    expected = gm / r * (radius / r) ** 2 * (rescaled * p20 + c22 * p22 * math.cos(2 * math.radians(lon)))
    assert hsynth == pytest.approx(expected, rel=1e-12)
    syn = GeoidSynthesis(model, preset="nga-hsynth")
    assert syn.zero_degree_term_m == -0.41
    with pytest.raises(ValueError):
        GeoidSynthesis(model, ellipsoid=GRS80, preset="nga-f477")
    with pytest.raises(ValueError):
        GeoidSynthesis(model, preset="f477")
    with pytest.raises(ValueError):
        GeoidSynthesis(model, max_degree=3)


def test_correction_is_summed_without_radial_factor_in_its_unit():
    # C̄20 of the normal field itself, so that N stays within the geoid's physical range
    model = small_model(2, {(2, 0): (WGS84.zonal_cbar(2), 0.0)}, gm=WGS84.gm, radius=WGS84.a)
    C = np.zeros((3, 3))
    S = np.zeros((3, 3))
    C[0, 0], C[1, 1], S[2, 1] = 12.0, -3.0, 5.0  # centimetres
    corr = CorrectionModel("corr", 2, C, S, unit_m=0.01)
    syn = GeoidSynthesis(model, corr, preset="generic", zero_degree_term_m=0.0)
    syn0 = GeoidSynthesis(model, preset="generic", zero_degree_term_m=0.0)
    lat, lon = np.array([-40.0, 10.0, 75.0]), np.array([5.0, 100.0, -120.0])
    _, psi = ecef_geometry(lat, lon)
    x, c = np.sin(psi), np.cos(psi)
    lam = np.radians(lon)
    expected = 0.01 * (12.0 - 3.0 * math.sqrt(3) * c * np.cos(lam) + 5.0 * math.sqrt(15) * x * c * np.sin(lam))
    np.testing.assert_allclose(syn.undulation(lat, lon) - syn0.undulation(lat, lon), expected, atol=1e-14)


# ----------------------------------------------------------------------------- API behaviour


@pytest.fixture(scope="module")
def toy():
    rng = np.random.default_rng(7)
    nmax = 40
    coeffs = {}
    for n in range(2, nmax + 1):
        for m in range(n + 1):
            s = 0.0 if m == 0 else rng.normal() * 1e-6 / n**2
            coeffs[(n, m)] = (rng.normal() * 1e-6 / n**2, s)
    coeffs[(2, 0)] = (-0.484165371736e-3, 0.0)
    return GeoidSynthesis(small_model(nmax, coeffs), preset="nga-hsynth")


def test_undulation_scalars_nan_and_range(toy):
    value = toy.undulation(12.5, 33.0)
    assert isinstance(value, float)
    assert toy.undulation(12.5, 33.0 + 360.0) == pytest.approx(value, abs=1e-12)
    assert toy.undulation(12.5, 33.0 - 720.0) == pytest.approx(value, abs=1e-12)
    arr = toy.undulation(np.array([[12.5, np.nan], [0.0, 90.0]]), np.array([33.0, 1.0]))
    assert arr.shape == (2, 2)
    assert arr[0, 0] == pytest.approx(value, abs=1e-12)
    assert np.isnan(arr[0, 1]) and np.isfinite(arr[1]).all()
    assert np.isnan(toy.undulation(0.0, np.nan))
    # at the poles the value does not depend on longitude
    assert toy.undulation(90.0, 0.0) == pytest.approx(toy.undulation(90.0, 77.0), abs=1e-12)
    with pytest.raises(CoordinateError):
        toy.undulation(90.0001, 0.0)
    with pytest.raises(CoordinateError):
        toy.undulation([0.0, -91.0], [0.0, 0.0])
    with pytest.raises(CoordinateError):
        toy.undulation(0.0, np.inf)
    with pytest.raises(CoordinateError):
        toy.undulation(np.zeros(3), np.zeros(2))


def test_nodes_lattice_equals_point_synthesis(toy):
    # a region across the antimeridian (few columns: direct longitude sums) ...
    region = Region(-12.3, 170.2, 7.9, -171.1)
    sample = toy.nodes(region, 0.5)
    assert isinstance(sample, NodeSample)
    step = toy.lattice_step(0.5)
    assert step == 0.5
    assert np.all(np.diff(sample.longitude) > 0) and np.all(np.diff(sample.latitude) > 0)
    assert sample.latitude[0] <= region.south and sample.latitude[-1] >= region.north
    assert sample.longitude[0] <= region.west and sample.longitude[-1] >= region.east
    assert sample.longitude[-1] > 180.0
    la, lo = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    np.testing.assert_allclose(sample.undulation, toy.undulation(la, lo), rtol=0, atol=1e-9)
    # ... and the whole sphere (FFT path), poles included
    full = toy.nodes(GLOBAL, 7.0)
    step = toy.lattice_step(7.0)
    assert step <= 7.0 and (180.0 / step) == round(180.0 / step) and (360.0 / step) == round(360.0 / step)
    assert full.latitude[0] == -90.0 and full.latitude[-1] == 90.0
    assert full.longitude[0] == -180.0 and full.longitude[-1] == 180.0
    la, lo = np.meshgrid(full.latitude, full.longitude, indexing="ij")
    np.testing.assert_allclose(full.undulation, toy.undulation(la, lo), rtol=0, atol=1e-9)
    np.testing.assert_allclose(full.undulation[:, 0], full.undulation[:, -1], atol=1e-9)


def test_default_lattice_and_protocol(toy):
    assert toy.lattice_step() == pytest.approx(90.0 / 40)
    assert toy.lattice_step(5 / 60) == pytest.approx(5 / 60)
    assert toy.lattice_step(0.3) == pytest.approx(180 / 600)
    with pytest.raises(ValueError):
        toy.lattice_step(0.0)
    assert isinstance(toy, GeoidSource)
    assert toy.extent.is_global
    prov = toy.provenance
    assert prov.kind == "harmonic" and prov.model == "synthetic"
    assert prov.zero_degree_term_m == -0.41 and prov.tide_system == "tide_free"
    assert any("no zeta-to-N correction" in note for note in prov.notes)


# ----------------------------------------------------------------------------- EGM96 (real data)


@pytest.fixture(scope="module")
def egm96():
    if not (EGM96.is_file() and CORRCOEF.is_file()):
        pytest.skip(f"NGA EGM96 files not found under {DATA}")
    model = read_nga(EGM96)
    corr = read_nga_correction(CORRCOEF)
    return model, corr, GeoidSynthesis(model, corr, preset="nga-f477")


@needs_egm96
def test_egm96_files_read_as_documented(egm96):
    model, corr, syn = egm96
    assert (model.name, model.gm, model.radius, model.max_degree, model.tide_system) == (
        "EGM96", 3.986004415e14, 6378136.3, 360, "tide_free",
    )
    assert model.C[2, 0] == -0.484165371736e-03 and model.C[2, 2] == 0.243914352398e-05
    assert model.C[360, 360] == -0.447516389678e-24 and model.S[360, 360] == -0.830224945525e-10
    assert model.sigma_C[2, 0] == 0.35610635e-10
    assert model.sha256 == hashlib.sha256(EGM96.read_bytes()).hexdigest()
    assert model.sha256.startswith("c4f9afff1b74bbf3")
    assert corr.max_degree == 360 and corr.unit_m == 0.01
    assert corr.C[0, 0] == pytest.approx(-5.02745269977, abs=1e-11)
    prov = syn.provenance
    assert (prov.kind, prov.model, prov.tide_system, prov.zero_degree_term_m) == ("harmonic", "EGM96", "tide_free", -0.53)
    assert prov.sha256 == model.sha256
    assert any(corr.sha256 in note for note in prov.notes)


@needs_egm96
def test_egm96_disturbing_potential_matches_pyshtools(egm96):
    pyshtools = pytest.importorskip("pyshtools")
    model, _, syn = egm96
    nmax = 360
    cilm = np.zeros((2, nmax + 1, nmax + 1))
    cilm[0], cilm[1] = model.C, model.S
    for n, j in NGA_WGS84_J.items():  # F477: C̄n0 + Jn/√(2n+1)
        cilm[0, n, 0] += j / math.sqrt(2 * n + 1)
    cilm[:, :2, :] = 0.0
    gm84, a84 = 3.986004418e14, 6378137.0
    rng = np.random.default_rng(2024)
    lat = np.r_[np.degrees(np.arcsin(rng.uniform(-1, 1, 12))), 89.99, -89.999, 0.0]
    lon = np.r_[rng.uniform(-180, 180, 12), 10.0, 200.0, 0.0]
    r, psi = ecef_geometry(lat, lon)
    degree = np.arange(nmax + 1)[None, :, None]
    expected = np.array([
        gm84 / ri * pyshtools.expand.MakeGridPoint(cilm * (a84 / ri) ** degree, math.degrees(p), lo, norm=1, csphase=1)
        for ri, p, lo in zip(r, psi, lon)
    ])
    T = syn.disturbing_potential(lat, lon)
    np.testing.assert_allclose(T, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@needs_egm96
@needs_dac
def test_egm96_f477_reproduces_nga_15min_grid(egm96):
    """WW15MGH.DAC holds NGA's 15' grid in cm. Its values behave exactly like
    rint(g·100) of the mm-rounded values g of WW15MGH.GRD (text, metres to 3 decimals;
    rint rounds float ties to even): so every node agrees to ≤ 5.5 mm, and, more sharply,
    rint(round_mm(N)·100) reproduces the file except where N lies within a few µm of a
    half-millimetre boundary, i.e. the synthesis equals NGA's to a few µm."""
    _, _, syn = egm96
    dac = np.fromfile(DAC, dtype=">i2").reshape(721, 1440).astype(np.int64)
    sample = syn.nodes(GLOBAL, 0.25)
    assert sample.undulation.shape == (721, 1441)
    ours = sample.undulation[::-1][:, np.r_[720:1440, 0:720]]  # 90N→90S, 0→359.75E
    assert sample.longitude[720] == 0.0 and sample.latitude[-1] == 90.0
    diff_mm = (ours - dac / 100.0) * 1000.0
    assert np.abs(diff_mm).max() <= 5.5 + 0.005  # half a cm + half a mm (double rounding) + 5 µm
    assert math.sqrt(np.mean(diff_mm**2)) < 3.0  # cm quantisation alone gives 2.9 mm
    mm = np.rint(ours * 1000.0)
    cm = np.rint(mm / 1000.0 * 100.0).astype(np.int64)
    mismatch = cm != dac
    off_boundary = np.abs(np.mod(ours * 1000.0, 1.0) - 0.5)  # mm from the nearest half-mm
    assert mismatch.sum() < 200  # of 1,038,240
    assert off_boundary[mismatch].max() < 0.005  # i.e. NGA's values and ours agree to < 5 µm there
    # the per-point synthesis at 200 random nodes gives the same
    rng = np.random.default_rng(96)
    rows, cols = rng.integers(0, 721, 200), rng.integers(0, 1440, 200)
    point = syn.undulation(90.0 - rows * 0.25, cols * 0.25)
    assert np.abs(point - dac[rows, cols] / 100.0).max() <= 0.0055 + 5e-6
    np.testing.assert_allclose(point, ours[rows, cols], atol=1e-9)


@needs_egm96
def test_egm96_against_nga_readme_points(egm96):
    """NGA_EGM96_README.TXT prints INTPT's output: values interpolated (spline) from the
    15' grid, in metres to 3 decimals, and intpt_OUTINTPT.DAT adds 4 nodes of that grid.
    At the grid nodes INTPT returns the grid value, so the synthesis must agree to the
    printed rounding (0.5 mm); between nodes the interpolation adds up to ~3 mm."""
    _, _, syn = egm96
    readme = [
        (38.628155, 269.779155, -31.628),
        (-14.621217, 305.021114, -2.969),
        (46.874319, 102.448729, -43.575),
        (-23.617446, 133.874712, 15.871),
        (38.625473, 359.999500, 50.066),
        (-0.466744, 0.002300, 17.329),
    ]
    nodes = [(38.0, 360.0, 49.156), (-38.0, 360.0, 16.597), (89.0, 360.0, 15.452), (-89.0, 360.0, -27.880)]
    lat, lon, printed = np.array(readme + nodes).T
    diff = syn.undulation(lat, lon) - printed
    np.testing.assert_array_less(np.abs(diff[:6]), 0.0035)  # interpolated: measured ≤ 3.24 mm
    np.testing.assert_array_less(np.abs(diff[6:]), 0.0005)  # grid nodes: printed rounding only
    assert syn.undulation(0.0, 0.0) == pytest.approx(17.16, abs=0.005)  # the data README's N(0,0)
    assert syn.undulation(90.0, 0.0) == pytest.approx(13.61, abs=0.005)
    assert syn.undulation(-90.0, 0.0) == pytest.approx(-29.53, abs=0.005)


# ----------------------------------------------------------------------------- EGM2008 excerpts


@needs_egm2008
def test_egm2008_gfc_reads_with_tide_check():
    with warnings.catch_warnings():
        warnings.simplefilter("error", TideSystemWarning)
        model = read_icgem(GFC2008)
    assert (model.name, model.max_degree, model.gm, model.radius) == ("EGM2008", 120, 3.986004415e14, 6378136.3)
    # its C̄20 is EGM2008's tide-free value, as its header says
    assert model.C[2, 0] == C20_2008_TIDE_FREE and model.tide_system == "tide_free"
    assert any("C̄20 checked" in note for note in model.notes)
    assert model.sigma_C[2, 0] == 0.7481239490e-11
    assert read_model(GFC2008).C[120, 120] == model.C[120, 120]
    # NGA's excerpt named "TideFree" holds the zero-tide C̄20: warned about and relabelled
    with pytest.warns(TideSystemWarning, match="zero_tide"):
        excerpt = read_nga(NGA2008, max_degree=6)
    assert excerpt.tide_system == "zero_tide" and excerpt.C[2, 0] == C20_2008_ZERO_TIDE
    assert any("NGA's file name says tide_free" in note for note in excerpt.notes)
    same = excerpt.C[2:].copy()
    same[0, 0] = model.C[2, 0]
    np.testing.assert_array_equal(same, model.C[2:7, :7])
    np.testing.assert_array_equal(excerpt.S[2:], model.S[2:7, :7])
    # converting the excerpt back to tide free gives the gfc's value
    assert excerpt.with_tide_system("tide_free").C[2, 0] == pytest.approx(model.C[2, 0], abs=1e-14)
    syn = GeoidSynthesis(model, preset="nga-hsynth")
    values = syn.nodes(GLOBAL, 3.0).undulation
    assert -110 < values.min() < -95 and 80 < values.max() < 90  # EGM2008 N range to degree 120


def test_icgem_header_tide_label_contradicted_by_c20(tmp_path):
    lines = list(GFC_LINES)
    lines[1] = f"gfc 2 0 {C20_2008_ZERO_TIDE!r} 0.0 1e-11 0.0"
    path = write(tmp_path / "egm2008_bad.gfc", gfc_text(lines, GFC_HEADER.replace("TESTMODEL", "EGM2008")))
    with pytest.warns(TideSystemWarning, match=r"egm2008_bad\.gfc.*zero_tide"):
        model = read_icgem(path)
    assert model.tide_system == "zero_tide"
    assert model.notes and "tide_free" in model.notes[0]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert read_icgem(path, check_tide_system=False).tide_system == "tide_free"


# ----------------------------------------------------------------------------- readers: good and malformed


def test_icgem_reader_parses_fortran_exponents_gzip_and_truncation(tmp_path):
    path = write(tmp_path / "m.gfc", gfc_text())
    model = read_icgem(path)
    assert (model.name, model.gm, model.radius, model.max_degree, model.tide_system) == (
        "TESTMODEL", 3.986004415e14, 6378136.3, 3, "tide_free",
    )
    assert model.C[2, 1] == -0.2e-9 and model.S[2, 1] == 0.13e-8 and model.S[3, 3] == 0.14e-5
    assert model.sigma_C[2, 1] == 1e-11
    gz = tmp_path / "m.gfc.gz"
    gz.write_bytes(gzip.compress(path.read_bytes()))
    zipped = read_model(gz)
    np.testing.assert_array_equal(zipped.C, model.C)
    assert zipped.sha256 == hashlib.sha256(gz.read_bytes()).hexdigest() != model.sha256
    cut = read_icgem(path, max_degree=2)
    assert cut.max_degree == 2 and cut.C.shape == (3, 3)


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda L: L[:5], r"3 coefficient\(s\) missing .*\(n=3, m=1\), \(n=3, m=2\), \(n=3, m=3\)"),
        (lambda L: L[:5] + ["gfc 3 1 0.20E-05"], r"line {l5}: expected 'gfc n m C S"),
        (lambda L: L[:4] + ["gfct 3 0 0.95E-06 0.0 1e-11 0.0 20050101"] + L[5:], r"line {l4}: time-variable .*'gfct'"),
        (lambda L: L[:6] + L[7:], r"missing .*\(n=3, m=2\)"),
        (lambda L: L + ["gfc 3 2 0.90E-06 -0.62E-06 1e-11 1e-11"], r"line {l8}: duplicate coefficient n=3 m=2 \(first on line {l6}\)"),
        (lambda L: L[:3] + ["gfc 2 2 0.24X-05 -0.14D-05 1e-11 1e-11"] + L[4:], r"line {l3}: C '0.24X-05' is not a number"),
        (lambda L: L[:3] + ["gfc 2 x 0.24D-05 -0.14D-05 1e-11 1e-11"] + L[4:], r"line {l3}: order m 'x' is not an integer"),
        (lambda L: L + ["gfc 4 0 1.0 0.0 0.0 0.0"], r"line {l8}: degree 4 exceeds the header's max_degree 3"),
        (lambda L: L[:1] + ["gfc 2 3 1.0 0.0 0.0 0.0"] + L[1:], r"line {l1}: need 0 <= m <= n"),
        (lambda L: L[:1] + ["xyz 2 0 1.0 0.0 0.0 0.0"] + L[2:], r"line {l1}: unknown data key 'xyz'"),
    ],
)
def test_icgem_reader_rejects_malformed_data(tmp_path, mutate, message):
    path = write(tmp_path / "bad.gfc", gfc_text(mutate(list(GFC_LINES))))
    lines = {f"l{i}": FIRST_DATA_LINE + i for i in range(10)}
    with pytest.raises(InputFileError) as info:
        read_icgem(path)
    text = str(info.value)
    assert text.startswith(str(path) + ": ")
    assert info.value.path == str(path)
    assert re.search(message.format(**lines), text), text


def test_icgem_reader_rejects_bad_headers(tmp_path):
    cases = [
        (GFC_HEADER.replace("end_of_head", "end_of_hea"), r"no 'end_of_head' line"),
        (GFC_HEADER.replace("fully_normalized", "unnormalized"), r"line 8: norm 'unnormalized' is not supported"),
        (GFC_HEADER.replace("radius           6378136.3\n", ""), r"header lacks the mandatory key 'radius'"),
        (GFC_HEADER.replace("tide_free", "tidy"), r"line 9: unknown tide_system 'tidy'"),
        (GFC_HEADER.replace("3.986004415E+14", "3.98600x4415E+14"), r"line 5: earth_gravity_constant '3.98600x4415E\+14' is not a number"),
    ]
    for header, message in cases:
        path = write(tmp_path / "h.gfc", gfc_text(header=header))
        with pytest.raises(InputFileError, match=str(path).replace(".", r"\.") + ": " + message):
            read_icgem(path)
    # header only, data cut off entirely
    path = write(tmp_path / "cut.gfc", GFC_HEADER)
    with pytest.raises(InputFileError, match=r"7 coefficient\(s\) missing"):
        read_icgem(path)
    with pytest.raises(InputFileError, match="file not found"):
        read_icgem(tmp_path / "nope.gfc")
    broken = tmp_path / "broken.gfc.gz"
    broken.write_bytes(gzip.compress(gfc_text().encode())[:-20])
    with pytest.raises(InputFileError, match="gzip"):
        read_icgem(broken)


def test_nga_readers_reject_malformed_files(tmp_path):
    good = "\n".join(
        f"{n:4d}{m:4d} {1e-7 * (n + m):.12E} {0.0 if m == 0 else 2e-7:.12E} 1.0E-10 1.0E-10" for n in range(2, 4) for m in range(n + 1)
    )
    path = write(tmp_path / "egm96_to360.ascii", good + "\n")
    # the name declares degree 360: a file that stops at 3 is a truncated copy ...
    with pytest.raises(InputFileError, match=r"egm96_to360\.ascii: the file name declares degree 360 but the model "
                       r"stops at degree 3: a truncated copy.*max_degree=3"):
        read_nga(path)
    model = read_nga(path, max_degree=3)  # ... unless truncated on purpose
    assert model.max_degree == 3 and model.name == "EGM96" and model.gm == 3.986004415e14
    assert any("none of the known EGM96 values" in note for note in model.notes)
    bad_cols = good.replace("   3   1 4.000000000000E-07 2.000000000000E-07 1.0E-10 1.0E-10", "   3   1 4.0E-07 2.0E-07")
    assert bad_cols != good
    path = write(tmp_path / "egm96_to360.ascii", bad_cols + "\n")
    with pytest.raises(InputFileError, match=r"egm96_to360\.ascii: line 5: expected 6 columns \(n m C S sigmaC sigmaS\), found 4"):
        read_nga(path)
    path = write(tmp_path / "egm96_to360.ascii", good.replace("4.000000000000E-07", "4.0000Q0E-07") + "\n")
    with pytest.raises(InputFileError, match=r"line 3: C '4.0000Q0E-07' is not a number"):
        read_nga(path)
    path = write(tmp_path / "mystery.txt", good + "\n")
    with pytest.raises(InputFileError, match="not one of NGA's standard file names"):
        read_nga(path)
    custom = read_nga(path, name="Mystery", gm=3.9e14, radius=6.4e6, tide_system="zero_tide")
    assert (custom.name, custom.gm, custom.tide_system) == ("Mystery", 3.9e14, "zero_tide")
    # correction coefficients: 4 columns from degree 0, every coefficient present
    corr = "\n".join(f"{n} {m} {n + 0.5 * m:.6e} {0.0 if m == 0 else -1.0:.6e}" for n in range(0, 3) for m in range(n + 1))
    path = write(tmp_path / "CORRCOEF", corr + "\n")
    cc = read_nga_correction(path)
    assert cc.max_degree == 2 and cc.C[2, 1] == 2.5 and cc.unit_m == 0.01
    path = write(tmp_path / "CORRCOEF", corr.replace("1 1 1.500000e+00 -1.000000e+00\n", "") + "\n")
    with pytest.raises(InputFileError, match=r"CORRCOEF: 1 coefficient\(s\) missing .*\(n=1, m=1\)"):
        read_nga_correction(path)
    path = write(tmp_path / "CORRCOEF", corr + "\n2 2 1.0 0.0 0.0\n")
    with pytest.raises(InputFileError, match=r"line 7: expected 4 columns"):
        read_nga_correction(path)


# ----------------------------------------------------------------------------- readers: block by block


def kaula_model(nmax, seed=5, name="EGM96"):
    """Coefficients of a Kaula-like decay (physical), EGM96's C̄20."""
    rng = np.random.default_rng(seed)
    C = np.zeros((nmax + 1, nmax + 1))
    S = np.zeros((nmax + 1, nmax + 1))
    for n in range(2, nmax + 1):
        C[n, : n + 1] = rng.normal(size=n + 1) * 1e-5 / n**2
        S[n, 1 : n + 1] = rng.normal(size=n) * 1e-5 / n**2
    C[2, 0] = -0.484165371736e-3
    return HarmonicModel(name=name, gm=3.986004415e14, radius=6378136.3, max_degree=nmax, tide_system="tide_free",
                         C=C, S=S, sigma_C=np.abs(C) * 1e-3, sigma_S=np.abs(S) * 1e-3)


def nga_lines(model):
    return [f"{n:5d}{m:5d}{model.C[n, m]:25.15E}{model.S[n, m]:25.15E}{model.sigma_C[n, m]:20.10E}"
            f"{model.sigma_S[n, m]:20.10E}" for n in range(2, model.max_degree + 1) for m in range(n + 1)]


@pytest.fixture
def small_blocks(monkeypatch):
    """Blocks of 1 kB (a few lines each), and a count of the blocks read each way."""
    from geoidspline.sources.harmonics import models

    monkeypatch.setattr(models, "_BLOCK_BYTES", 1024)
    counts = {"fast": 0, "line by line": 0}

    def counted(func, key):
        def wrapped(*args):
            result = func(*args)
            counts[key] += result is not None
            return result
        return wrapped

    monkeypatch.setattr(models, "_fast_block", counted(models._fast_block, "fast"))
    monkeypatch.setattr(models, "_slow_block", counted(models._slow_block, "line by line"))
    return counts


def float_model(lines, nmax, first=0):
    """C, S, σC, σS from the lines by Python's int() and float(), token by token."""
    arrays = [np.zeros((nmax + 1, nmax + 1)) for _ in range(4)]
    for line in lines:
        parts = line.split()[first:]
        n, m = int(parts[0]), int(parts[1])
        for array, token in zip(arrays, parts[2:]):
            array[n, m] = float(token.replace("D", "e"))
    return dict(zip(("C", "S", "sigma_C", "sigma_S"), arrays))


def assert_same_model(a, b):
    for key in ("C", "S", "sigma_C", "sigma_S"):
        np.testing.assert_array_equal(getattr(a, key), getattr(b, key), err_msg=key)
    assert a.max_degree == b.max_degree


def test_nga_text_read_alike_whatever_its_layout(tmp_path, small_blocks):
    """Blocks parsed by numpy at once and blocks read line by line (Fortran D exponents,
    CRLF, blank lines, tabs, a form feed, a lone CR as line end, gzip) give the same
    numbers, bit for bit, as Python's float() of every token."""
    model = kaula_model(40)
    lines = nga_lines(model)
    plain = read_nga(write(tmp_path / "egm96_to360.ascii", "\n".join(lines) + "\n"), max_degree=40,
                     check_tide_system=False)
    for key, expected in float_model(lines, 40).items():
        np.testing.assert_array_equal(getattr(plain, key), expected, err_msg=key)
    odd = [line.replace("E", "D") if i % 3 == 0 else line for i, line in enumerate(lines)]
    odd[100] = odd[100] + "\r"  # CRLF on one line
    odd[200] = "\t" + odd[200].replace(" ", "\t", 3)
    odd[300] = odd[300] + "\n\n   "  # blank lines
    odd[400] = odd[400] + "\r" + odd.pop(401)  # a lone CR ends a line: that block line by line
    odd[500] = odd[500] + "\x0c"  # a form feed is whitespace to str.split()
    text = "\n".join(odd)  # and no final line end
    for path in (write(tmp_path / "egm96_to360.ascii", text),
                 tmp_path / "egm96_to360.ascii.gz"):
        if path.suffix == ".gz":
            path.write_bytes(gzip.compress(text.encode()))
        assert_same_model(read_nga(path, max_degree=40, check_tide_system=False), plain)
    assert small_blocks["fast"] > 10 and small_blocks["line by line"] >= 2


def test_bad_lines_named_across_blocks(tmp_path, small_blocks):
    """Line numbers stay those of the text from block to block (blank lines, CRLF, a lone
    CR): a bad number, a repeated coefficient and a non-zero S̄ of order 0 far apart."""
    model = kaula_model(30)
    lines = nga_lines(model)
    lines[50] = lines[50] + "\r\n"  # blank line after line 51
    lines[60] = lines[60] + "\r" + lines.pop(61)  # lines 62 and 63 in one '\n' line
    # text line numbers: lines[i] is line i + 1 up to 50, one more after the blank line,
    # one more again after the lone CR
    def numbered(index):
        return index + 1 + (index > 50) + (index > 60)

    bad = list(lines)
    bad[300] = bad[300].replace("E", "Q", 1)
    message = refused_nga(tmp_path, bad)
    assert re.search(rf"line {numbered(300)}: C '[-0-9.]+Q[-+0-9]+' is not a number", message), message
    bad = list(lines)
    bad[400] = lines[10]
    assert f"line {numbered(400)}: duplicate coefficient n=4 m=3 (first on line 11)" in refused_nga(tmp_path, bad)
    bad = list(lines)
    zonal = next(i for i in range(350, 400) if int(bad[i].split()[1]) == 0)
    fields = bad[zonal].split()
    bad[zonal] = " ".join(fields[:3] + ["1.0E-09"] + fields[4:])
    assert f"line {numbered(zonal)}: S̄ of n={fields[0]} m=0 must be 0, found 1e-09" in refused_nga(tmp_path, bad)


def refused_nga(tmp_path, lines):
    with pytest.raises(InputFileError) as info:
        read_nga(write(tmp_path / "egm96_to360.ascii", "\n".join(lines) + "\n"), max_degree=30, check_tide_system=False)
    return str(info.value)


def test_icgem_text_read_alike_whatever_its_layout(tmp_path, small_blocks):
    """ICGEM: upper-case keys, D exponents, lines with and without sigmas mixed."""
    model = kaula_model(30)
    data = [f"gfc {n} {m} {model.C[n, m]:.15e} {model.S[n, m]:.15e} {model.sigma_C[n, m]:.10e} {model.sigma_S[n, m]:.10e}"
            for n in range(2, 31) for m in range(n + 1)]
    header = GFC_HEADER.replace("max_degree       3", "max_degree       30")
    plain = read_icgem(write(tmp_path / "m.gfc", gfc_text(data, header)), check_tide_system=False)
    for key, expected in float_model(data, 30, first=1).items():
        np.testing.assert_array_equal(getattr(plain, key), expected, err_msg=key)
    odd = [line.replace("e", "D").replace("gfc", "GFC") if i % 4 == 0 else line for i, line in enumerate(data)]
    for i in range(7, len(odd), 50):  # a few lines without sigmas: those sigmas read as 0
        odd[i] = " ".join(odd[i].split()[:5])
    mixed = read_icgem(write(tmp_path / "m.gfc", gfc_text(odd, header)), check_tide_system=False)
    np.testing.assert_array_equal(mixed.C, plain.C)
    np.testing.assert_array_equal(mixed.S, plain.S)
    missing = np.zeros_like(plain.sigma_C, dtype=bool)
    for i in range(7, len(odd), 50):
        n, m = (int(v) for v in odd[i].split()[1:3])
        missing[n, m] = True
    assert (mixed.sigma_C[missing] == 0).all()
    np.testing.assert_array_equal(mixed.sigma_C[~missing], plain.sigma_C[~missing])
    assert small_blocks["fast"] > 10 and small_blocks["line by line"] >= 1


# ----------------------------------------------------------------------------- EGM2008's zeta-to-N correction


def zeta_to_n_text(C, S):
    """NGA's Zeta-to-N_to2160_egm2008 layout: ``n m C S`` from degree 0, every order,
    Fortran D exponents (the coefficients in metres)."""
    nmax = C.shape[0] - 1
    return "".join(f"{n:5d}{m:5d}{C[n, m]:25.15E}{S[n, m]:25.15E}\n".replace("E", "D")
                   for n in range(nmax + 1) for m in range(n + 1))


def egm2008_gfc(tmp_path, nmax):
    model = kaula_model(nmax, name="EGM2008")
    data = [f"gfc {n} {m} {model.C[n, m]:.15e} {model.S[n, m]:.15e}" for n in range(2, nmax + 1) for m in range(n + 1)]
    header = (GFC_HEADER.replace("TESTMODEL", "EGM2008_synthetic").replace("max_degree       3", f"max_degree       {nmax}")
              .replace("errors           formal", "errors           no"))
    return write(tmp_path / "egm2008_synthetic.gfc", gfc_text(data, header))


def test_egm2008_zeta_to_n_read_in_metres_and_applied_as_hsynth(tmp_path):
    """EGM2008's correction file: n m C S from degree 0 with D exponents, in metres,
    summed without (a/r)^n beside nga-hsynth's ζ and N0 (hsynth_WGS84 reads it with the
    routine of its elevation models, unscaled, and adds the sum to ζ + N0). CORRCOEF's
    layout is the same in centimetres: the unit follows the file's name."""
    from geoidspline.sources.resolve import load_synthesis

    nmax = 24
    C = np.zeros((nmax + 1, nmax + 1))
    S = np.zeros((nmax + 1, nmax + 1))
    C[0, 0], C[2, 0], C[3, 1], S[3, 1] = 0.25, -0.5, 0.125, 0.0625
    zeta = write(tmp_path / "Zeta-to-N_to24_egm2008", zeta_to_n_text(C, S))
    corr = read_nga_correction(zeta)
    assert (corr.unit_m, corr.max_degree, corr.C[2, 0], corr.S[3, 1]) == (1.0, 24, -0.5, 0.0625)
    model_path = egm2008_gfc(tmp_path, nmax)
    plain = load_synthesis(model_path)
    corrected = load_synthesis(model_path, zeta)
    assert plain.preset == corrected.preset == "nga-hsynth"
    assert any("in m (sha256" in note for note in corrected.provenance.notes)
    lat = np.array([-89.0, -45.0, 0.0, 30.0, 60.0])
    lon = np.array([10.0, 200.0, 33.0, 0.0, 300.0])
    r, psi = ecef_geometry(lat, lon)
    t = np.sin(psi)
    lam = np.radians(lon)
    p20 = math.sqrt(5) * (3 * t**2 - 1) / 2
    p31 = math.sqrt(7 / 6) * 1.5 * (5 * t**2 - 1) * np.cos(psi)  # fully normalised (4π): sqrt(2 (2n+1) (n-m)!/(n+m)!)
    expected = 0.25 - 0.5 * p20 + p31 * (0.125 * np.cos(lam) + 0.0625 * np.sin(lam))
    np.testing.assert_allclose(corrected.undulation(lat, lon) - plain.undulation(lat, lon), expected, atol=1e-9)
    # the same numbers under CORRCOEF's name are centimetres (and EGM2008 + CORRCOEF is F477's mix)
    corrcoef = write(tmp_path / "CORRCOEF", zeta_to_n_text(C, S))
    assert read_nga_correction(corrcoef).unit_m == 0.01
    # a renamed copy takes the unit of the model it goes with
    renamed = write(tmp_path / "zeta_to_n.txt", zeta_to_n_text(C, S))
    with_renamed = load_synthesis(model_path, renamed)
    assert with_renamed.correction.unit_m == 1.0 and with_renamed.preset == "nga-hsynth"
    # a correction beyond what any part of N can be, in metres
    C[5, 5] = 200.0
    with pytest.raises(InputFileError, match=r"line 21: the coefficient of n=5 m=5 is beyond 150 m"):
        read_nga_correction(write(tmp_path / "Zeta-to-N_to24_egm2008", zeta_to_n_text(C, S)))


@pytest.mark.slow
def test_egm2008_zeta_to_n_at_full_degree(tmp_path):
    """NGA's file at its full degree, 2160 (2,336,041 lines, gzip), beside a degree-2190
    model: read, its unit metres, and accepted for the synthesis to 2190."""
    nmax = 2160
    rng = np.random.default_rng(2160)
    n = np.arange(nmax + 1)[:, None]
    m = np.arange(nmax + 1)[None, :]
    C = np.where(m <= n, rng.normal(size=(nmax + 1, nmax + 1)) * 1e-4, 0.0)
    S = np.where((m <= n) & (m > 0), rng.normal(size=(nmax + 1, nmax + 1)) * 1e-4, 0.0)
    C[0, 0] = 0.25
    path = tmp_path / "Zeta-to-N_to2160_egm2008.gz"
    path.write_bytes(gzip.compress(zeta_to_n_text(C, S).encode(), compresslevel=1))
    corr = read_nga_correction(path)
    assert (corr.unit_m, corr.max_degree) == (1.0, 2160)
    rows = [(0, 0), (2160, 2160), (1500, 777), (3, 1)]
    assert all(corr.C[r] == float(f"{C[r]:.15E}") and corr.S[r] == float(f"{S[r]:.15E}") for r in rows)
    model = small_model(2190, {(2, 0): (-0.484165143790815e-3, 0.0)}, name="EGM2008")
    syn = GeoidSynthesis(model, corr, preset="nga-hsynth")
    assert syn.correction.max_degree == 2160 and syn.max_degree == 2190


def test_reading_a_model_is_a_progress_stage(tmp_path):
    """load_synthesis reports each file's reading as a stage counted in the file's
    bytes (the bar's total and ETA), advanced to the end."""
    from geoidspline.sources.resolve import load_synthesis

    class Recorder:
        def __init__(self):
            self.stages = []

        def stage(self, name, total, unit="step"):
            import contextlib

            record = [name, total, unit, 0]
            self.stages.append(record)

            def advance(n=1):
                record[3] += n

            return contextlib.nullcontext(advance)

    nmax = 24
    C = np.zeros((nmax + 1, nmax + 1))
    C[0, 0] = 0.1
    model_path = egm2008_gfc(tmp_path, nmax)
    zeta = tmp_path / "Zeta-to-N_to24_egm2008.gz"
    zeta.write_bytes(gzip.compress(zeta_to_n_text(C, np.zeros_like(C)).encode()))
    recorder = Recorder()
    load_synthesis(model_path, zeta, progress=recorder)
    assert recorder.stages == [
        [f"read {model_path.name}", model_path.stat().st_size, "byte", model_path.stat().st_size],
        [f"read {zeta.name}", zeta.stat().st_size, "byte", zeta.stat().st_size],
    ]


# ----------------------------------------------------------------------------- lattices by ducc0's transforms


def white_model(nmax, seed=11, name="EGM2008"):
    """Degree amplitudes that do not fall off (the hardest case for the radial
    expansion: (a/r)^n matters most at high n), damped so that N stays geoid-like."""
    rng = np.random.default_rng(seed)
    n = np.arange(nmax + 1)[:, None]
    m = np.arange(nmax + 1)[None, :]
    sigma = np.where(n >= 2, 2e-8 * np.exp(-n / 80.0) + 3e-9, 0.0)
    C = np.where(m <= n, rng.normal(size=(nmax + 1, nmax + 1)), 0.0) * sigma
    S = np.where((m <= n) & (m > 0), rng.normal(size=(nmax + 1, nmax + 1)), 0.0) * sigma
    C[2, 0] = -0.484165143790815e-3
    return HarmonicModel(name=name, gm=3.986004415e14, radius=6378136.3, max_degree=nmax, tide_system="tide_free",
                         C=C, S=S)


@pytest.mark.parametrize("region, spacing", [(GLOBAL, 1.0), (Region(40, 0, 45, 5), 0.1), (Region(-90, 10, -70, 40), 0.25),
                                             (Region(-3, 170, 4, -170), 0.2)])
def test_sht_lattice_equals_the_exact_synthesis(region, spacing):
    """ducc0's transforms with the (a/r)^n factor expanded band by band give the exact
    synthesis's lattice (per-row Legendre sums) to far below 0.01 mm: a degree-400
    model whose high degrees do not fall off, with a ζ-to-N correction (a set without
    the radial factor), globally (both hemispheres in one band), on a tile, at a pole,
    across the antimeridian."""
    model = white_model(400)
    rng = np.random.default_rng(3)
    Cc = np.tril(rng.normal(size=(401, 401))) * 1e-3
    Sc = np.tril(rng.normal(size=(401, 401))) * 1e-3
    Sc[:, 0] = 0.0
    corr = CorrectionModel("zeta", 400, Cc, Sc, unit_m=1.0)
    syn = GeoidSynthesis(model, corr, preset="nga-hsynth")
    syn.lattice_engine = "exact"
    exact = syn.nodes(region, spacing)
    syn.lattice_engine = "sht"
    fast = syn.nodes(region, spacing)
    np.testing.assert_array_equal(fast.latitude, exact.latitude)
    np.testing.assert_array_equal(fast.longitude, exact.longitude)
    assert np.abs(exact.undulation).max() > 10.0
    assert np.abs(fast.undulation - exact.undulation).max() < 1e-7
    bands = syn._sht().plan(np.log(syn.conventions.scale_a / syn._geometry(exact.latitude)[2]),
                            np.ones(exact.latitude.size))
    assert sorted(np.concatenate([b[0] for b in bands])) == list(range(exact.latitude.size))
    if region is not GLOBAL:
        return
    # north and south rows of one radius share a band
    row_band = {int(r): i for i, b in enumerate(bands) for r in b[0]}
    assert all(row_band[i] == row_band[exact.latitude.size - 1 - i] for i in range(exact.latitude.size))
    # a row's bits do not depend on the other rows of the call (canonical groups; the
    # FFT of the full circle is row by row, as sample_nodes' bands need)
    syn._sht_cache.clear()
    for south, north in ((region.south, (region.south + region.north) / 2), ((region.south + region.north) / 2,
                                                                              region.north)):
        part = syn.nodes(Region(south, region.west, north, region.east), spacing)
        rows = np.searchsorted(fast.latitude, part.latitude)
        np.testing.assert_array_equal(part.undulation, fast.undulation[rows])


@needs_egm2008
def test_sht_lattice_of_egm2008_120_equals_the_exact_synthesis():
    """The real EGM2008 to degree 120: the two lattice engines agree within the radial
    expansion's error bound (1e-7 m)."""
    syn = GeoidSynthesis(read_icgem(GFC2008), preset="nga-hsynth")
    values = {}
    for engine in ("exact", "sht"):
        syn.lattice_engine = engine
        values[engine] = syn.nodes(GLOBAL, 0.75).undulation
    assert np.abs(values["sht"] - values["exact"]).max() < 1e-7


def test_lattice_engine_from_the_environment(monkeypatch):
    model = white_model(30)
    assert GeoidSynthesis(model).lattice_engine == "exact"
    monkeypatch.setenv("GEOIDSPLINE_LATTICE_ENGINE", "sht")
    assert GeoidSynthesis(model).lattice_engine == "sht"
    monkeypatch.setenv("GEOIDSPLINE_LATTICE_ENGINE", "fast")
    from geoidspline.errors import ParameterError

    with pytest.raises(ParameterError, match="GEOIDSPLINE_LATTICE_ENGINE must be 'exact' or 'sht', got 'fast'"):
        GeoidSynthesis(model)


def test_points_sharing_latitudes_are_summed_once_a_latitude(monkeypatch):
    """Points on few latitudes (check points come 10 a latitude) take each latitude's
    Legendre sums once (the lattice's row sums), then the longitude sum a point: the
    point synthesis's values within rounding, poles, a correction and every quantity
    included; points on as many latitudes as there are points keep the point synthesis."""
    model = white_model(200)
    rng = np.random.default_rng(5)
    Cc = np.tril(rng.normal(size=(201, 201))) * 1e-3
    Sc = np.tril(rng.normal(size=(201, 201))) * 1e-3
    Sc[:, 0] = 0.0
    syn = GeoidSynthesis(model, CorrectionModel("zeta", 200, Cc, Sc, unit_m=1.0), preset="nga-hsynth")
    lat = np.repeat([-90.0, -41.3, 0.0, 12.5, 89.99, 90.0], 10)
    lon = rng.uniform(-180.0, 180.0, lat.size)
    each = {name: np.array([getattr(syn, name)(a, b) for a, b in zip(lat, lon)])  # one point a call
            for name in ("undulation", "height_anomaly", "disturbing_potential")}

    def no_point_sums(*args):
        raise AssertionError("the point synthesis ran for points on shared latitudes")

    monkeypatch.setattr(legendre, "point_sums", no_point_sums)
    for name, values in each.items():
        rings = getattr(syn, name)(lat, lon)
        assert np.abs(values).max() > 1.0
        assert np.abs(rings - values).max() <= 1e-12 * np.abs(values).max()
    with pytest.raises(AssertionError, match="point synthesis ran"):
        syn.undulation(rng.uniform(-90, 90, 20), rng.uniform(-180, 180, 20))  # 20 latitudes for 20 points


def test_points_on_shared_latitudes_in_chunks_of_rings_and_points(monkeypatch):
    """Rings and points taken a few at a time give the values of one step."""
    syn = GeoidSynthesis(white_model(60), preset="nga-hsynth")
    rng = np.random.default_rng(8)
    lat = rng.choice(rng.uniform(-90.0, 90.0, 37), 400)
    lon = rng.uniform(-180.0, 180.0, 400)
    whole = syn.undulation(lat, lon)
    monkeypatch.setattr(GeoidSynthesis, "_RING_CHUNK", 5)
    monkeypatch.setattr(GeoidSynthesis, "_RING_POINT_CHUNK", 7)
    np.testing.assert_array_equal(syn.undulation(lat, lon), whole)
    monkeypatch.setattr(GeoidSynthesis, "RING_SHARING", 10**6)  # the point synthesis
    assert np.abs(syn.undulation(lat, lon) - whole).max() <= 1e-12 * np.abs(whole).max()
