"""Every answer of the command line is true or refused (issue 10, command-line side).

A point outside the store's coverage, a NaN, a longitude of 1e308 or a row that only
looks like a header never become a number with exit status 0; bad command lines
(regions wider than the globe, a height column that is a coordinate) are refused;
faults writing the output are one ERROR line. The session's small store covers
10..30 N, 20..40 E (conftest).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest
from test_cli import QUICK_FIT, assert_user_error, fmt, invoke

import geoidspline
from geoidspline.cli.export import main as export_main
from geoidspline.cli.fit import main as fit_main
from geoidspline.query.batch import _looks_like_header
from geoidspline.cli.query import main as query_main
from geoidspline.cli.update import main as update_main
from geoidspline.errors import CoordinateError
from geoidspline.sources.base import Provenance
from geoidspline.sources.formats import write_gtx
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.region import Region

PARIS = ("48.85", "2.35")
OUTSIDE = "outside the store's coverage (outside its region S 10 W 20 N 30 E 40)"


@pytest.fixture(scope="module")
def api(small_store):
    return geoidspline.open_store(small_store.path)


def query(small_store, *args, input=None):
    return invoke(query_main, ["--store", small_store.path, *args], input=input)


# -- outside the coverage -------------------------------------------------------------


def test_a_point_outside_the_coverage_is_an_error_not_a_number(small_store):
    result = query(small_store, *PARIS)
    assert_user_error(result)
    assert result.stdout == ""
    assert result.stderr.strip() == f"ERROR: {OUTSIDE}"
    just_outside = query(small_store, "30.5", "30")  # half a degree north of the region
    assert_user_error(just_outside)
    assert "outside the store's coverage" in just_outside.stderr


def test_outside_nan_is_the_explicit_opt_in(small_store, api):
    result = query(small_store, "--outside", "nan", *PARIS)
    assert result.exit_code == 0 and result.stdout == "nan\n"
    inside = query(small_store, "--outside", "nan", "20", "30")
    assert inside.exit_code == 0 and inside.stdout == fmt(api.undulation(20.0, 30.0)) + "\n"


def test_rows_outside_the_coverage_are_error_rows_and_the_others_go_on(small_store, api):
    rows = "lat,lon,name\n20,30,in\n48.85,2.35,paris\n-33.45,-70.66,santiago\n21,31,in2\n"
    result = query(small_store, "--input", "-", input=rows)
    assert result.exit_code == 1
    assert result.stdout.splitlines() == [
        "lat,lon,name,undulation_m",
        f"20,30,in,{fmt(api.undulation(20.0, 30.0))}",
        f"ERROR: line 3: {OUTSIDE}",
        f"ERROR: line 4: {OUTSIDE}",
        f"21,31,in2,{fmt(api.undulation(21.0, 31.0))}",
    ]
    assert "2 row(s)" in result.stderr
    opted = query(small_store, "--input", "-", "--outside", "nan", input=rows)
    assert opted.exit_code == 0
    assert opted.stdout.splitlines()[2:4] == ["48.85,2.35,paris,nan", "-33.45,-70.66,santiago,nan"]


@pytest.mark.parametrize("extra, columns", [
    (["--with-error"], 2),
    (["--deflection"], 5),
    (["--height-in", "ellipsoidal"], 2),
    (["--deflection", "--with-error", "--height-in", "orthometric"], 7),
], ids=["with-error", "deflection", "height", "all"])
def test_every_column_kind_is_refused_outside_the_coverage(small_store, extra, columns):
    point = [*PARIS, "100"] if "--height-in" in extra else list(PARIS)
    single = query(small_store, *extra, *point)
    assert_user_error(single)
    assert OUTSIDE in single.stderr and single.stdout == ""
    rows = ",".join(point) + "\n" + ("20,30,100\n" if "--height-in" in extra else "20,30\n")
    batch = query(small_store, "--input", "-", *extra, input=rows)
    assert batch.exit_code == 1
    bad, good = batch.stdout.splitlines()
    assert bad == f"ERROR: line 1: {OUTSIDE}"
    assert len(good.split(",")) == len(rows.splitlines()[1].split(",")) + columns
    assert "nan" not in good
    opted = query(small_store, "--outside", "nan", *extra, *point)
    assert opted.exit_code == 0 and opted.stdout.strip() == ",".join(["nan"] * columns)


def test_crs_input_outside_the_coverage(small_store):
    # EPSG:4326 through --crs: x is the longitude
    single = query(small_store, "--crs", "EPSG:4326", "2.35", "48.85")
    assert_user_error(single)
    assert OUTSIDE in single.stderr
    opted = query(small_store, "--crs", "EPSG:4326", "--outside", "nan", "2.35", "48.85")
    assert opted.exit_code == 0
    lat, lon, n = opted.stdout.strip().split(",")
    assert (float(lat), float(lon), n) == (48.85, 2.35, "nan")  # the position is still converted
    inside = query(small_store, "--crs", "EPSG:4326", "30", "20")
    assert inside.exit_code == 0 and inside.stdout.startswith("20.000000000,30.000000000,")


def test_crs_longitudes_beyond_a_million_degrees_are_refused(small_store, api):
    wrapped_inside = 30.0 + 360.0 * 2778  # 1,000,110: would wrap to 30 E, inside the region
    bad = query(small_store, "--crs", "EPSG:4326", repr(wrapped_inside), "20")
    assert_user_error(bad)
    assert "cannot transform" in bad.stderr
    sane = query(small_store, "--crs", "EPSG:4326", repr(wrapped_inside - 360.0), "20")
    assert sane.exit_code == 0 and sane.stdout.strip().endswith("," + fmt(api.undulation(20.0, 30.0)))


def test_jsonl_outside_the_coverage(small_store):
    result = query(small_store, "--input", "-", "--format", "jsonl", "--with-error", input="48.85,2.35\n20,30\n")
    assert result.exit_code == 1
    bad, good = (json.loads(line) for line in result.stdout.splitlines())
    assert bad["error"] == f"line 1: {OUTSIDE}" and bad["undulation_m"] is None and bad["error_bound_m"] is None
    assert good["error"] is None and good["undulation_m"] is not None and good["error_bound_m"] > 0
    opted = query(small_store, "--format", "jsonl", "--outside", "nan", *PARIS)
    record = json.loads(opted.stdout)
    assert opted.exit_code == 0 and record["undulation_m"] is None and record["error"] is None


def test_a_store_that_knows_reasons_names_them(small_store, monkeypatch):
    """With the store's own coverage reasons (holes where its source had no data) the
    message names the reason; the region is named only for points outside it."""
    from geoidspline.store.reader import TileStore

    def covers(self, lat, lon):
        lat = np.asarray(lat, dtype=float)
        return Region(*self.manifest["region"]).contains(lat, lon) & ~((lat > 14) & (lat < 16))

    def coverage_reason(self, lat, lon):
        inside = Region(*self.manifest["region"]).contains(lat, lon)
        return np.where(inside, "no data in the source here", "outside the region")

    monkeypatch.setattr(TileStore, "covers", covers)
    monkeypatch.setattr(TileStore, "coverage_reason", coverage_reason, raising=False)
    result = query(small_store, "--input", "-", input="15,30\n48.85,2.35\n20,30\n")
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert lines[0] == "ERROR: line 1: outside the store's coverage (no data in the source here)"
    assert lines[1] == f"ERROR: line 2: {OUTSIDE}"
    assert lines[2].startswith("20,30,")


# -- exit statuses and rows -----------------------------------------------------------


@pytest.mark.parametrize("point, words", [
    (("nan", "30"), "finite"), (("20", "nan"), "finite"), (("inf", "30"), "finite"),
    (("95", "30"), "latitude 95"), (("20", "1e308"), "beyond ±1e+06"), (("20", "-1000000.5"), "beyond ±1e+06"),
], ids=["nan-lat", "nan-lon", "inf", "lat-95", "lon-1e308", "lon-1e6"])
def test_a_single_point_that_cannot_be_answered_exits_1(small_store, point, words):
    result = query(small_store, *point)
    assert_user_error(result)
    assert words in result.stderr and result.stdout == ""


def test_large_but_sane_longitudes_are_wrapped(small_store, api):
    lon = 30.0 + 360.0 * 2777  # 999,750: within ±1e6
    result = query(small_store, "20", repr(lon))
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == fmt(api.undulation(20.0, 30.0))


def test_rows_with_huge_longitudes_are_error_rows(small_store, api):
    rows = "".join(f"20,{lon}\n" for lon in ("1e308", "-1e308", "1000000.5", "30")) + "20," + "9" * 400 + "\n"
    result = query(small_store, "--input", "-", input=rows)
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    for n in (1, 2, 3):
        assert lines[n - 1].startswith(f"ERROR: line {n}: longitude ") and "beyond" in lines[n - 1]
    assert lines[3] == f"20,30,{fmt(api.undulation(20.0, 30.0))}"
    assert lines[4].startswith("ERROR: line 5: ")  # inf after float(): not finite


def test_a_bom_without_header_keeps_the_first_row(small_store, api, tmp_path):
    path = tmp_path / "bom.csv"
    path.write_bytes(b"\xef\xbb\xbf20,30\n21,31\n")
    for source in (["--input", path], ["--input", "-"]):
        result = query(small_store, *source, input=path.read_bytes())
        assert result.exit_code == 0, result.output
        assert result.stdout.splitlines() == [f"20,30,{fmt(api.undulation(20.0, 30.0))}",
                                              f"21,31,{fmt(api.undulation(21.0, 31.0))}"]
    path.write_bytes(b"\xef\xbb\xbflat,lon\r\n20,30\r\n")
    with_header = query(small_store, "--input", path)
    assert with_header.stdout.splitlines() == ["lat,lon,undulation_m", f"20,30,{fmt(api.undulation(20.0, 30.0))}"]


def test_a_first_row_with_hemisphere_letters_is_a_bad_row_not_a_header(small_store, api):
    result = query(small_store, "--input", "-", input="-33.45S,-70.66W\n20,30\n")
    assert result.exit_code == 1
    assert result.stdout.splitlines() == [
        "ERROR: line 1: latitude/longitude are not numbers: '-33.45S', '-70.66W'",
        f"20,30,{fmt(api.undulation(20.0, 30.0))}",
    ]


@pytest.mark.parametrize("line", [
    "lat,lon", "Latitude,Longitude", "lat_deg,lon_deg,name", '"lat","lon"', "y (deg),x (deg)",
    "lat [°],lon [°]", "Breite,Länge", "_lat,_lon", "phi.deg,lambda-deg",
])
def test_what_is_a_header(line):
    assert _looks_like_header(line, (0, 1))


@pytest.mark.parametrize("line", [
    "-33.45S,-70.66W", "33.45S,70.66W", "N45.2,E7.1", "s 33,w 70", "abc,30", "20,lon", "nan,nan", "inf,lat",
    "lat", "1e5,x", "lat;lon", "lat,", "(lat),(lon)", "lat!,lon?",
])
def test_what_is_not_a_header(line):
    assert not _looks_like_header(line, (0, 1))


def test_a_line_longer_than_the_limit_is_a_bad_row_and_is_not_kept(small_store, api, tmp_path, monkeypatch):
    """Memory stays bounded whatever the input (a file without newlines, /dev/zero)."""
    import geoidspline.query.batch as query_module

    monkeypatch.setattr(query_module, "MAX_LINE_BYTES", 100_000)
    path = tmp_path / "long.csv"
    path.write_bytes(b"20,30\n21,31," + b"x" * 1_000_000 + b"\n22,32\n" + b"y" * 300_000)
    result = query(small_store, "--input", path)
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert lines[0] == f"20,30,{fmt(api.undulation(20.0, 30.0))}"
    assert lines[1].startswith("ERROR: line 2: longer than 100,000 bytes, not read ('21,31,xxx")
    assert lines[2] == f"22,32,{fmt(api.undulation(22.0, 32.0))}"
    assert lines[3].startswith("ERROR: line 4: longer than 100,000 bytes") and len(lines) == 4


def test_quoted_numbers_are_numbers(small_store, api):
    result = query(small_store, "--input", "-", input='"20", "30",x\n')
    assert result.exit_code == 0
    assert result.stdout == f'"20", "30",x,{fmt(api.undulation(20.0, 30.0))}\n'


@pytest.mark.parametrize("column", ["0", "1"])
def test_height_column_that_is_a_coordinate_is_refused(small_store, column):
    result = query(small_store, "--height-in", "ellipsoidal", "--height-column", column, "--input", "-",
                   input="20,30,5\n")
    assert_user_error(result, code=2)
    assert f"--height-column {column}" in result.stderr
    assert ("latitude" if column == "0" else "longitude") + " column" in result.stderr
    utm = query(small_store, "--crs", "EPSG:32633", "--height-in", "ellipsoidal", "--height-column", column,
                "500000", "3000000", "5")
    assert_user_error(utm, code=2)
    assert ("x" if column == "0" else "y") + " column" in utm.stderr


def test_a_far_height_column_costs_no_memory(small_store, api):
    rows = "20,30,a,b,7\n20,30\n"
    far = query(small_store, "--height-in", "ellipsoidal", "--height-column", "4", "--input", "-", input=rows)
    assert far.exit_code == 1
    first, second = far.stdout.splitlines()
    assert first == f"20,30,a,b,7,{fmt(api.undulation(20.0, 30.0))},{fmt(7 - api.undulation(20.0, 30.0))}"
    assert second.startswith("ERROR: line 2: expected at least 5 columns (lat,lon,...,ellipsoidal height in column 4)")
    huge = query(small_store, "--height-in", "ellipsoidal", "--height-column", str(10**12), "--input", "-",
                 input="20,30,1\n")
    assert huge.exit_code == 1 and "expected at least 1000000000001 columns" in huge.stdout


# -- regions --------------------------------------------------------------------------


@pytest.mark.parametrize("bounds, words", [
    ((-36, -72, -32, 1000), "beyond ±540"),
    ((-36, -600, -32, -590), "beyond ±540"),
    ((-36, -72, -32, 300), "spans 372"),
    ((-36, -180, -32, 181), "spans 361"),
])
def test_region_refuses_more_than_the_globe(bounds, words):
    with pytest.raises(CoordinateError, match=words):
        Region.from_bounds(*bounds)


@pytest.mark.parametrize("bounds, expected", [
    ((-36, -72, -32, 288), (-36.0, -72.0, -32.0, 288.0)),
    ((-36, 170, -32, -170), (-36.0, 170.0, -32.0, 190.0)),
    ((-36, 0, -32, 360), (-36.0, 0.0, -32.0, 360.0)),
    ((-36, 350, -32, 370), (-36.0, -10.0, -32.0, 10.0)),
    ((-36, -540, -32, -530), (-36.0, 180.0 - 360.0, -32.0, -170.0)),
])
def test_regions_that_stay_valid(bounds, expected):
    assert Region.from_bounds(*bounds).as_tuple() == pytest.approx(expected)


def test_every_command_with_region_refuses_a_region_wider_than_the_globe(small_store, store_copy, synthetic_gtx,
                                                                          tmp_path):
    wide = ["--region", "-36", "-72", "-32", "1000"]
    fit = invoke(fit_main, [synthetic_gtx, "--store", tmp_path / "s", *wide, "-q"])
    assert_user_error(fit)
    assert "beyond ±540" in fit.stderr and not (tmp_path / "s").exists()
    update = invoke(update_main, [synthetic_gtx, "--store", store_copy, "--region", "12", "22", "18", "400", "-q"])
    assert_user_error(update)
    assert "spans 378" in update.stderr
    old_update = invoke(fit_main, [synthetic_gtx, "--update", store_copy, "--region", "12", "22", "18", "400", "-q"])
    assert_user_error(old_update)
    assert geoidspline.open_store(store_copy).info()["store_version"] == 1
    export = invoke(export_main, ["--store", small_store.path, "--out", tmp_path / "g.gtx", "--spacing", "1", *wide])
    assert_user_error(export)
    assert not (tmp_path / "g.gtx").exists()


# -- exports and coverage -------------------------------------------------------------


def test_export_outside_the_store_is_an_error_and_holes_are_no_data(small_store, tmp_path, monkeypatch):
    from geoidspline.sources.formats import read_grid
    from geoidspline.store.reader import TileStore

    outside = invoke(export_main, ["--store", small_store.path, "--out", tmp_path / "o.gtx", "--spacing", "1",
                                   "--region", "40", "0", "50", "10"])
    assert_user_error(outside)
    original = TileStore.covers

    def holey(self, lat, lon):  # the store helper's coverage: a hole 14..16 N
        lat = np.asarray(lat, dtype=float)
        return original(self, lat, lon) & ~((lat > 14) & (lat < 16))

    monkeypatch.setattr(TileStore, "covers", holey)
    result = invoke(export_main, ["--store", small_store.path, "--out", tmp_path / "h.gtx", "--spacing", "1"])
    assert result.exit_code == 0, result.output
    grid = read_grid(tmp_path / "h.gtx")
    hole = (grid.latitude > 14) & (grid.latitude < 16)
    assert np.isnan(grid.values[hole]).all() and np.isfinite(grid.values[~hole]).all()
    assert (tmp_path / "h.gtx").read_bytes().count(np.array([-88.8888], ">f4").tobytes()) == 21  # PROJ's no data


def test_export_keeps_edge_nodes_a_rounding_error_outside_the_region(small_store, tmp_path, monkeypatch):
    """11.3 + 17 * 1.1 is 30.000000000000004: a lattice's last node can lie beyond the
    region's edge by a rounding error; it is a node of the region, not no data."""
    from geoidspline.api.export import export_grid, export_lattice
    from geoidspline.store.reader import TileStore

    store = geoidspline.open_store(small_store.path)
    region = Region.from_bounds(11.3, 22.0, 30.0, 30.8)
    lat, _, _ = export_lattice(store, 1.1, region)
    assert lat[-1] > 30.0  # the rounding this test is about
    strict = TileStore.covers

    def strict_covers(self, lat, lon):  # a coverage test without any tolerance
        return strict(self, lat, lon) & (np.asarray(lat) <= 30.0)

    monkeypatch.setattr(TileStore, "covers", strict_covers)
    grid = export_grid(store, tmp_path / "f.nc", 1.1, region)
    assert np.isfinite(grid.values).all()
    assert grid.values[-1, 0] == pytest.approx(store.undulation(30.0, 22.0), abs=1e-6)


