"""Sources are what they say (issue 24): datum, quantity and tide system checked or
converted by one rule, bands and variables named, NGS .bin grids read by content, and
implausible updates refused before anything is written."""

from __future__ import annotations

import hashlib
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is not installed (pip install -e '.[test]')")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import geoidspline  # noqa: E402
from geoidspline.api import build_store  # noqa: E402
from geoidspline.errors import InputFileError, StoreError  # noqa: E402
from geoidspline.fitting.parameters import FitParameters  # noqa: E402
from geoidspline.sources.base import Provenance  # noqa: E402
from geoidspline.sources.formats import read_grid, write_gtx  # noqa: E402
from geoidspline.sources.grid import GeoidGrid  # noqa: E402
from geoidspline.sources.ngs import write_ngs  # noqa: E402
from geoidspline.sources.plausibility import MAX_SLOPE, check_update, steepest_slope  # noqa: E402
from geoidspline.sources.reference import (  # noqa: E402
    Target,
    conform,
    for_new_store,
    tide_offset_m,
    tide_slope_north,
)
from geoidspline.sphere.region import Region  # noqa: E402
from geoidspline.api.regional import update_store  # noqa: E402

EGM96_GTX = Path("/usr/share/proj/egm96_15.gtx")
PARAMS = FitParameters(h0=0.2, max_level=2, tolerance_m=0.05, tile_size=1.0)
STORE_REGION = Region(-10, 0, 30, 40)
UPDATE_REGION = Region(5, 15, 15, 25)


def field(lat, lon):
    """A smooth geoid-like field around 35 m (slopes of 1e-5 m/m)."""
    p, l = np.radians(lat), np.radians(lon)
    return 30 + 4 * np.sin(3 * p) * np.cos(2 * l) + 2 * np.cos(p) * np.sin(l)


def lattice_grid(south, west, north, east, step, values=field, **prov):
    lat = np.arange(south, north + 1e-9, step)
    lon = np.arange(west, east + 1e-9, step)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    v = values(lat2, lon2) if callable(values) else values
    return GeoidGrid(lat, lon, v, Provenance(**{"source": "test", "model": "test", "tide_system": "tide_free",
                                                **prov}))


def snapshot(path):
    return {p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(path).rglob("*")) if p.is_file() and p.name != ".lock"}


def invoke(command, args):
    return CliRunner().invoke(command, [str(a) for a in args])


def assert_user_error(result, *fragments):
    assert result.exit_code == 1, (result.stdout, result.stderr)
    assert result.stderr.startswith("ERROR: ") and result.stderr.count("\n") == 1, result.stderr
    assert "Traceback" not in result.stderr
    for fragment in fragments:
        assert fragment in result.stderr, result.stderr


# -- tide systems ----------------------------------------------------------------------
def test_tide_offsets_are_ekmans():
    """N_mean − N_zero = 9.9 − 29.6 sin²φ cm and N_mean − N_free = (1 + k)(9.9 − 29.6 sin²φ) cm
    (Ekman 1989, k = 0.3), to 2 mm; zero − free is k times mean − zero."""
    lat = np.linspace(-90, 90, 37)
    s2 = np.sin(np.radians(lat)) ** 2
    np.testing.assert_allclose(tide_offset_m(lat, "zero_tide", "mean_tide"), (9.9 - 29.6 * s2) / 100, atol=2e-3)
    np.testing.assert_allclose(tide_offset_m(lat, "tide_free", "mean_tide"), 1.3 * (9.9 - 29.6 * s2) / 100, atol=3e-3)
    np.testing.assert_allclose(tide_offset_m(lat, "tide_free", "zero_tide"),
                               0.3 * tide_offset_m(lat, "zero_tide", "mean_tide"), rtol=1e-12)
    assert float(tide_offset_m(0.0, "tide_free", "mean_tide")) == pytest.approx(0.12897, abs=1e-5)
    assert float(tide_offset_m(90.0, "tide_free", "mean_tide")) == pytest.approx(-0.25793, abs=1e-5)


SYSTEMS = st.sampled_from(["tide_free", "zero_tide", "mean_tide"])


