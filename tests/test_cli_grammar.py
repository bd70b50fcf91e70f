"""One grammar across the commands: --version, --store, ERROR lines, update options."""

from __future__ import annotations

import json

import pytest
from test_cli import QUICK_FIT, assert_user_error, invoke, run_module

import geoidspline
from geoidspline.cli.export import main as export_main
from geoidspline.cli.fit import main as fit_main
from geoidspline.cli.info import main as info_main
from geoidspline.cli.query import main as query_main
from geoidspline.cli.update import main as update_main

COMMANDS = {"fit": fit_main, "update": update_main, "query": query_main, "info": info_main, "export": export_main}


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_every_command_has_version_help_and_store(name):
    version = invoke(COMMANDS[name], ["--version"])
    assert version.exit_code == 0 and version.stdout.strip() == f"geoidspline {geoidspline.__version__}"
    helped = invoke(COMMANDS[name], ["-h"])
    assert helped.exit_code == 0 and "--store DIR" in helped.stdout
    for flag in ("-v, --verbose", "-q, --quiet", "--version"):
        assert flag in helped.stdout


@pytest.mark.parametrize("name", sorted(COMMANDS))
def test_a_bad_option_is_one_error_line(name):
    result = invoke(COMMANDS[name], ["--no-such-option"])
    assert_user_error(result, code=2)
    assert "--no-such-option" in result.stderr and "--help" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1


def test_the_module_entry_point_has_every_command_and_the_version():
    listed = run_module("--help")
    assert listed.returncode == 0
    for name in COMMANDS:
        assert name in listed.stdout
    version = run_module("--version")
    assert version.stdout.strip() == f"geoidspline {geoidspline.__version__}"
    bad = run_module("nosuchcommand")
    assert bad.returncode == 2 and bad.stderr.startswith("ERROR: ")


def test_the_store_is_named_the_same_way_everywhere_and_old_spellings_still_work(small_store, tmp_path):
    store = str(small_store.path)
    for args in (["--store", store], [store]):
        info = invoke(info_main, [*args, "--json"])
        assert info.exit_code == 0 and json.loads(info.stdout)["coefficients"] > 0
        out = tmp_path / f"g{len(args)}.gtx"
        export = invoke(export_main, [*args, "--out", out, "--spacing", "2"])
        assert export.exit_code == 0 and out.stat().st_size > 40
    twice = invoke(info_main, [store, "--store", str(tmp_path / "other")])
    assert_user_error(twice, code=2)
    assert "twice" in twice.stderr


def test_fit_writes_with_store_and_with_the_old_out(synthetic_gtx, tmp_path):
    for flag in ("--store", "--out"):
        out = tmp_path / flag.strip("-")
        result = invoke(fit_main, [synthetic_gtx, flag, out, *QUICK_FIT, "-q"])
        assert result.exit_code in (0, 3), result.stderr
        assert (out / "manifest.json").is_file()


@pytest.mark.parametrize("option", [["--h0", "0.05"], ["--max-level", "3"], ["--order", "6"],
                                    ["--method", "interpolation"], ["--sample-spacing", "0.1"], ["--overwrite"],
                                    ["--scheduler", "local"]])
def test_fit_update_refuses_the_options_it_cannot_honour(store_copy, synthetic_gtx, option):
    before = (store_copy / "manifest.json").read_bytes()
    result = invoke(fit_main, [synthetic_gtx, "--update", store_copy, "--region", "15", "25", "20", "30", *option])
    assert_user_error(result, code=2)
    assert option[0] in result.stderr and "geoid-update" in result.stderr
    assert (store_copy / "manifest.json").read_bytes() == before


def test_geoid_update_and_the_old_fit_update_give_the_same_store(store_copy, synthetic_gtx, tmp_path):
    import shutil

    other = tmp_path / "other"
    shutil.copytree(store_copy, other)
    new = invoke(update_main, [synthetic_gtx, "--store", store_copy, "--region", "15", "25", "20", "30", "--json"])
    old = invoke(fit_main, [synthetic_gtx, "--update", other, "--region", "15", "25", "20", "30", "--json", "-q"])
    assert new.exit_code == old.exit_code and new.exit_code in (0, 3), new.stderr
    a, b = json.loads(new.stdout), json.loads(old.stdout)
    assert a["store_version"] == b["store_version"] == 2
    assert a["tiles_rewritten"] == b["tiles_rewritten"] and a["max_error_m"] == b["max_error_m"]


def test_library_messages_name_options_on_the_command_line(small_store, synthetic_gtx):
    result = invoke(fit_main, [synthetic_gtx, "--store", small_store.path, *QUICK_FIT, "-q"])
    assert_user_error(result)
    assert "--overwrite" in result.stderr and "overwrite=True" not in result.stderr


def test_the_api_refuses_longitudes_no_coordinate_has(small_store):
    """Wrapping 1e308 degrees would give a plausible number: refused, small and large batches."""
    from geoidspline.errors import CoordinateError

    store = geoidspline.open_store(small_store.path)
    with pytest.raises(CoordinateError, match="longitude"):
        store.undulation(20.0, 1e308)
    with pytest.raises(CoordinateError, match="longitude"):
        store.undulation([20.0] * 5000, [30.0] * 4999 + [-2e6])
    assert store.undulation(20.0, 30.0 + 720.0) == pytest.approx(store.undulation(20.0, 30.0), abs=1e-9)
