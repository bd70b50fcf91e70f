"""Grid readers/writers, GeoidGrid interpolation and nodes, and the catalogue."""

from __future__ import annotations

import hashlib
import logging
from pathlib import Path

import numpy as np
import pytest
import xarray as xr
from reference_data import need, reference_file

from geoidspline.errors import CoordinateError, InputFileError
from geoidspline.sources.base import GeoidSource, Provenance
from geoidspline.sources.catalogue import list_catalogue
from geoidspline.sources.formats import GTX_NODATA, pgm_header, read_grid, write_gtx, write_netcdf
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sources.resolve import resolve_source
from geoidspline.sphere.region import Region

DAC = reference_file("egm96", "WW15MGH.DAC")
PGM = reference_file("geographiclib", "egm84-30.pgm")
GTX = Path("/usr/share/proj/egm96_15.gtx")


def _need(path: Path, how: str) -> Path:
    if not path.is_file():
        pytest.skip(f"{path} not found: {how}")
    return path


def need_dac():
    return need(DAC)


def need_pgm():
    return need(PGM)


def need_gtx():
    return _need(GTX, "PROJ's EGM96 grid is not installed (apt-get install proj-data)")


def field(lat, lon):
    """A smooth, non-symmetric test field (metres), periodic in longitude."""
    lat_r, lon_r = np.radians(lat), np.radians(lon)
    return 20 * np.sin(2 * lat_r) * np.cos(lon_r) + 5 * np.cos(3 * lon_r + 0.3) + 0.01 * lat


def make_grid(lat, lon, values=None, source="test"):
    lat, lon = np.asarray(lat, float), np.asarray(lon, float)
    if values is None:
        values = field(lat[:, None], lon[None, :])
    # float32-representable values so a GTX round trip is exact.
    values = np.asarray(values, float).astype(np.float32).astype(float)
    return GeoidGrid(lat, lon, values, Provenance(source=source, model="TEST"))


@pytest.fixture
def global_grid():
    return make_grid(np.arange(-90, 90.1, 2.0), np.arange(-180, 180, 2.0))


# -- generated files: round trips ----------------------------------------------------
def test_gtx_round_trip_keeps_values_nodata_and_hash(tmp_path, global_grid):
    values = global_grid.values.copy()
    values[10, 20] = np.nan
    grid = make_grid(global_grid.latitude, global_grid.longitude, values)
    path = write_gtx(tmp_path / "g.gtx", grid)
    assert path.stat().st_size == 40 + 91 * 180 * 4
    back = read_grid(path)
    np.testing.assert_array_equal(back.latitude, grid.latitude)
    np.testing.assert_array_equal(back.longitude, grid.longitude)
    np.testing.assert_array_equal(back.values, grid.values)  # NaN == NaN here
    assert np.isnan(back.values[10, 20]) and np.isnan(back.values).sum() == 1
    assert back.is_global_in_longitude
    assert back.provenance.source == "g.gtx"
    assert back.provenance.sha256 == hashlib.sha256(path.read_bytes()).hexdigest()
    # the nodata marker really is in the file
    raw = np.fromfile(path, ">f4", offset=40).reshape(91, 180)
    assert raw[10, 20] == np.float32(GTX_NODATA)
    assert isinstance(back, GeoidSource)


def test_gtx_regional_with_origin_at_0(tmp_path):
    grid = make_grid(np.arange(30, 40.01, 0.5), np.arange(0, 12.01, 0.5))
    back = read_grid(write_gtx(tmp_path / "r.gtx", grid))
    np.testing.assert_array_equal(back.values, grid.values)
    assert not back.is_global_in_longitude
    assert back.extent.as_tuple() == (30.0, 0.0, 40.0, 12.0)


def _raw_gtx(path, lat0, lon0, dlat, dlon, rows, cols, values=None, extra=b""):
    header = np.array([lat0, lon0, dlat, dlon], ">f8").tobytes() + np.array([rows, cols], ">i4").tobytes()
    if values is None:
        values = np.zeros((rows, cols))
    path.write_bytes(header + np.asarray(values, ">f4").tobytes() + extra)
    return path


def test_gtx_repeated_360_column_is_dropped(tmp_path):
    lat = np.arange(-90, 90.1, 10.0)
    lon = np.arange(0, 360.1, 10.0)  # 37 columns, 0 and 360 both present
    values = field(lat[:, None], lon[None, :]).astype(np.float32)
    path = _raw_gtx(tmp_path / "dup.gtx", -90, 0, 10, 10, lat.size, lon.size, values)
    grid = read_grid(path)
    assert grid.shape == (19, 36) and grid.is_global_in_longitude
    np.testing.assert_array_equal(grid.values, values[:, :-1].astype(float))
    values[3, -1] += 0.01
    _raw_gtx(path, -90, 0, 10, 10, lat.size, lon.size, values)
    with pytest.raises(InputFileError, match=r"dup\.gtx: the last longitude column .* differs from it by up to 0\.01"):
        read_grid(path)