@settings(max_examples=60, deadline=None)
@given(SYSTEMS, SYSTEMS, SYSTEMS, st.floats(-90, 90))
def test_tide_conversions_compose_and_invert(a, b, c, lat):
    ab, bc, ac = (float(tide_offset_m(lat, x, y)) for x, y in ((a, b), (b, c), (a, c)))
    assert ab + bc == pytest.approx(ac, abs=1e-12)
    assert float(tide_offset_m(lat, b, a)) == pytest.approx(-ab, abs=1e-15)
    # the slope is the derivative of the offset over the Gaussian radius
    from geoidspline.geodesy.ellipsoids import gaussian_mean_radius

    h = 1e-4
    lo, hi = max(lat - h, -90.0), min(lat + h, 90.0)
    numeric = (float(tide_offset_m(hi, a, c)) - float(tide_offset_m(lo, a, c))) / np.radians(hi - lo)
    assert float(tide_slope_north(lat, a, c)) == pytest.approx(numeric / float(gaussian_mean_radius(lat)), abs=1e-12)


def test_a_source_in_another_tide_system_is_converted_and_said():
    grid = lattice_grid(0, 0, 10, 10, 1.0, tide_system="mean_tide")
    converted, notes = conform(grid, Target("the store", tide_system="tide_free"))
    lat2 = np.broadcast_to(grid.latitude[:, None], grid.shape)
    np.testing.assert_allclose(converted.values, grid.values + tide_offset_m(lat2, "mean_tide", "tide_free"),
                               atol=1e-12)
    assert converted.provenance.tide_system == "tide_free" and grid.provenance.tide_system == "mean_tide"
    assert notes and "converted from mean_tide to tide_free" in notes[0]
    assert notes[0] in converted.provenance.notes
    # unknown tide system: cannot be converted to the one asked
    unknown = lattice_grid(0, 0, 10, 10, 1.0, tide_system=None)
    kept, notes = for_new_store(unknown)
    assert kept.provenance.tide_system is None and notes == []
    taken, notes = conform(unknown, Target("the store", tide_system="tide_free"))
    assert np.array_equal(taken.values, unknown.values) and "not stated by the source" in notes[0]
    with pytest.raises(InputFileError, match=r"test: the source states no tide system, so it cannot be converted to "
                                             r"mean_tide; drop --tide-system"):
        for_new_store(unknown, tide_system="mean-tide")


# -- datums and quantities ---------------------------------------------------------------
def test_one_rule_for_every_reader(tmp_path):
    """A NAD27 GeoTIFF, a Bessel ISG and a quasi-geoid ISG are refused alike, naming both
    sides and the option; a GSI grid on JGD2011 (GRS80) and an ISG on GRS80 are taken,
    and said, because PROJ converts them to within 1 m / they are geocentric."""
    pytest.importorskip("rasterio")
    from geoidspline.sources.geotiff import write_geotiff
    from geoidspline.sources.gsi import write_gsi
    from geoidspline.sources.isg import write_isg

    grid = lattice_grid(30, -100, 35, -95, 0.25)
    nad27 = write_geotiff(tmp_path / "nad27.tif", grid, crs_epsg=4267)
    read = read_grid(nad27)
    assert (read.provenance.datum, read.provenance.ellipsoid) == ("EPSG:4267", "Clarke 1866")
    with pytest.raises(InputFileError, match=r"nad27\.tif: the source is on NAD27 .*Clarke 1866.*, a new store on "
                                             r"WGS 84: PROJ's best transformation 'NAD27 to WGS 84 .*accuracy 7 m.* "
                                             r"give --accept-datum"):
        for_new_store(read)
    accepted, notes = for_new_store(read, accept_datum=True)
    assert accepted.provenance.ellipsoid == "WGS84" and accepted.provenance.datum is None
    assert any("converted from NAD27" in n for n in notes) and any("--accept-datum" in n for n in notes)
    # NAD27 -> WGS 84 moves geoid heights by tens of metres here (Clarke 1866 is not geocentric)
    shift = accepted.values - read.values
    assert 20.0 < float(np.nanmedian(np.abs(shift))) < 60.0
    assert np.isfinite(accepted.values).sum() >= 0.8 * accepted.values.size

    bessel = write_isg(tmp_path / "bessel.isg", lattice_grid(47, 6, 50, 10, 0.25, ellipsoid="Bessel 1841"))
    with pytest.raises(InputFileError, match=r"bessel\.isg: the source is on the Bessel 1841 ellipsoid \(no datum "
                                             r"stated\), a new store on WGS84.*--accept-datum"):
        for_new_store(read_grid(bessel))
    quasi = write_isg(tmp_path / "quasi.isg", lattice_grid(47, 6, 50, 10, 0.25, ellipsoid="GRS80"),
                      data_type="quasi-geoid")
    assert read_grid(quasi).provenance.quantity == "quasi-geoid"
    with pytest.raises(InputFileError, match=r"quasi\.isg: the source holds height anomalies \(a quasi-geoid\), a "
                                             r"new store geoid undulations N; .*--accept-quasi-geoid"):
        for_new_store(read_grid(quasi))
    taken, notes = for_new_store(read_grid(quasi), accept_quasi_geoid=True)
    assert taken.provenance.quantity == "quasi-geoid" and "quasi-geoid" in notes[-1]

    grs80, notes = for_new_store(read_grid(write_isg(tmp_path / "grs80.isg", lattice_grid(47, 6, 50, 10, 0.25,
                                                                                         ellipsoid="GRS80"))))
    assert grs80.provenance.ellipsoid == "WGS84" and "both geocentric" in notes[0]
    gsi = read_grid(write_gsi(tmp_path / "gsigeo.asc", lattice_grid(30, 130, 35, 135, 0.25)))
    assert gsi.provenance.datum == "EPSG:6668"
    converted, notes = for_new_store(gsi)
    assert "JGD2011 to WGS 84" in notes[0] and "accuracy 1 m" in notes[0]
    np.testing.assert_allclose(converted.values, gsi.values, atol=1e-3)  # EPSG's null transformation
    # a file that says nothing (GTX) is taken as WGS 84, as before
    plain = read_grid(write_gtx(tmp_path / "plain.gtx", grid))
    assert for_new_store(plain)[1] == []