# -- exit status 3 with --json --------------------------------------------------------


def test_fit_json_keeps_exit_3(synthetic_gtx, tmp_path):
    args = [synthetic_gtx, "--store", tmp_path / "s", "--region", "10", "20", "30", "40",
            "--h0", "0.2", "--max-level", "0", "--tolerance", "1e-6", "-q", "--json"]
    result = invoke(fit_main, args)
    assert result.exit_code == 3, result.output
    assert json.loads(result.stdout)["converged"] is False


def test_update_json_keeps_exit_3(synthetic_grid, store_copy, tmp_path):
    """Noise of ±1 m on the 2° nodes cannot be fitted to the store's 2 mm with its
    levels (the finest is coarser than the data): written, exit status 3."""
    rng = np.random.default_rng(3)
    noisy = GeoidGrid(synthetic_grid.latitude, synthetic_grid.longitude,
                      synthetic_grid.values + rng.uniform(-1, 1, synthetic_grid.values.shape),
                      Provenance(source="noisy", model="synthetic", kind="grid"))
    path = write_gtx(tmp_path / "noisy.gtx", noisy)
    result = invoke(update_main, [path, "--store", store_copy, "--region", "14", "24", "26", "36", "--json", "-q"])
    assert result.exit_code == 3, result.output
    assert json.loads(result.stdout)["converged"] is False
    assert geoidspline.open_store(store_copy).info()["store_version"] == 2