def test_netcdf_round_trip_and_cf_attributes(tmp_path, global_grid):
    path = write_netcdf(tmp_path / "g.nc", global_grid)
    with xr.open_dataset(path) as ds:
        assert ds["geoid_height"].attrs["units"] == "m"
        assert "long_name" in ds["geoid_height"].attrs
        assert ds["latitude"].attrs["units"] == "degrees_north"
        assert ds["latitude"].attrs["standard_name"] == "latitude"
        assert ds["longitude"].attrs["units"] == "degrees_east"
        assert ds["longitude"].attrs["standard_name"] == "longitude"
        assert ds.attrs["model"] == "TEST"
    back = read_grid(path)
    np.testing.assert_array_equal(back.values, global_grid.values)
    np.testing.assert_array_equal(back.longitude, global_grid.longitude)
    assert back.is_global_in_longitude and back.provenance.model == "TEST"


LAT = np.arange(-60, 60.1, 5.0)
LON = np.arange(-180, 180, 5.0)


def _nc(path, lat, lon, values, *, lat_name="lat", lon_name="lon", lat_attrs=None, lon_attrs=None,
        var="N", var_attrs=None, encoding=None, extra_vars=None):
    lat_attrs = {"units": "degrees_north", "standard_name": "latitude"} if lat_attrs is None else lat_attrs
    lon_attrs = {"units": "degrees_east", "standard_name": "longitude"} if lon_attrs is None else lon_attrs
    data_vars = {var: ((lat_name, lon_name), values, {"units": "m"} if var_attrs is None else var_attrs)}
    for name, arr in (extra_vars or {}).items():
        data_vars[name] = ((lat_name, lon_name), arr, {"units": "m"})
    ds = xr.Dataset(data_vars, coords={lat_name: (lat_name, lat, lat_attrs), lon_name: (lon_name, lon, lon_attrs)})
    ds.to_netcdf(path, engine="netcdf4", encoding=encoding or {})
    return path


def expected_values():
    return field(LAT[:, None], LON[None, :])


def test_netcdf_descending_latitude(tmp_path):
    path = _nc(tmp_path / "desc.nc", LAT[::-1], LON, expected_values()[::-1])
    grid = read_grid(path)
    np.testing.assert_array_equal(grid.latitude, LAT)
    np.testing.assert_allclose(grid.values, expected_values(), rtol=0, atol=1e-12)


def test_netcdf_longitude_0_360(tmp_path):
    lon360 = np.mod(LON, 360.0)
    order = np.argsort(lon360)
    path = _nc(tmp_path / "east.nc", LAT, lon360[order], expected_values()[:, order])
    grid = read_grid(path)
    assert grid.longitude[0] == 0.0 and grid.longitude[-1] == 355.0 and grid.is_global_in_longitude
    np.testing.assert_allclose(grid.values, expected_values()[:, order], atol=1e-12)
    # The same field, wherever the seam is.
    np.testing.assert_allclose(grid.undulation(LAT[3], -175.0), expected_values()[3, 1], atol=1e-12)


def test_netcdf_unsorted_longitude_is_sorted(tmp_path):
    lon360 = np.mod(LON, 360.0)  # 180..355, 0..175: not monotonic
    path = _nc(tmp_path / "rolled.nc", LAT, lon360, expected_values())
    grid = read_grid(path)
    np.testing.assert_array_equal(grid.longitude, np.arange(0, 360, 5.0))
    np.testing.assert_allclose(grid.undulation(10.0, 200.0, "bilinear"), field(10.0, 200.0), atol=1e-12)


def test_netcdf_centimetres(tmp_path):
    path = _nc(tmp_path / "cm.nc", LAT, LON, expected_values() * 100.0, var_attrs={"units": "cm"})
    np.testing.assert_allclose(read_grid(path).values, expected_values(), rtol=1e-14, atol=1e-12)
    path = _nc(tmp_path / "mm.nc", LAT, LON, expected_values() * 1000.0, var_attrs={"units": "mm"})
    np.testing.assert_allclose(read_grid(path).values, expected_values(), rtol=1e-14, atol=1e-12)


def test_netcdf_cf_units_without_standard_names(tmp_path):
    path = _nc(tmp_path / "xy.nc", LAT, LON, expected_values(), lat_name="y", lon_name="x",
               lat_attrs={"units": "degrees_north"}, lon_attrs={"units": "degrees_east"}, var="band1")
    grid = read_grid(path)
    np.testing.assert_array_equal(grid.latitude, LAT)
    np.testing.assert_allclose(grid.values, expected_values(), atol=1e-12)