def test_geoid_fit_refuses_a_nad27_geotiff_and_says_what_it_converts(tmp_path):
    pytest.importorskip("rasterio")
    from geoidspline.cli.fit import main as fit_main
    from geoidspline.sources.geotiff import write_geotiff

    tif = write_geotiff(tmp_path / "nad27.tif", lattice_grid(30, -100, 35, -95, 0.25), crs_epsg=4267)
    result = invoke(fit_main, [tif, "--store", tmp_path / "s", "--region", 31, -99, 34, -96, "--h0", 0.2,
                               "--max-level", 1, "--tolerance", 5])
    assert_user_error(result, "nad27.tif: the source is on NAD27", "--accept-datum")
    assert not (tmp_path / "s").exists()
    jgd = write_geotiff(tmp_path / "jgd.tif", lattice_grid(30, 130, 35, 135, 0.25), crs_epsg=6668)
    result = invoke(fit_main, [jgd, "--store", tmp_path / "j", "--region", 31, 131, 34, 134, "--h0", 0.2,
                               "--max-level", 1, "--tolerance", 5, "--tide-system", "mean-tide"])
    assert result.exit_code in (0, 3), result.stderr
    assert "source     converted from JGD2011" in result.stdout
    assert "source     converted from tide_free to mean_tide" in result.stdout
    prov = geoidspline.open_store(tmp_path / "j").manifest["provenance"]
    assert (prov["ellipsoid"], prov["tide_system"], prov["quantity"]) == ("WGS84", "mean_tide", "geoid")
    assert any("JGD2011" in n for n in prov["notes"])


