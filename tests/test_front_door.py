"""One front door: ``geoidspline.fit``/``update``/the batch engine and ``geoid-fit``/
``geoid-update``/``geoid-query`` with the same arguments give the same results, bit for bit
(the commands only parse, call :mod:`geoidspline.api` and print)."""

from __future__ import annotations

import io
import json
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

import geoidspline
from geoidspline import api
from geoidspline.cli.fit import main as fit_main
from geoidspline.cli.query import main as query_main
from geoidspline.cli.update import main as update_main
from geoidspline.errors import CoordinateError
from geoidspline.sources.base import Provenance
from geoidspline.sources.formats import write_gtx
from geoidspline.sources.grid import GeoidGrid

REGION = (10.0, 20.0, 20.0, 30.0)


def invoke(command, args, input=None):
    return CliRunner().invoke(command, [str(a) for a in args], input=input)


def coefficients(path):
    """Every level's (level, h, keys, coefficients) as bytes: equal only if bitwise equal."""
    spline = geoidspline.open_store(path, lazy=False).spline.full
    return [(lv.level, lv.h, lv.indices.tobytes(), lv.coefficients.tobytes()) for lv in spline.levels]


def manifest(path):
    return json.loads((path / "manifest.json").read_text())


def test_fit_and_geoid_fit_build_the_same_store(synthetic_gtx, tmp_path):
    """No parameter but the tolerance given: both choose the rest the same way."""
    result = invoke(fit_main, [synthetic_gtx, "--store", tmp_path / "cli", "--region", *REGION,
                               "--tolerance", 0.05, "-q"])
    assert result.exit_code == 0, result.output
    geoidspline.fit(synthetic_gtx, tmp_path / "api", region=REGION, tolerance_m=0.05)
    assert coefficients(tmp_path / "cli") == coefficients(tmp_path / "api")
    by_cli, by_api = manifest(tmp_path / "cli")["fit"], manifest(tmp_path / "api")["fit"]
    assert by_cli["parameters"] == by_api["parameters"]
    assert by_cli["choices"] == by_api["choices"]
    assert by_cli["method"] == by_api["method"]


def test_given_parameters_are_used_by_both(synthetic_gtx, tmp_path):
    args = ["--h0", 0.2, "--max-level", 1, "--order", 4, "--refinement", "overlays"]
    result = invoke(fit_main, [synthetic_gtx, "--store", tmp_path / "cli", "--region", *REGION,
                               "--tolerance", 0.5, *args, "-q"])
    assert result.exit_code == 0, result.output
    geoidspline.fit(synthetic_gtx, tmp_path / "api", region=REGION, tolerance_m=0.5, h0=0.2, max_level=1,
                    order=4, refinement="overlays")
    assert coefficients(tmp_path / "cli") == coefficients(tmp_path / "api")
    params = manifest(tmp_path / "api")["fit"]["parameters"]
    assert (params["h0"], params["max_level"], params["order"], params["refinement"]) == (0.2, 1, 4, "overlays")


def test_the_manifest_names_the_method_used(synthetic_gtx, tmp_path):
    """fit.method says what was done: §5.3 for the hierarchical basis, §5.2 for overlays."""
    geoidspline.fit(synthetic_gtx, tmp_path / "h", region=REGION, tolerance_m=0.5, h0=0.2, max_level=1,
                    refinement="hierarchical")
    geoidspline.fit(synthetic_gtx, tmp_path / "o", region=REGION, tolerance_m=0.5, h0=0.2, max_level=1,
                    refinement="overlays")
    assert manifest(tmp_path / "h")["fit"]["method"] == \
        "hierarchical B-spline basis by least squares (Lehmann 2013, section 5.3)"
    assert manifest(tmp_path / "o")["fit"]["method"] == "hierarchical overlays (Lehmann 2013, section 5.2)"


def test_update_and_geoid_update_give_the_same_store(small_store, synthetic_grid, tmp_path):
    g = synthetic_grid
    bump = np.where((np.abs(g.latitude[:, None] - 20.0) < 5) & (np.abs(g.longitude[None, :] - 30.0) < 5), 0.5, 0.0)
    bumped = GeoidGrid(g.latitude, g.longitude, g.values + bump, Provenance(source="bumped", model="bumped"))
    source = write_gtx(tmp_path / "bumped.gtx", bumped)
    for name in ("cli", "api"):
        shutil.copytree(small_store.path, tmp_path / name)
    result = invoke(update_main, [source, "--store", tmp_path / "cli", "--region", 16, 26, 24, 34,
                                  "--blend-width", 200, "--json", "-q"])
    assert result.exit_code in (0, 3), result.output
    by_cli = json.loads(result.stdout)
    by_api = geoidspline.update(tmp_path / "api", source, (16, 26, 24, 34), blend_width_km=200)
    assert by_cli["store_version"] == by_api["store_version"] == 2
    assert by_cli["tiles_rewritten"] == by_api["tiles_rewritten"] > 0
    assert coefficients(tmp_path / "cli") == coefficients(tmp_path / "api")
    assert coefficients(tmp_path / "api") != coefficients(small_store.path)


def test_the_batch_engine_is_what_geoid_query_streams_through(small_store):
    rows = "lat,lon\n20,30\n95,30\n21.5,33.25\nabc,1\n"
    result = invoke(query_main, ["--store", small_store.path, "--input", "-", "--deflection"], input=rows)
    assert result.exit_code == 1  # two bad rows
    store = api.open_store(small_store.path)
    out = io.StringIO()
    bad = api.query_rows(api.BatchQuery(store, is_store=True, deflection=True), io.StringIO(rows), out)
    assert bad == 2
    assert out.getvalue() == result.stdout
    lines = out.getvalue().splitlines()
    assert lines[0] == "lat,lon,undulation_m,xi_arcsec,eta_arcsec,dNdn_m_per_m,dNde_m_per_m"
    assert float(lines[1].split(",")[2]) == pytest.approx(float(store.undulation(20.0, 30.0)), abs=1e-4)
    assert lines[2].startswith("ERROR: line 3: latitude 95 is outside")


def test_one_point_through_the_engine(small_store):
    q = api.BatchQuery(api.open_store(small_store.path), is_store=True)
    assert api.query_point(q, (20.0, 30.0)) == invoke(query_main, ["--store", small_store.path, 20, 30]).stdout.strip()
    with pytest.raises(CoordinateError, match="latitude 95 is outside"):
        api.query_point(q, (95.0, 30.0))