def test_netcdf_fill_values_become_nan(tmp_path):
    cm = np.round(expected_values() * 100).astype(np.int16)
    cm[2, 3] = -32767
    cm[4, :] = -32767
    path = _nc(tmp_path / "fill.nc", LAT, LON, cm, var_attrs={"units": "cm"},
               encoding={"N": {"_FillValue": -32767, "dtype": "int16"}})
    grid = read_grid(path)
    assert np.isnan(grid.values[2, 3]) and np.isnan(grid.values[4]).all()
    assert int(np.isnan(grid.values).sum()) == LON.size + 1
    assert grid.values[0, 0] == cm[0, 0] / 100.0
    with pytest.raises(InputFileError, match=rf"fill\.nc: {LON.size + 1} of {cm.size} nodes are NaN"):
        read_grid(path, complete=True)


def test_netcdf_float32_coordinates_are_regularised(tmp_path):
    lat = np.arange(-90, 90.01, 1 / 3).astype(np.float32)
    lon = (np.arange(1080) / 3 - 180 + 1 / 6).astype(np.float32)  # cell-centred
    values = field(lat.astype(float)[:, None], lon.astype(float)[None, :])
    grid = read_grid(_nc(tmp_path / "f32.nc", lat, lon, values))
    assert grid.is_global_in_longitude
    assert grid.latitude[0] == -90.0 and grid.latitude[-1] == 90.0
    assert abs(grid.longitude[0] - (-180 + 1 / 6)) < 1e-12


def test_netcdf_missing_units_warns_and_assumes_metres(tmp_path, caplog):
    path = _nc(tmp_path / "nounits.nc", LAT, LON, expected_values(), var_attrs={})
    with caplog.at_level(logging.WARNING, logger="geoidspline.sources"):
        grid = read_grid(path)
    assert "no units" in caplog.text and "assuming metres" in caplog.text
    np.testing.assert_allclose(grid.values, expected_values(), atol=1e-12)


# -- malformed files -------------------------------------------------------------------
def test_truncated_gtx_names_file_and_sizes(tmp_path, global_grid):
    path = write_gtx(tmp_path / "cut.gtx", global_grid)
    data = path.read_bytes()
    path.write_bytes(data[:-1000])
    with pytest.raises(InputFileError) as info:
        read_grid(path)
    expected = 40 + 91 * 180 * 4
    assert str(path) in str(info.value)
    assert f"GTX file is {expected - 1000} bytes, header says 91 x 180 float32 nodes need {expected}" in str(info.value)
    path.write_bytes(data + b"\0" * 8)  # padded
    with pytest.raises(InputFileError, match=rf"is {expected + 8} bytes, header says 91 x 180"):
        read_grid(path)
    path.write_bytes(data[:30])
    with pytest.raises(InputFileError, match="shorter than its 40-byte header"):
        read_grid(path)


def test_gtx_bad_headers(tmp_path):
    path = _raw_gtx(tmp_path / "neg.gtx", 0, 0, -0.5, 0.5, 3, 3)
    with pytest.raises(InputFileError, match=r"neg\.gtx: GTX header spacing must be > 0 degrees, got dlat=-0\.5"):
        read_grid(path)
    # header claims 4 x 3 but the file holds 3 x 3 nodes
    path = _raw_gtx(tmp_path / "rc.gtx", 0, 0, 0.5, 0.5, 4, 3, values=np.zeros((3, 3)))
    with pytest.raises(InputFileError, match=r"rc\.gtx: GTX file is 76 bytes, header says 4 x 3 float32 nodes need 88"):
        read_grid(path)
    path = _raw_gtx(tmp_path / "zero.gtx", 0, 0, 0.5, 0.5, 0, 3)
    with pytest.raises(InputFileError, match=r"rows > 0 and cols > 0, got rows=0"):
        read_grid(path)
    path = _raw_gtx(tmp_path / "lat.gtx", 80, 0, 5, 5, 4, 3)
    with pytest.raises(InputFileError, match=r"lat\.gtx: GTX latitudes 80.0\.\.95.0 go beyond \[-90, 90\]"):
        read_grid(path)


def test_all_nan_and_raw_nan_gtx_are_rejected(tmp_path):
    path = _raw_gtx(tmp_path / "empty.gtx", 0, 0, 1, 1, 3, 4, values=np.full((3, 4), GTX_NODATA))
    with pytest.raises(InputFileError, match=r"empty\.gtx: all 12 nodes are NaN \(no data\)"):
        read_grid(path)
    values = np.zeros((3, 4))
    values[1, 1:3] = np.nan
    path = _raw_gtx(tmp_path / "nan.gtx", 0, 0, 1, 1, 3, 4, values=values)
    with pytest.raises(InputFileError, match=r"nan\.gtx: 2 nodes are NaN or infinite; GTX marks no data with -88\.8888"):
        read_grid(path)