@pytest.mark.parametrize("mapping, expected", [
    ({"grid_mapping_name": "latitude_longitude", "crs_wkt": "GEOGCRS[broken"}, "PROJ cannot read the CRS"),
    ({"grid_mapping_name": "latitude_longitude", "crs_wkt": "EPSG:4258"}, None),
    ({"grid_mapping_name": "latitude_longitude", "semi_major_axis": 6377397.155, "inverse_flattening": 299.1528128},
     "no datum stated"),
])
def test_netcdf_grid_mapping_states_the_datum(tmp_path, mapping, expected):
    """CF grid_mapping: a CRS PROJ cannot read is refused by name; ETRS89 is converted
    (PROJ's null transformation, 1 m); Bessel's parameters alone give no datum: refused."""
    import xarray as xr

    grid = lattice_grid(47, 6, 50, 10, 0.5)
    ds = xr.Dataset({"N": (("lat", "lon"), grid.values, {"units": "m", "grid_mapping": "crs"}),
                     "crs": ((), 0, mapping)},
                    coords={"lat": ("lat", grid.latitude, {"units": "degrees_north"}),
                            "lon": ("lon", grid.longitude, {"units": "degrees_east"})})
    path = tmp_path / "mapped.nc"
    ds.to_netcdf(path, engine="netcdf4")
    if expected == "PROJ cannot read the CRS":
        with pytest.raises(InputFileError, match=r"mapped\.nc: grid_mapping variable 'crs': PROJ cannot read the CRS"):
            read_grid(path)
        return
    read = read_grid(path)
    if expected is None:
        assert read.provenance.datum == "EPSG:4258"
        converted, notes = for_new_store(read)
        assert "converted from ETRS89" in notes[0] and "accuracy 1 m" in notes[0]
        np.testing.assert_allclose(converted.values, read.values, atol=1e-3)
    else:
        assert read.provenance.datum is None and read.provenance.ellipsoid == "Bessel 1841"
        with pytest.raises(InputFileError, match=expected + r".*--accept-datum"):
            for_new_store(read)


def test_an_isg_epsg_code_proj_does_not_know_is_refused(tmp_path):
    from geoidspline.sources.isg import write_isg

    path = write_isg(tmp_path / "code.isg", lattice_grid(47, 6, 50, 10, 0.25, ellipsoid="GRS80"))
    path.write_text(path.read_text().replace("EPSG code      : ---", "EPSG code      : 999999"))
    with pytest.raises(InputFileError, match=r"code\.isg: ISG EPSG code 999999 is not a CRS PROJ knows"):
        read_grid(path)
    path.write_text(path.read_text().replace("EPSG code      : 999999", "EPSG code      : 4258"))
    assert read_grid(path).provenance.datum == "EPSG:4258"


# -- bands and variables -------------------------------------------------------------------
def test_a_multi_band_geotiff_needs_its_band_named(tmp_path):
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import Affine

    grid = lattice_grid(30, 0, 35, 5, 0.5)
    path = tmp_path / "two.tif"
    data = grid.values[::-1].astype(np.float32)
    with rasterio.open(path, "w", driver="GTiff", width=grid.shape[1], height=grid.shape[0], count=2,
                       dtype="float32", crs="EPSG:4326",
                       transform=Affine(0.5, 0, -0.25, 0, -0.5, 35.25)) as ds:
        ds.write(data, 1)
        ds.write(np.full_like(data, 0.02), 2)
        ds.set_band_description(1, "geoid_undulation")
        ds.set_band_description(2, "error")
    with pytest.raises(InputFileError, match=r"two\.tif: GeoTIFF has 2 bands \(1 'geoid_undulation', 2 'error'\): "
                                             r"name the one holding the undulations with --band N"):
        read_grid(path)
    np.testing.assert_allclose(read_grid(path, band=1).values, grid.values, atol=1e-5)
    assert np.all(read_grid(path, band=2).values == np.float32(0.02))
    with pytest.raises(InputFileError, match=r"--band 3 is not a band of this GeoTIFF; its bands are 1 "):
        read_grid(path, band=3)
    with pytest.raises(InputFileError, match=r"is a PROJ GTX grid, which has one band: --band applies to GeoTIFF"):
        read_grid(write_gtx(tmp_path / "one.gtx", grid), band=1)
    from geoidspline.cli.update import main as update_main

    assert_user_error(invoke(update_main, [path, "--store", tmp_path, "--region", 31, 1, 34, 4]),
                      "GeoTIFF has 2 bands", "--band N")


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.sampled_from(["N", "zeta", "err", "geoid_height", "sigma"]), min_size=2, max_size=4, unique=True))
def test_a_netcdf_with_several_variables_needs_one_named(tmp_path_factory, names):
    import xarray as xr

    grid = lattice_grid(0, 0, 3, 4, 1.0)
    ds = xr.Dataset({name: (("lat", "lon"), grid.values + k, {"units": "m"}) for k, name in enumerate(names)},
                    coords={"lat": ("lat", grid.latitude, {"units": "degrees_north"}),
                            "lon": ("lon", grid.longitude, {"units": "degrees_east"})})
    path = tmp_path_factory.mktemp("nc") / "several.nc"
    ds.to_netcdf(path, engine="netcdf4")
    with pytest.raises(InputFileError) as info:
        read_grid(path)
    assert f"candidates {', '.join(sorted(names))}; name one with --variable NAME" in str(info.value)
    for k, name in enumerate(names):
        np.testing.assert_allclose(read_grid(path, variable=name).values, grid.values + k, atol=1e-12)


