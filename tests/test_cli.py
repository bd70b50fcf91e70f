"""The command-line tools: geoid-fit, geoid-query, geoid-info and ``python -m geoidspline``.

One full fit + query + info cycle runs in real subprocesses; everything else uses
click's CliRunner in-process (fast).
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import geoidspline
from geoidspline.__main__ import main as geoidspline_main
from geoidspline.cli.fit import main as fit_main
from geoidspline.cli.info import main as info_main
from geoidspline.cli.query import main as query_main
from geoidspline.sources.catalogue import list_catalogue

INFO_KEYS = ("coefficients", "levels", "tiles", "max_error_m", "rms_error_m", "bytes")
#: A fit of the synthetic grid that converges at once (tolerance 1 m), a few tenths of a second.
QUICK_FIT = ["--region", "10", "20", "30", "40", "--h0", "0.2", "--max-level", "1", "--tolerance", "1.0"]


def run_module(*args, stdin=None, cwd=None):
    return subprocess.run(
        [sys.executable, "-m", "geoidspline", *map(str, args)],
        input=stdin, capture_output=True, text=True, timeout=300, cwd=cwd,
    )


def invoke(command, args, input=None):
    return CliRunner().invoke(command, [str(a) for a in args], input=input)


def assert_user_error(result, code=1):
    """Exit status ``code``, one ``ERROR:`` message on stderr, no traceback."""
    assert result.exit_code == code, (result.stdout, result.stderr)
    assert result.stderr.startswith("ERROR: "), result.stderr
    assert "Traceback" not in result.stderr and "Traceback" not in result.stdout
    assert isinstance(result.exception, SystemExit)  # not an escaped exception


def fmt(value, precision=4):
    return f"{value:.{precision}f}"


# -- one full cycle in real processes ------------------------------------------------


def test_fit_query_info_cycle_in_subprocesses(synthetic_gtx, tmp_path, analytic):
    out = tmp_path / "store"
    fit = run_module("fit", synthetic_gtx, "--out", out, *QUICK_FIT, cwd=tmp_path)
    assert fit.returncode == 0, fit.stderr
    assert "Traceback" not in fit.stderr
    assert (out / "manifest.json").is_file()
    assert "level" in fit.stdout and "coefficients" in fit.stdout
    assert "progress" not in fit.stderr  # stderr is not a terminal: no progress without -v
    assert "progress" not in fit.stdout
    store = geoidspline.open_store(out)
    info = store.info()
    assert f"total      {info['coefficients']:,} coefficients" in fit.stdout

    query = run_module("query", "--store", out, "20", "30", cwd=tmp_path)
    assert query.returncode == 0, query.stderr
    assert query.stdout == fmt(store.undulation(20.0, 30.0)) + "\n"
    assert abs(float(query.stdout) - analytic(20.0, 30.0)) < 1.0

    csv = tmp_path / "points.csv"
    csv.write_text("lat,lon,name\n20,30,a\n95,30,b\n21.5,31.25,c\n")
    batch = run_module("query", "--store", out, "--input", csv, cwd=tmp_path)
    assert batch.returncode == 1
    assert batch.stdout.splitlines() == [
        "lat,lon,name,undulation_m",
        f"20,30,a,{fmt(store.undulation(20.0, 30.0))}",
        "ERROR: line 3: latitude 95 is outside [-90, 90] degrees",
        f"21.5,31.25,c,{fmt(store.undulation(21.5, 31.25))}",
    ]
    assert "Traceback" not in batch.stderr

    # stdin through a real pipe, larger than one 64 KiB read, one bad row far down
    rng = np.random.default_rng(9)
    lat = np.round(rng.uniform(10, 30, 20000), 5)
    lon = np.round(rng.uniform(20, 40, 20000), 5)
    rows = [f"{a},{b},row{i}" for i, (a, b) in enumerate(zip(lat, lon))]
    rows[15000] = "not,a,number"
    piped = run_module("query", "--store", out, "--input", "-", stdin="\n".join(rows) + "\n", cwd=tmp_path)
    assert piped.returncode == 1
    lines = piped.stdout.splitlines()
    assert len(lines) == 20000
    assert lines[15000] == "ERROR: line 15001: latitude/longitude are not numbers: 'not', 'a'"
    good = np.array([i for i in range(20000) if i != 15000])
    values = store.undulation(lat[good], lon[good])
    assert [lines[i] for i in good] == [f"{rows[i]},{fmt(v)}" for i, v in zip(good, values)]

    shown = run_module("info", out, "--json", cwd=tmp_path)
    assert shown.returncode == 0, shown.stderr
    assert json.loads(shown.stdout) == json.loads(json.dumps(info))


def test_module_help_lists_the_commands():
    result = run_module("--help")
    assert result.returncode == 0
    commands = re.findall(r"^\s{2}(\w+)\s", result.stdout.split("Commands:")[1], flags=re.M)
    assert sorted(commands) == ["export", "fit", "info", "plot", "query", "update"]


def test_nonexistent_source_in_a_subprocess(tmp_path):
    result = run_module("fit", tmp_path / "missing.gtx", "--out", tmp_path / "store", cwd=tmp_path)
    assert result.returncode == 1
    assert result.stderr.startswith("ERROR: ")
    assert "missing.gtx" in result.stderr
    assert "Traceback" not in result.stderr
    assert not (tmp_path / "store").exists()


# -- geoid-fit -------------------------------------------------------------------------


def test_fit_prints_levels_and_coefficients(synthetic_gtx, tmp_path, small_store):
    out = tmp_path / "store"
    p = small_store.params
    result = invoke(fit_main, [synthetic_gtx, "--out", out, "--region", *small_store.region.as_tuple(),
                               "--h0", p.h0, "--max-level", p.max_level, "--tolerance", p.tolerance_m,
                               "--refinement", "overlays"])
    assert result.exit_code == 0, result.output
    info = geoidspline.open_store(out).info()
    lines = result.stdout.splitlines()
    assert lines[0].startswith(f"store      {out}")
    assert f"{info['tiles']} tiles" in lines[0]
    table = [ln.split() for ln in lines if re.match(r"^\s+\d+\s", ln)]
    assert [int(row[0]) for row in table] == [lv["level"] for lv in info["levels"]]
    assert [float(row[1]) for row in table] == [lv["h"] for lv in info["levels"]]
    assert [int(row[2].replace(",", "")) for row in table] == [lv["coefficients"] for lv in info["levels"]]
    assert f"total      {info['coefficients']:,} coefficients" in result.stdout
    assert "kept in the store" in result.stdout and "NOT kept" not in result.stdout
    assert "progress" not in result.stderr  # stderr is not a terminal: progress only with -v


def test_a_hierarchical_fit_prints_one_row_per_refinement_step(synthetic_gtx, tmp_path, small_store):
    """The default for a grid: every step refits all levels, so the table has a row per
    step, its finest level and the whole basis's coefficients, ending at the store's."""
    out = tmp_path / "store"
    p = small_store.params
    result = invoke(fit_main, [synthetic_gtx, "--out", out, "--region", *small_store.region.as_tuple(),
                               "--h0", p.h0, "--max-level", p.max_level, "--tolerance", p.tolerance_m])
    assert result.exit_code == 0, result.output
    assert "refinement = hierarchical" in result.stdout
    info = geoidspline.open_store(out).info()
    assert "step  finest level" in result.stdout
    table = [ln.split() for ln in result.stdout.splitlines() if re.match(r"^\s+\d+\s", ln)]
    assert [int(row[0]) for row in table] == list(range(len(table)))
    assert int(table[-1][1]) == max(lv["level"] for lv in info["levels"])
    assert int(table[-1][3].replace(",", "")) == info["coefficients"]
    assert "kept in the store" in result.stdout and "NOT kept" not in result.stdout


def test_fit_quiet_has_no_progress_bar(synthetic_gtx, tmp_path):
    result = invoke(fit_main, [synthetic_gtx, "--out", tmp_path / "store", *QUICK_FIT, "-q"])
    assert result.exit_code == 0, result.output
    assert result.stderr == ""
    assert "coefficients" in result.stdout


def test_fit_json_keeps_exit_status_3_when_the_tolerance_is_not_reached(synthetic_gtx, tmp_path):
    result = invoke(fit_main, [synthetic_gtx, "--out", tmp_path / "store", "--region", 10, 20, 30, 40, "--h0", 0.2,
                               "--max-level", 0, "--tolerance", 0.001, "--json", "-q"])
    assert result.exit_code == 3, result.output
    assert json.loads(result.stdout)["converged"] is False


def test_fit_json_output_parses(synthetic_gtx, tmp_path):
    out = tmp_path / "store"
    result = invoke(fit_main, [synthetic_gtx, "--out", out, *QUICK_FIT, "--json", "-q"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in INFO_KEYS:
        assert key in data
    assert data["wall_seconds"] >= 0
    info = geoidspline.open_store(out).info()
    assert {k: v for k, v in data.items() if k not in ("wall_seconds", "choices", "promise")} == json.loads(json.dumps(info))
    assert data["promise"]["kept"] is True and data["promise"]["node_max_m"] == info["node_max_error_m"]
    assert data["region"] == [10.0, 20.0, 30.0, 40.0]
    assert data["provenance"]["source"] == "synthetic.gtx"


def test_fit_nonexistent_source_is_a_user_error(tmp_path):
    result = invoke(fit_main, [tmp_path / "missing.gtx", "--out", tmp_path / "store"])
    assert_user_error(result)
    assert "missing.gtx" in result.stderr


def test_fit_unknown_catalogue_name_lists_known_names(tmp_path):
    result = invoke(fit_main, ["no-such-geoid", "--out", tmp_path / "store"])
    assert_user_error(result)
    assert "no-such-geoid" in result.stderr
    names = [entry.name for entry in list_catalogue()]
    assert names
    for name in names:
        assert name in result.stderr


def test_fit_refuses_existing_store_unless_overwrite(synthetic_gtx, store_copy):
    before = {p: p.read_bytes() for p in store_copy.rglob("*") if p.is_file()}
    result = invoke(fit_main, [synthetic_gtx, "--out", store_copy, *QUICK_FIT, "-q"])
    assert_user_error(result)
    assert "already exists" in result.stderr and "--overwrite" in result.stderr
    assert {p: p.read_bytes() for p in store_copy.rglob("*") if p.is_file()} == before
    result = invoke(fit_main, [synthetic_gtx, "--out", store_copy, *QUICK_FIT, "-q", "--overwrite"])
    assert result.exit_code == 0, result.output
    assert geoidspline.open_store(store_copy).info()["store_version"] == 2


def test_fit_not_converged_exits_3(synthetic_gtx, tmp_path):
    out = tmp_path / "store"
    args = [synthetic_gtx, "--out", out, "--region", "10", "20", "30", "40",
            "--h0", "0.2", "--max-level", "0", "--tolerance", "1e-6", "-q"]
    result = invoke(fit_main, args)
    assert result.exit_code == 3
    assert "NOT kept (the given --max-level stopped the refinement" in result.stdout
    assert geoidspline.open_store(out).info()["converged"] is False


@pytest.mark.parametrize(
    "args, words, code",
    # a number outside its option's range is a usage error (exit 2, geoidspline.options);
    # bounds that do not make a region are the region's error (exit 1)
    [(["--h0", "0.9"], "'--h0': must be a finite number in [0.0001, 0.5]", 2),
     (["--region", "30", "20", "10", "40"], "south", 1),
     (["--order", "1"], "'--order': must be a whole number in [2, 8]", 2)],
    ids=["h0", "region", "order"],
)
def test_fit_bad_parameters_are_user_errors(synthetic_gtx, tmp_path, args, words, code):
    result = invoke(fit_main, [synthetic_gtx, "--out", tmp_path / "store", *args, "-q"])
    assert_user_error(result, code)
    assert words in result.stderr
    assert not (tmp_path / "store" / "manifest.json").exists()


# -- geoid-query -----------------------------------------------------------------------


@pytest.fixture(scope="module")
def api(small_store):
    return geoidspline.open_store(small_store.path)


def query(small_store, *args, input=None):
    return invoke(query_main, ["--store", small_store.path, *args], input=input)


def test_query_one_point(small_store, api):
    result = query(small_store, "20", "30")
    assert result.exit_code == 0, result.output
    value = api.undulation(20.0, 30.0)
    assert result.stdout == fmt(value) + "\n"
    assert abs(float(result.stdout) - value) <= 0.5e-4
    precise = query(small_store, "--precision", "8", "21.25", "33.5")
    assert precise.stdout.strip() == fmt(api.undulation(21.25, 33.5), 8)
    assert re.fullmatch(r"-?\d+\.\d{8}\n", precise.stdout)


def test_query_negative_coordinates(small_store, api):
    """Southern latitudes and western longitudes are ordinary positional values (and a
    longitude is taken modulo 360: -330 E is 30 E, inside the store's region)."""
    result = query(small_store, "20", "-330")
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == fmt(api.undulation(20.0, 30.0))
    south_west = query(small_store, "-20", "-30.5")  # parsed as a point, not options
    assert_user_error(south_west)
    assert "outside the store's coverage" in south_west.stderr


# Each CSV case: the file's text, the extra CLI arguments, and the rows expected back as
# (the row as written, latitude, longitude) with "" for the header row.
CSV_ROUND_TRIPS = {
    "with header": ("lat,lon\n20,30\n21.5,31.25\n", (),
                    [("lat,lon,undulation_m", None, None), ("20,30", 20.0, 30.0), ("21.5,31.25", 21.5, 31.25)]),
    "no header, no final newline": ("20,30\n25.125,35.5", (),
                                    [("20,30", 20.0, 30.0), ("25.125,35.5", 25.125, 35.5)]),
    "extra columns kept": ("lat,lon,name,height_m\n20,30,Station A,12.5\n22,24,B,-3\n", ("--precision", "3"),
                           [("lat,lon,name,height_m,undulation_m", None, None),
                            ("20,30,Station A,12.5", 20.0, 30.0), ("22,24,B,-3", 22.0, 24.0)]),
    "empty lines skipped": ("lat,lon\n20,30\n\n   \n21,31\n\n", (),
                            [("lat,lon,undulation_m", None, None), ("20,30", 20.0, 30.0), ("21,31", 21.0, 31.0)]),
}


@pytest.mark.parametrize("case", list(CSV_ROUND_TRIPS))
def test_query_input_round_trip(small_store, api, tmp_path, case):
    """Each row comes back as written with its undulation appended, in input order."""
    text, extra, expected = CSV_ROUND_TRIPS[case]
    precision = int(extra[1]) if extra else 4
    csv = tmp_path / "in.csv"
    csv.write_text(text)
    result = query(small_store, "--input", csv, *extra)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [
        row if lat is None else f"{row},{fmt(api.undulation(lat, lon), precision)}" for row, lat, lon in expected
    ]


def test_query_bad_rows_are_reported_in_place(small_store, api, tmp_path):
    csv = tmp_path / "in.csv"
    csv.write_text("lat,lon,id\n20,30,a\nabc,30,b\n95,30,c\n42\nnan,30,d\n21,inf,e\n21,31,f\n")
    result = query(small_store, "--input", csv)
    assert result.exit_code == 1
    lines = result.stdout.splitlines()
    assert len(lines) == 8
    assert lines[0] == "lat,lon,id,undulation_m"
    assert lines[1] == f"20,30,a,{fmt(api.undulation(20.0, 30.0))}"
    assert lines[7] == f"21,31,f,{fmt(api.undulation(21.0, 31.0))}"
    for n, line in zip(range(3, 8), lines[2:7]):
        assert line.startswith(f"ERROR: line {n}: "), line
    assert "not numbers" in lines[2] and "'abc'" in lines[2]
    assert "latitude 95" in lines[3]
    assert "columns" in lines[4]
    assert "'nan'" in lines[5] and "finite" in lines[5]
    assert "'inf'" in lines[6]
    assert "Traceback" not in result.output
    assert "5 row(s)" in result.stderr


def test_query_line_numbers_count_empty_lines(small_store, api, tmp_path):
    csv = tmp_path / "in.csv"
    csv.write_text("lat,lon\n20,30\n\n21,31\n\nxyz,31\n22,32\n")  # the bad row is line 6
    result = query(small_store, "--input", csv)
    assert result.exit_code == 1
    assert result.stdout.splitlines() == [
        "lat,lon,undulation_m",
        f"20,30,{fmt(api.undulation(20.0, 30.0))}",
        f"21,31,{fmt(api.undulation(21.0, 31.0))}",
        "ERROR: line 6: latitude/longitude are not numbers: 'xyz', '31'",
        f"22,32,{fmt(api.undulation(22.0, 32.0))}",
    ]


def test_query_header_after_leading_empty_line(small_store, api, tmp_path):
    csv = tmp_path / "in.csv"
    csv.write_text("\nlat,lon\n20,30\n")
    result = query(small_store, "--input", csv)
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == ["lat,lon,undulation_m", f"20,30,{fmt(api.undulation(20.0, 30.0))}"]


def test_query_reads_stdin(small_store, api):
    result = query(small_store, "--input", "-", input="20,30\n15.5,-335\n")
    assert result.exit_code == 0, result.output
    assert result.stdout.splitlines() == [
        f"20,30,{fmt(api.undulation(20.0, 30.0))}",
        f"15.5,-335,{fmt(api.undulation(15.5, 25.0))}",
    ]


def test_query_nonexistent_store(tmp_path):
    result = invoke(query_main, ["--store", tmp_path / "nowhere", "20", "30"])
    assert_user_error(result)
    assert "nowhere" in result.stderr
    assert result.stdout == ""


def test_query_corrupt_store(store_copy):
    entry = max(json.loads((store_copy / "manifest.json").read_text())["tiles"], key=lambda e: e["bytes"])
    tile = store_copy / entry["file"]
    tile.write_bytes(tile.read_bytes()[:100])
    result = invoke(query_main, ["--store", store_copy, "20", "30"])
    assert_user_error(result)
    assert Path(entry["file"]).name in result.stderr


@pytest.mark.parametrize("args", [[], ["20"], ["--input", "-", "20", "30"]], ids=["neither", "one", "both"])
def test_query_usage_errors(small_store, args):
    result = query(small_store, *args, input="20,30\n")
    assert result.exit_code == 2
    assert result.stderr.startswith("ERROR: ") and "--help" in result.stderr  # click's usage error, our grammar
    if args != ["20"]:
        assert "--input" in result.stderr
    assert "Traceback" not in result.output
    assert result.stdout == ""


# -- geoid-info ------------------------------------------------------------------------


def test_info_json(small_store):
    result = invoke(info_main, [small_store.path, "--json"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    for key in INFO_KEYS:
        assert key in data
    assert data == json.loads(json.dumps(geoidspline.open_store(small_store.path).info()))
    assert all({"h", "coefficients"} <= set(lv) for lv in data["levels"])
    real = sum(p.stat().st_size for p in small_store.path.rglob("*") if p.is_file())
    assert data["bytes"] == real


def test_info_text(small_store):
    result = invoke(info_main, [small_store.path])
    assert result.exit_code == 0, result.output
    info = small_store.info
    for lv in info["levels"]:
        assert re.search(rf"level {lv['level']}\s+h {lv['h']:g}\s+{lv['coefficients']:,} coefficients", result.stdout)
    assert f"coefficients {info['coefficients']:,} in {info['tiles']} tiles, {info['bytes']:,} bytes" in result.stdout
    assert info["provenance"]["sha256"][:16] in result.stdout


def _info_lines(path):
    result = invoke(info_main, ["--store", path])
    assert result.exit_code == 0, result.output
    return result.stdout.splitlines()


def test_info_names_the_source_file_with_its_full_sha256(small_store):
    lines = _info_lines(small_store.path)
    prov = json.loads((small_store.path / "manifest.json").read_text())["provenance"]
    assert prov["source"] == "synthetic.gtx" and len(prov["sha256"]) == 64
    assert lines[1] == "source       synthetic.gtx"
    assert lines[2] == f"  sha256     {prov['sha256']}"
    import hashlib

    assert prov["sha256"] == hashlib.sha256(small_store.gtx.read_bytes()).hexdigest()


def test_info_lists_every_level_from_0_with_chosen_against_used(synthetic_gtx, tmp_path):
    """A hierarchical fit allowed levels 0-4 that stops early and leaves coarse levels
    emptied by refinement: every level is listed, 0 included, with its coefficients."""
    from geoidspline.api import build_store
    from geoidspline.fitting.parameters import FitParameters
    from geoidspline.sources.formats import read_grid
    from geoidspline.sphere.region import Region

    path = tmp_path / "hier"
    params = FitParameters(h0=0.2, max_level=4, tolerance_m=0.05, refinement="hierarchical")
    build_store(read_grid(synthetic_gtx), path, Region.from_bounds(10, 20, 30, 40), params)
    manifest = json.loads((path / "manifest.json").read_text())
    stored = {lv["level"]: lv["coefficients"] for lv in manifest["spline"]["levels"]}
    used = sorted(level for level, count in stored.items() if count)
    assert 0 < len(used) < 5  # the case this test is about: not every allowed level holds coefficients
    lines = _info_lines(path)
    rows = [ln for ln in lines if re.match(r"  level \d", ln)]
    assert [int(ln.split()[1]) for ln in rows] == [0, 1, 2, 3, 4]
    for ln in rows:
        level, count = int(ln.split()[1]), int(ln.split()[4].replace(",", ""))
        assert count == stored.get(level, 0)
        assert float(ln.split()[3]) == pytest.approx(0.2 / 2 ** level, rel=1e-5)
    assert f"levels       {len(used)} of 5 chosen levels used (levels 0-4 allowed; " in "\n".join(lines)
    info = geoidspline.open_store(path).info()
    assert (info["levels_chosen"], info["levels_used"]) == (5, len(used))
    assert info["fit_parameters"]["refinement"] == "hierarchical"


def test_info_shows_the_update_history(store_copy, tmp_path):
    from geoidspline.sources.base import Provenance
    from geoidspline.sources.formats import write_gtx
    from geoidspline.sources.grid import GeoidGrid
    from geoidspline.sphere.region import Region
    from geoidspline.api.regional import update_store

    lat = np.arange(14.0, 26.0 + 1e-9, 0.5)
    lon = np.arange(24.0, 36.0 + 1e-9, 0.5)
    values = (np.full((lat.size, lon.size), 30.0) + 0.1 * lat[:, None]).astype(np.float32).astype(float)
    national = write_gtx(tmp_path / "national.gtx",
                         GeoidGrid(lat, lon, values, Provenance(source="national", model="national", kind="grid")))
    from geoidspline.sources.formats import read_grid

    record = update_store(store_copy, read_grid(national), Region(18.0, 28.0, 22.0, 32.0), blend_width_km=100.0)
    lines = _info_lines(store_copy)
    history = lines[lines.index("history      2 records") + 1:]
    manifest = json.loads((store_copy / "manifest.json").read_text())
    fit_record, update_record = manifest["history"]
    assert history[0].startswith(f"  {fit_record['time']}  fit     v1  synthetic.gtx sha256 {fit_record['sha256'][:12]}...")
    assert history[0].endswith("region S 10 W 20 N 30 E 40")
    assert history[1] == (
        f"  {update_record['time']}  update  v2  national.gtx sha256 {record['sha256'][:12]}...  "
        f"region S 18 W 28 N 22 E 32, blend 100 km, {record['tiles_rewritten']} tiles rewritten, "
        f"{record['coefficients_added']:+,d} coefficients, max |error| inside {record['max_error_m']:.4f} m of "
        f"{record['tolerance_m']:g} m" + ("" if record["converged"] else " (NOT reached)"))
    assert record["coefficients_added"] > 0 and record["tiles_rewritten"] > 0
    assert geoidspline.open_store(store_copy).info()["history"] == manifest["history"]


def test_info_errors(tmp_path):
    result = invoke(info_main, [tmp_path / "nowhere"])
    assert_user_error(result)
    (tmp_path / "half" / "tiles").mkdir(parents=True)
    result = invoke(info_main, [tmp_path / "half"])
    assert_user_error(result)
    assert "not a geoidspline store" in result.stderr


def test_group_dispatches_to_the_commands(small_store, api):
    runner = CliRunner()
    result = runner.invoke(geoidspline_main, ["query", "--store", str(small_store.path), "20", "30"])
    assert result.exit_code == 0, result.output
    assert result.stdout.strip() == fmt(api.undulation(20.0, 30.0))
    result = runner.invoke(geoidspline_main, ["info", str(small_store.path), "--json"])
    assert json.loads(result.stdout)["tiles"] == small_store.info["tiles"]
    for name in ("fit", "query", "info"):
        assert runner.invoke(geoidspline_main, [name, "--help"]).exit_code == 0


def test_large_plain_batches_take_the_vectorised_parser_with_identical_output(small_store, tmp_path):
    """Hundreds of valid rows go through the one-pass parser; one bad row among them
    sends its batch back to the row-by-row parser, which names the line."""
    rng = np.random.default_rng(8)
    lat = rng.uniform(12, 28, 500)
    lon = rng.uniform(22, 38, 500)
    rows = [f"{a:.6f},{b:.6f},name{i}" for i, (a, b) in enumerate(zip(lat, lon))]
    runner = CliRunner()
    good = runner.invoke(query_main, ["--store", str(small_store.path), "--input", "-"], input="\n".join(rows) + "\n")
    assert good.exit_code == 0
    values = [float(line.rsplit(",", 1)[1]) for line in good.output.strip().splitlines()]
    expected = geoidspline.open_store(small_store.path).undulation(lat, lon)
    np.testing.assert_allclose(values, expected, atol=0.6e-4)
    rows[250] = "95,30,bad"
    bad = runner.invoke(query_main, ["--store", str(small_store.path), "--input", "-"], input="\n".join(rows) + "\n")
    assert bad.exit_code == 1
    out = bad.output.strip().splitlines()
    assert out[250].startswith("ERROR: line 251: latitude 95")
    assert out[:250] == good.output.strip().splitlines()[:250]