def _pgm(path, comments, width=8, height=5, maxval=65535, pixels=None, trim=0):
    head = "P5\n" + "".join(f"# {c}\n" for c in comments) + f"{width} {height}\n{maxval}\n"
    if pixels is None:
        pixels = np.arange(width * height).reshape(height, width) * 100
    data = head.encode() + np.asarray(pixels, ">u2").tobytes()
    path.write_bytes(data[: len(data) - trim])
    return path


def test_pgm_small_generated_file(tmp_path):
    pixels = np.arange(40).reshape(5, 8) * 100
    path = _pgm(tmp_path / "tiny.pgm", ["Description WGS84 EGM96, test", "Offset -108", "Scale 0.003"], pixels=pixels)
    grid = read_grid(path)
    assert grid.shape == (5, 8) and grid.latitude_spacing == 45.0 and grid.longitude_spacing == 45.0
    # first file row is 90N, first column 0E
    assert grid.values[-1, 0] == -108 + 0.003 * pixels[0, 0]
    assert grid.values[0, 7] == pytest.approx(-108 + 0.003 * pixels[4, 7], abs=1e-12)
    assert grid.provenance.model == "EGM96"


def test_pgm_header_errors(tmp_path):
    path = _pgm(tmp_path / "nooff.pgm", ["Scale 0.003"])
    with pytest.raises(InputFileError, match=r"nooff\.pgm: PGM header has no '# Offset' comment line"):
        read_grid(path)
    path = _pgm(tmp_path / "noscale.pgm", ["Offset -108"])
    with pytest.raises(InputFileError, match=r"no '# Scale' comment"):
        read_grid(path)
    path = _pgm(tmp_path / "short.pgm", ["Offset -108", "Scale 0.003"], trim=3)
    with pytest.raises(InputFileError, match=r"short\.pgm: PGM data is 77 bytes after the header .* 8 x 5 uint16 pixels need 80"):
        read_grid(path)
    path = _pgm(tmp_path / "max.pgm", ["Offset -108", "Scale 0.003"], maxval=255)
    with pytest.raises(InputFileError, match="maxval is 255"):
        read_grid(path)
    path = _pgm(tmp_path / "shape.pgm", ["Offset -108", "Scale 0.003"], width=6, height=5, pixels=np.zeros((5, 6)))
    with pytest.raises(InputFileError, match=r"width == 2\*\(height-1\)"):
        read_grid(path)


def test_dac_of_wrong_size(tmp_path):
    path = tmp_path / "WW15MGH.DAC"
    path.write_bytes(b"\0" * (721 * 1440 * 2 - 2))
    with pytest.raises(InputFileError) as info:
        read_grid(path)
    assert str(path) in str(info.value)
    assert "DAC file is 2076478 bytes, but 721 x 1440 int16 nodes" in str(info.value) and "need 2076480" in str(info.value)


def test_netcdf_two_candidate_variables(tmp_path):
    path = _nc(tmp_path / "two.nc", LAT, LON, expected_values(), var="a", extra_vars={"b": expected_values()})
    with pytest.raises(InputFileError, match=r"two\.nc: cannot tell which variable holds the undulations: "
                       r"candidates a, b; name one with --variable NAME"):
        read_grid(path)
    # a conventional name does not settle it (N and its error, N and zeta): the user names it
    path = _nc(tmp_path / "named.nc", LAT, LON, expected_values() * 2, var="geoid_height",
               extra_vars={"error": expected_values()})
    with pytest.raises(InputFileError, match=r"candidates error, geoid_height; name one with --variable"):
        read_grid(path)
    np.testing.assert_allclose(read_grid(path, variable="geoid_height").values, 2 * expected_values(), atol=1e-12)
    np.testing.assert_allclose(read_grid(path, variable="error").values, expected_values(), atol=1e-12)
    with pytest.raises(InputFileError, match=r"--variable 'N' is not a 2-D data variable .* the candidates are "
                                             r"error, geoid_height"):
        read_grid(path, variable="N")


def test_netcdf_unknown_units(tmp_path):
    path = _nc(tmp_path / "ft.nc", LAT, LON, expected_values(), var_attrs={"units": "ft"})
    with pytest.raises(InputFileError, match=r"ft\.nc: variable 'N' has units 'ft'; known units are m, cm, mm"):
        read_grid(path)