# -- NGS .bin ------------------------------------------------------------------------------
def numpy_reading(data: bytes, order: str):
    """An independent reading of the published layout: struct for the header, numpy for the rows."""
    slat, wlon, dlat, dlon, nlat, nlon, ikind = struct.unpack(order + "4d3i", data[:44])
    values = np.frombuffer(data[44:], dtype=order + "f4").reshape(nlat, nlon).astype(float)
    return slat, wlon, dlat, dlon, nlat, nlon, ikind, values


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.integers(2, 9), st.integers(2, 9), st.sampled_from([1 / 60, 0.05, 0.25, 1.0]),
       st.integers(-80, 70), st.integers(-179, 170), st.sampled_from(["<", ">"]), st.booleans(),
       st.integers(0, 2**32 - 1))
def test_ngs_bin_in_either_byte_order_reads_as_numpy_does(tmp_path_factory, nlat, nlon, step, south, west, order,
                                                          east, seed):
    values = np.random.default_rng(seed).uniform(-100, 100, (nlat, nlon)).astype(np.float32).astype(float)
    grid = lattice_grid(south, west, south + (nlat - 1) * step, west + (nlon - 1) * step, step, values[:, :])
    grid = GeoidGrid(south + step * np.arange(nlat), west + step * np.arange(nlon), values,
                     Provenance(source="x"))
    # the name says the other byte order: detection must not care
    name = "g2012bu0.bin" if order == ">" else "g2012bu0_be.bin"
    path = write_ngs(tmp_path_factory.mktemp("ngs") / name, grid, byte_order=order, east_longitudes=east)
    slat, wlon, dlat, dlon, n1, n2, ikind, expected = numpy_reading(path.read_bytes(), order)
    assert (n1, n2, ikind) == (nlat, nlon, 1) and (wlon >= 0 if east else True)
    read = read_grid(path)
    np.testing.assert_array_equal(read.values, expected)
    np.testing.assert_allclose(read.latitude, slat + dlat * np.arange(nlat), atol=1e-9)
    lon = wlon + dlon * np.arange(nlon)
    np.testing.assert_allclose((read.longitude - lon + 180) % 360 - 180, 0, atol=1e-9)
    assert ("big-endian" if order == ">" else "little-endian") in read.provenance.notes[0]


def test_ngs_bin_faults_are_named(tmp_path):
    grid = lattice_grid(30, -100, 31, -99, 0.5)
    good = write_ngs(tmp_path / "g.bin", grid, byte_order=">").read_bytes()
    # (4 bytes short, a big-endian .bin is byte for byte a valid GTX: 8 bytes short is neither)
    (tmp_path / "short.bin").write_bytes(good[:-8])
    with pytest.raises(InputFileError, match=r"short\.bin: not an NGS \.bin geoid grid in either byte order "
                                             r"\(little-endian: ikind .*; big-endian: file size 72 bytes where "
                                             r"3 x 3 float32 nodes need 80\)"):
        read_grid(tmp_path / "short.bin")
    bad = bytearray(good)
    bad[40:44] = struct.pack(">i", 2)
    (tmp_path / "kind.bin").write_bytes(bytes(bad))
    with pytest.raises(InputFileError, match=r"kind\.bin: .*big-endian: ikind 2 \(NGS grids are ikind 1"):
        read_grid(tmp_path / "kind.bin")
    (tmp_path / "inf.bin").write_bytes(good[:44] + struct.pack(">f", np.inf) + good[48:])
    with pytest.raises(InputFileError, match=r"inf\.bin: NGS \.bin grid has 1 infinite values"):
        read_grid(tmp_path / "inf.bin")