# -- faults writing the output (real processes) ---------------------------------------


def _module(*args):
    return [sys.executable, "-m", "geoidspline", *map(str, args)]


@pytest.fixture(scope="module")
def many_rows(tmp_path_factory):
    """200,000 rows inside the small store's region (7 MB of output: more than a pipe holds)."""
    rng = np.random.default_rng(5)
    path = tmp_path_factory.mktemp("rows") / "rows.csv"
    lat, lon = rng.uniform(10, 30, 200_000), rng.uniform(20, 40, 200_000)
    path.write_text("".join(f"{a:.5f},{b:.5f}\n" for a, b in zip(lat, lon)))
    return path


def test_a_closed_pipe_ends_quietly(small_store, many_rows):
    proc = subprocess.Popen(_module("query", "--store", small_store.path, "--input", many_rows),
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    first = proc.stdout.readline()
    proc.stdout.close()  # like `| head -1`
    stderr = proc.stderr.read().decode()
    assert proc.wait(timeout=600) == 0, stderr
    assert first.count(b",") == 2
    assert stderr == ""


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="/dev/full is Linux's always-full device")
@pytest.mark.parametrize("args", [["query", "20", "30"], ["query", "--input", "ROWS"], ["info"]],
                         ids=["point", "rows", "info"])
def test_a_full_disk_on_stdout_is_one_error_line(small_store, many_rows, args):
    args = [many_rows if a == "ROWS" else a for a in args]
    with open("/dev/full", "w") as full:
        proc = subprocess.run(_module(args[0], "--store", small_store.path, *args[1:]), stdout=full,
                              stderr=subprocess.PIPE, text=True, timeout=600)
    assert proc.returncode == 1
    assert proc.stderr == "ERROR: cannot write to the standard output: No space left on device\n"


def test_fit_on_a_full_stdout_is_an_error_but_the_store_is_written(synthetic_gtx, tmp_path):
    if not os.path.exists("/dev/full"):
        pytest.skip("/dev/full is Linux's always-full device")
    with open("/dev/full", "w") as full:
        proc = subprocess.run(_module("fit", synthetic_gtx, "--store", tmp_path / "s", *QUICK_FIT, "-q"),
                              stdout=full, stderr=subprocess.PIPE, text=True, timeout=600)
    assert proc.returncode == 1
    assert proc.stderr.startswith("ERROR: cannot write to the standard output") and "Traceback" not in proc.stderr
    assert math.isfinite(geoidspline.open_store(tmp_path / "s").undulation(20.0, 30.0))