def test_netcdf_without_coordinates_and_bad_content(tmp_path):
    ds = xr.Dataset({"N": (("a", "b"), np.zeros((3, 4)), {"units": "m"})})
    ds.to_netcdf(tmp_path / "nocoord.nc", engine="netcdf4")
    with pytest.raises(InputFileError, match=r"nocoord\.nc: no latitude coordinate found"):
        read_grid(tmp_path / "nocoord.nc")
    (tmp_path / "fake.nc").write_bytes(b"not a netcdf file")
    with pytest.raises(InputFileError, match=r"fake\.nc: not a netCDF file"):
        read_grid(tmp_path / "fake.nc")
    (tmp_path / "x.xyz").write_bytes(b"abc")
    with pytest.raises(InputFileError, match=r"x\.xyz: unrecognised grid format"):
        read_grid(tmp_path / "x.xyz")
    with pytest.raises(InputFileError, match="no such file"):
        read_grid(tmp_path / "absent.gtx")


def test_constructor_invariants():
    prov = Provenance(source="mem")
    with pytest.raises(InputFileError, match="mem: undulation has shape"):
        GeoidGrid([0, 1, 2], [0, 1], np.zeros((2, 3)), prov)
    with pytest.raises(InputFileError, match="latitude is not equally spaced"):
        GeoidGrid([0, 1, 3], [0, 1], np.zeros((3, 2)), prov)
    with pytest.raises(InputFileError, match="longitude must be strictly ascending"):
        GeoidGrid([0, 1], [1, 0], np.zeros((2, 2)), prov)
    with pytest.raises(InputFileError, match=r"beyond \[-90, 90\]"):
        GeoidGrid([89, 91], [0, 1], np.zeros((2, 2)), prov)
    with pytest.raises(InputFileError, match="may not repeat its first column"):
        GeoidGrid([0, 1], np.arange(0, 361, 90.0), np.zeros((2, 5)), prov)
    assert isinstance(InputFileError("x", "y"), ValueError)


# -- interpolation -------------------------------------------------------------------
def test_bilinear_reproduces_bilinear_function():
    lat = np.arange(10, 20.01, 0.5)
    lon = np.arange(-5, 7.01, 0.25)

    def f(la, lo):
        return 3.0 + 0.7 * la - 1.3 * lo + 0.11 * la * lo

    grid = GeoidGrid(lat, lon, f(lat[:, None], lon[None, :]), Provenance(source="bilin"))
    rng = np.random.default_rng(0)
    pla, plo = rng.uniform(10, 20, 500), rng.uniform(-5, 7, 500)
    np.testing.assert_allclose(grid.undulation(pla, plo, method="bilinear"), f(pla, plo), rtol=0, atol=1e-10)
    # degree <= 1 per axis: Catmull-Rom reproduces it too, but only away from the
    # edge cells, where the clamped rows/columns bend it.
    inner = (pla > 10.5) & (pla < 19.5) & (plo > -4.75) & (plo < 6.75)
    np.testing.assert_allclose(grid.undulation(pla[inner], plo[inner]), f(pla[inner], plo[inner]), atol=1e-10)
    assert np.abs(grid.undulation(pla[~inner], plo[~inner]) - f(pla[~inner], plo[~inner])).max() > 1e-3
    # the grid edges are inside too
    assert grid.undulation(20.0, 7.0, "bilinear") == pytest.approx(f(20.0, 7.0), abs=1e-10)


def test_bicubic_reproduces_quadratics_and_passes_through_nodes():
    lat = np.arange(-30, 30.01, 1.0)
    lon = np.arange(100, 140.01, 0.5)

    def q(la, lo):
        return 1.0 + 0.2 * la - 0.3 * lo + 0.05 * la**2 - 0.02 * lo**2 + 0.01 * la * lo + 1e-3 * la**2 * lo**2

    grid = GeoidGrid(lat, lon, q(lat[:, None], lon[None, :]), Provenance(source="quad"))
    rng = np.random.default_rng(1)
    # at least one cell from the edges, where the clamped rows/columns break the rule
    pla, plo = rng.uniform(-29, 29, 500), rng.uniform(100.5, 139.5, 500)
    np.testing.assert_allclose(grid.undulation(pla, plo, method="bicubic"), q(pla, plo), rtol=1e-12, atol=1e-9)
    # bilinear does not reproduce the quadratic: make sure the test could fail
    assert np.abs(grid.undulation(pla, plo, method="bilinear") - q(pla, plo)).max() > 1e-3
    # through the nodes
    np.testing.assert_allclose(grid.undulation(lat[5], lon[7]), grid.values[5, 7], atol=1e-10)
    # a cubic is NOT reproduced (Catmull-Rom has quadratic precision only)
    cubic = GeoidGrid(lat, lon, np.broadcast_to(lat[:, None] ** 3, (lat.size, lon.size)), Provenance(source="c"))
    assert cubic.undulation(0.25, 120.0) == pytest.approx(0.109375, abs=1e-12)  # not 0.25**3