def test_a_bin_fits_and_answers_like_the_same_grid_as_gtx(tmp_path):
    """GEOID18's layout (west longitude 260 = 100°W, little-endian) and its big-endian
    twin give the same store as the grid written as GTX: same answers to the last bit."""
    grid = lattice_grid(30, -100, 36, -94, 0.25)
    gtx = write_gtx(tmp_path / "g.gtx", grid)
    stores = {}
    for name, path in (("gtx", gtx),
                       ("le", write_ngs(tmp_path / "g18.bin", read_grid(gtx), byte_order="<", east_longitudes=True)),
                       ("be", write_ngs(tmp_path / "g18_be.bin", read_grid(gtx), byte_order=">"))):
        stores[name] = geoidspline.fit(path, tmp_path / name, region=(31, -99, 35, -95), h0=0.2, max_level=2,
                                       tolerance_m=0.05, tile_size=1.0)
    rng = np.random.default_rng(3)
    lat, lon = rng.uniform(31, 35, 500), rng.uniform(-99, -95, 500)
    reference = stores["gtx"].undulation(lat, lon)
    assert np.abs(reference - field(lat, lon)).max() < 0.1
    for name in ("le", "be"):
        np.testing.assert_array_equal(stores[name].undulation(lat, lon), reference)


# -- plausibility of updates ---------------------------------------------------------------
def test_egm96_is_within_the_slope_bound():
    """The bound is checked against the real geoid: EGM96's steepest step is 3.5e-4 m/m."""
    if not EGM96_GTX.is_file():
        pytest.skip(f"{EGM96_GTX} not found (apt-get install proj-data)")
    egm = read_grid(EGM96_GTX)
    slope, first, second = steepest_slope(egm.latitude, egm.longitude, egm.values)
    assert 3.0e-4 < slope < 4.0e-4 and slope * 5 < MAX_SLOPE


@settings(max_examples=40, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.5, 30.0), st.sampled_from([1 / 60, 0.1, 0.25]))
def test_a_corrupt_node_is_found_where_it_is(seed, error, step):
    """One node off by `error` metres in a smooth field: refused by the change bound (beyond
    10 m) or by the slope bound (a step beyond 2e-3 m/m), naming that node."""
    rng = np.random.default_rng(seed)
    lat = 40 + step * np.arange(12)
    lon = 5 + step * np.arange(14)
    stored = field(*np.meshgrid(lat, lon, indexing="ij"))
    new = stored + 0.1 * np.sin(np.radians(lat))[:, None]  # a decimetre revision passes
    measured = check_update("national", lat, lon, new, stored)
    assert measured["max_change_m"] < 0.2 and measured["max_slope"] < 1e-4
    i, j = int(rng.integers(1, 11)), int(rng.integers(1, 13))
    new[i, j] -= error
    spacing_m = np.radians(step) * 6371e3 * np.cos(np.radians(lat[i]))  # east-west: the shorter step
    # the node's steps to its neighbours are the error plus or minus the field's own step
    field_slope = steepest_slope(lat, lon, stored)[0]
    change = abs(new[i, j] - stored[i, j])  # the error less the node's decimetre revision
    if change <= 10.0 and error / spacing_m + field_slope <= MAX_SLOPE:
        check_update("national", lat, lon, new, stored)
        return
    if change <= 10.0 and error / spacing_m - field_slope <= MAX_SLOPE:
        return  # on the bound, within the field's own slope: either answer is right
    with pytest.raises(InputFileError, match="national: implausible update") as info:
        check_update("national", lat, lon, new, stored)
    assert f"{lat[i]:.6g}" in str(info.value) and f"{lon[j]:.6g}" in str(info.value)
    assert "--accept-implausible" in str(info.value)
    check_update("national", lat, lon, new, stored, max_change_m=None, max_slope=None)  # the override


@pytest.fixture(scope="module")
def small_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("plausible") / "base"
    build_store(lattice_grid(-10, 0, 30, 40, 1.0), path, STORE_REGION, PARAMS)
    return path


def national(values=field, step=1 / 12):
    return lattice_grid(3, 13, 17, 27, step, values, source="national")


def test_a_corrupt_patch_is_refused_and_the_store_unchanged(small_store, tmp_path):
    """The issue's case: a national grid with a patch where 34.96 m is stored as 0.3 m."""
    store = tmp_path / "store"
    shutil.copytree(small_store, store)
    before = snapshot(store)
    grid = national()
    values = np.array(grid.values)
    values[80:84, 90:95] = 0.3
    corrupt = GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance)
    with pytest.raises(InputFileError, match=r"national: implausible update: at latitude .* the source gives 0\.3000 "
                                             r"m where the store holds 3\d\.\d{4} m, a change of 3\d\.\d+ m, beyond the "
                                             r"10 m .*--accept-implausible"):
        update_store(store, corrupt, UPDATE_REGION, blend_width_km=100.0)
    assert snapshot(store) == before
    from geoidspline.cli.update import main as update_main

    path = write_gtx(tmp_path / "national.gtx", corrupt)
    assert_user_error(invoke(update_main, [path, "--store", store, "--region", 5, 15, 15, 25]),
                      "implausible update", "--accept-implausible")
    assert snapshot(store) == before