def test_bicubic_clamps_latitude_at_edge_rows():
    lat = np.arange(0, 10.01, 1.0)
    lon = np.arange(0, 10.01, 1.0)
    grid = GeoidGrid(lat, lon, np.broadcast_to(lat[:, None] ** 2, (11, 11)), Provenance(source="edge"))
    # t = 0.5: weights (-1/16, 9/16, 9/16, -1/16) on rows -1, 0, 1, 2; row -1 is clamped
    # to row 0 (value 0, not 1), so 9/16 * 1 - 1/16 * 4 = 0.3125 instead of lat^2 = 0.25.
    assert grid.undulation(0.5, 5.0) == pytest.approx(0.3125, abs=1e-12)
    assert grid.undulation(5.5, 5.0) == pytest.approx(30.25, abs=1e-12)  # interior: exact


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_longitude_wrap(global_grid, method):
    rng = np.random.default_rng(2)
    lat, lon = rng.uniform(-89, 89, 200), rng.uniform(-180, 180, 200)
    base = global_grid.undulation(lat, lon, method)
    np.testing.assert_allclose(global_grid.undulation(lat, lon + 360.0, method), base, atol=1e-9)
    np.testing.assert_allclose(global_grid.undulation(lat, lon - 720.0, method), base, atol=1e-9)
    # across the seam 179..180(=-180): bilinear is the mean of the two columns
    mid = global_grid.undulation(10.0, 179.0, "bilinear")
    i = np.searchsorted(global_grid.latitude, 10.0)
    assert mid == pytest.approx(0.5 * (global_grid.values[i, -1] + global_grid.values[i, 0]), abs=1e-12)
    # and it is a smooth field: the interpolant is close to it everywhere
    assert np.abs(base - field(lat, lon)).max() < 0.3


def test_nan_in_nan_out_and_latitude_range(global_grid):
    out = global_grid.undulation([np.nan, 10.0, 10.0], [0.0, np.nan, 20.0])
    assert np.isnan(out[0]) and np.isnan(out[1]) and np.isfinite(out[2])
    assert np.isnan(global_grid.undulation(np.nan, 0.0))
    for bad in (90.5, -91.0, np.inf):
        with pytest.raises(CoordinateError, match="latitude"):
            global_grid.undulation(bad, 0.0)
    with pytest.raises(CoordinateError):
        global_grid.undulation([0.0, 95.0], [0.0, 0.0])
    with pytest.raises(CoordinateError, match="longitude must be finite"):
        global_grid.undulation(0.0, np.inf)
    with pytest.raises(ValueError, match="method"):
        global_grid.undulation(0.0, 0.0, method="nearest")
    # poles are fine, and every longitude at a pole gives the pole row's value there
    assert np.isfinite(global_grid.undulation(90.0, 33.0)) and np.isfinite(global_grid.undulation(-90.0, 0.0))


def test_nodata_node_propagates(global_grid):
    values = global_grid.values.copy()
    values[50, 100] = np.nan
    grid = make_grid(global_grid.latitude, global_grid.longitude, values)
    lat, lon = grid.latitude[50] + 0.5, grid.longitude[100] + 0.5
    assert np.isnan(grid.undulation(lat, lon, "bilinear"))
    assert np.isnan(grid.undulation(lat + 2.0, lon, "bicubic"))  # in the 4x4 neighbourhood
    assert np.isfinite(grid.undulation(lat + 6.0, lon, "bicubic"))


def test_scalars_stay_scalars_and_arrays_broadcast(global_grid):
    value = global_grid.undulation(10.0, 20.0)
    assert type(value) is np.float64 and np.ndim(value) == 0
    assert type(global_grid.undulation(10, 20, "bilinear")) is np.float64
    out = global_grid.undulation(np.array([[0.0], [10.0], [20.0]]), np.array([0.0, 5.0, 10.0, 15.0]))
    assert out.shape == (3, 4)
    assert out[1, 2] == global_grid.undulation(10.0, 10.0)
    assert global_grid.undulation([10.0], [20.0]).shape == (1,)


# -- nodes ---------------------------------------------------------------------------
def test_nodes_across_antimeridian_and_global(global_grid):
    sample = global_grid.nodes(Region(-10, 170, 10, -170))
    np.testing.assert_array_equal(sample.longitude, np.arange(170, 190.1, 2.0))
    np.testing.assert_array_equal(sample.latitude, np.arange(-10, 10.1, 2.0))
    j = np.searchsorted(global_grid.longitude, -178.0)
    i = np.searchsorted(global_grid.latitude, 0.0)
    assert sample.longitude[6] == 182.0 and sample.latitude[5] == 0.0
    assert sample.undulation[5, 6] == global_grid.values[i, j]  # lon 182 is -178
    whole = global_grid.nodes(Region(-90, -180, 90, 180), spacing_deg=0.1)
    assert whole.undulation.shape == (91, 180) and np.unique(np.mod(whole.longitude, 360)).size == 180
    np.testing.assert_array_equal(whole.undulation, global_grid.values)
    # a region given in 0..360 is normalised by Region (west 350 -> -10)
    east = global_grid.nodes(Region(0, 350, 4, 370))
    np.testing.assert_array_equal(east.longitude, np.arange(-10, 10.1, 2.0))
    # inclusive edges with tolerance
    edge = global_grid.nodes(Region(0.0, 10.0 + 1e-12, 4.0 - 1e-12, 14.0))
    np.testing.assert_array_equal(edge.latitude, [0.0, 2.0, 4.0])
    np.testing.assert_array_equal(edge.longitude, [10.0, 12.0, 14.0])


def test_nodes_regional_grid_checks_extent():
    grid = make_grid(np.arange(30, 40.01, 0.5), np.arange(0, 12.01, 0.5))
    sample = grid.nodes(Region(31, 1, 32, 2))
    np.testing.assert_array_equal(sample.latitude, [31, 31.5, 32])
    np.testing.assert_array_equal(sample.longitude, [1, 1.5, 2])
    assert grid.nodes(Region(30, 0, 40, 12)).undulation.shape == (21, 25)
    assert grid.nodes(Region(30, 360, 40, 372)).undulation.shape == (21, 25)  # same place, 360 apart
    for region in (Region(29, 1, 32, 2), Region(31, -1, 32, 2), Region(31, 11, 32, 13)):
        with pytest.raises(CoordinateError, match="outside the grid"):
            grid.nodes(region)
    with pytest.raises(CoordinateError, match="outside the grid"):
        grid.undulation(35.0, 20.0)
    assert grid.undulation(35.0, 360.0 + 6.0) == pytest.approx(grid.undulation(35.0, 6.0), abs=1e-12)


# -- real files ---------------------------------------------------------------------
@pytest.fixture(scope="module")
def dac_grid():
    return read_grid(need_dac(), complete=True)


@pytest.fixture(scope="module")
def gtx_grid():
    return read_grid(need_gtx(), complete=True)


def test_ww15mgh_dac_published_values(dac_grid):
    assert dac_grid.shape == (721, 1440) and dac_grid.is_global_in_longitude
    assert dac_grid.undulation(0.0, 0.0) == pytest.approx(17.16, abs=1e-9)
    assert dac_grid.undulation(90.0, 0.0) == pytest.approx(13.61, abs=1e-9)
    assert dac_grid.undulation(-90.0, 123.0) == pytest.approx(-29.53, abs=1e-9)
    prov = dac_grid.provenance
    assert (prov.model, prov.tide_system, prov.zero_degree_term_m) == ("EGM96", "tide_free", -0.53)
    assert prov.sha256.startswith("c738c9910ea04492")


def test_egm96_15_gtx_agrees_with_ww15mgh_dac(gtx_grid, dac_grid):
    # Align longitudes: GTX starts at -180, DAC at 0; ask both for the same region.
    region = Region(-90, -180, 90, 180)
    a, b = gtx_grid.nodes(region), dac_grid.nodes(region)
    np.testing.assert_array_equal(a.longitude, b.longitude)
    diff = np.abs(a.undulation - b.undulation)
    # Measured: max 5.50 mm; ~5% of nodes exceed the 5 mm of cm rounding by up to 0.5 mm,
    # so the DAC is not exactly the GTX rounded to cm (the files come from different runs).
    assert diff.max() <= 0.0056
    assert np.mean(diff > 0.005) < 0.06
    assert np.median(diff) < 0.003


def test_egm84_30_pgm_header_and_values():
    path = need_pgm()
    head = pgm_header(path)
    assert (head["offset"], head["scale"], head["data_offset"]) == (-108.0, 0.003, 416)
    assert (head["width"], head["height"], head["maxval"]) == (720, 361, 65535)
    grid = read_grid(path)
    raw = path.read_bytes()
    first = int.from_bytes(raw[416:418], "big")  # the pixel at 90N, 0E
    assert grid.undulation(90.0, 0.0) == pytest.approx(-108 + 0.003 * first, abs=1e-12) == pytest.approx(13.098)
    assert grid.undulation(0.0, 0.0) == pytest.approx(18.33, abs=1e-9)
    assert grid.provenance.model == "EGM84"