def test_a_decimetre_revision_passes_and_a_tide_system_is_converted(small_store, tmp_path):
    store = tmp_path / "store"
    shutil.copytree(small_store, store)
    revision = national(lambda la, lo: field(la, lo) + 0.1 * np.cos(np.radians(4 * lo)))
    record = update_store(store, revision, UPDATE_REGION, blend_width_km=100.0)
    assert record["plausibility"]["max_change_m"] < 0.15 and record["plausibility"]["max_slope"] < 1e-4
    assert "source_notes" not in record
    # the same revision published mean-tide: converted to the store's tide-free, and said
    mean = national(lambda la, lo: field(la, lo) + 0.1 * np.cos(np.radians(4 * lo))
                    + tide_offset_m(la, "tide_free", "mean_tide"))
    mean.provenance = Provenance(**{**mean.provenance.as_dict(), "notes": (), "tide_system": "mean_tide"})
    record = update_store(store, mean, UPDATE_REGION, blend_width_km=100.0)
    assert "converted from mean_tide to tide_free" in record["source_notes"][0]
    updated = geoidspline.open_store(store)
    lat, lon = np.meshgrid(np.arange(6, 14.1, 0.5), np.arange(16, 24.1, 0.5), indexing="ij")
    truth = field(lat, lon) + 0.1 * np.cos(np.radians(4 * lon))
    assert np.abs(updated.undulation(lat, lon) - truth).max() < 2 * PARAMS.tolerance_m
    history = updated.manifest["history"][-1]
    assert history["source_notes"] == record["source_notes"]


def test_query_and_export_answer_in_the_tide_system_asked(small_store, tmp_path):
    from geoidspline.cli.export import main as export_main
    from geoidspline.cli.query import main as query_main

    plain = invoke(query_main, ["--store", small_store, "--precision", 6, 20, 10])
    mean = invoke(query_main, ["--store", small_store, "--precision", 6, "--tide-system", "mean-tide", 20, 10])
    assert plain.exit_code == 0 and mean.exit_code == 0, (plain.stderr, mean.stderr)
    n_plain, n_mean = (float(r.stdout.strip().split(",")[-1]) for r in (plain, mean))
    assert n_mean - n_plain == pytest.approx(float(tide_offset_m(20.0, "tide_free", "mean_tide")), abs=2e-6)
    out = tmp_path / "mean.nc"
    result = invoke(export_main, ["--store", small_store, "--out", out, "--spacing", 1, "--region", 0, 5, 20, 30,
                                  "--tide-system", "zero_tide"])
    assert result.exit_code == 0 and "tide system zero_tide" in result.stdout, result.stderr
    written = read_grid(out)
    own = geoidspline.open_store(small_store)
    lat2, lon2 = np.meshgrid(written.latitude, written.longitude, indexing="ij")
    np.testing.assert_allclose(written.values - own.undulation(lat2, lon2),
                               tide_offset_m(lat2, "tide_free", "zero_tide"), atol=1e-9)
    assert written.provenance.tide_system == "zero_tide"


def test_tide_system_needs_a_store_that_records_its_own(tmp_path):
    grid = lattice_grid(0, 0, 4, 4, 0.5, tide_system=None)
    store = tmp_path / "unknown"
    build_store(grid, store, Region(0.5, 0.5, 3.5, 3.5), FitParameters(h0=0.2, max_level=0, tolerance_m=5,
                                                                       tile_size=1.0))
    from geoidspline.cli.query import main as query_main

    assert_user_error(invoke(query_main, ["--store", store, "--tide-system", "mean_tide", 1, 1]),
                      "tide system is unknown", "mean_tide")
    with pytest.raises(StoreError, match="tide system is unknown"):
        from geoidspline.api.export import export_grid

        export_grid(geoidspline.open_store(store), tmp_path / "x.gtx", 0.5, tide_system="mean_tide")