def test_gtx_bilinear_matches_pyproj_vgridshift(gtx_grid):
    pyproj = pytest.importorskip("pyproj")
    pyproj.datadir.append_data_dir(str(GTX.parent))
    # pyproj converts degrees to the radians vgridshift wants; z_out = z_in + N with +multiplier=1.
    transformer = pyproj.Transformer.from_pipeline("+proj=vgridshift +grids=egm96_15.gtx +multiplier=1")
    rng = np.random.default_rng(42)
    lat, lon = rng.uniform(-89.9, 89.9, 50), rng.uniform(-180, 180, 50)
    _, _, z = transformer.transform(lon, lat, np.zeros(50))
    ours = gtx_grid.undulation(lat, lon, method="bilinear")
    assert np.abs(ours - z).max() < 1e-6  # measured ~1e-12 m
    assert np.abs(gtx_grid.undulation(lat, lon, method="bicubic") - z).max() > 1e-4  # the check can fail


# -- catalogue -------------------------------------------------------------------------
def test_catalogue_entries():
    names = {e.name for e in list_catalogue()}
    assert {"egm96-15", "egm96-15-nga", "egm84-30"} <= names
    for entry in list_catalogue():
        assert entry.file and entry.model and entry.reference and entry.search and entry.how_to_get


def test_resolve_by_name_and_path(monkeypatch):
    need_gtx()
    monkeypatch.delenv("PROJ_DATA", raising=False)
    monkeypatch.delenv("PROJ_LIB", raising=False)
    grid = resolve_source("egm96-15")
    assert grid.shape == (721, 1440) and grid.provenance.model == "EGM96"
    assert grid.provenance.zero_degree_term_m == -0.53
    assert grid.undulation(0.0, 0.0, "bilinear") == pytest.approx(17.1616, abs=1e-4)
    by_path = resolve_source(str(GTX))
    assert by_path.provenance.sha256 == grid.provenance.sha256


def test_resolve_nga_dac_by_name(monkeypatch):
    need_dac()
    monkeypatch.setenv("GEOIDSPLINE_DATA", str(DAC.parent))
    assert resolve_source("egm96-15-nga").undulation(0.0, 0.0) == pytest.approx(17.16, abs=1e-9)


def test_catalogue_never_searches_the_working_directory(monkeypatch, tmp_path, caplog):
    """Seen: the catalogue searched ../shared/data/egm96 relative to the working
    directory, so a WW15MGH.DAC planted there was used. Now only absolute directories
    are searched; a relative one in an environment variable is skipped with a warning."""
    planted = tmp_path / "work" / "data"
    planted.mkdir(parents=True)
    (planted / "WW15MGH.DAC").write_bytes(b"\0" * (721 * 1440 * 2))
    monkeypatch.chdir(tmp_path / "work")
    monkeypatch.setenv("GEOIDSPLINE_DATA", "data")  # relative: skipped
    with caplog.at_level(logging.WARNING), pytest.raises(InputFileError, match="searched \\(no directories\\)"):
        resolve_source("egm96-15-nga")
    assert "relative to the working directory; skipped" in caplog.text
    for entry in list_catalogue():
        for spec in entry.search:
            assert spec.startswith(("$", "pyproj:", "/")), f"{entry.name}: relative search entry {spec!r}"


def test_unknown_name_lists_known_names():
    with pytest.raises(InputFileError) as info:
        resolve_source("egm2020-1")
    message = str(info.value)
    assert "egm2020-1" in message and "egm96-15" in message and "egm84-30" in message


def test_missing_catalogue_file_says_where_and_how(monkeypatch, tmp_path):
    monkeypatch.setenv("GEOIDSPLINE_DATA", str(tmp_path))
    with pytest.raises(InputFileError) as info:
        resolve_source("egm96-15-nga")
    message = str(info.value)
    assert "WW15MGH.DAC" in message and str(tmp_path) in message and "GEOIDSPLINE_DATA" in message


def test_proj_data_env_var_is_searched_first(monkeypatch, tmp_path):
    grid = make_grid(np.arange(-90, 90.1, 10.0), np.arange(-180, 180, 10.0))
    write_gtx(tmp_path / "egm96_15.gtx", grid)
    monkeypatch.setenv("PROJ_DATA", str(tmp_path))
    # another file under the catalogue's name: refused, naming both digests and the way out
    with pytest.raises(InputFileError) as info:
        resolve_source("egm96-15")
    message = str(info.value)
    digest = hashlib.sha256((tmp_path / "egm96_15.gtx").read_bytes()).hexdigest()
    assert str(tmp_path / "egm96_15.gtx") in message and digest in message
    assert "c02a6eb70a7a78efebe5adf3ade626eb75390e170bb8b3f36136a2c28f5326a0" in message
    assert "allow_unknown_copy=True" in message
    found = resolve_source("egm96-15", allow_unknown_copy=True)
    assert found.shape == (19, 36)
    np.testing.assert_array_equal(found.values, grid.values)
    assert found.provenance.model == "EGM96"
    assert any("sha256 differs" in note for note in found.provenance.notes)
