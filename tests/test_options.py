"""Every numeric option and API argument checked by one rule (issue 24 item 4), and
CSV numbers read as plain ASCII decimals only.

The oracle is the rule table (``geoidspline.options.RULES``: the documented ranges) and a
regex for a plain decimal written here; hypothesis feeds arbitrary floats and strings to
every numeric option of every command: the command either goes on (and then fails for
the missing store or source, exit 1, one ERROR line) or refuses the value (exit 2, one
``ERROR: Invalid value for '--opt'`` line naming the range), never with a traceback.
"""

from __future__ import annotations

import math
import re

import pytest
from click.testing import CliRunner

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is not installed (pip install -e '.[test]')")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import geoidspline  # noqa: E402
from geoidspline.cli import export, fit, info, plot, query, update  # noqa: E402
from geoidspline.errors import GeoidSplineError  # noqa: E402
from geoidspline.fitting.executors import Executor  # noqa: E402
from geoidspline.fitting.parameters import FitParameters  # noqa: E402
from geoidspline.options import RULES, OptionError, check_number  # noqa: E402

PLAIN_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")
SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def keeps_rule(text: str, rule: str) -> bool:
    """The oracle: a plain decimal, finite, whole for a count, inside the rule's range."""
    text = text.strip(" \t\r\n")
    if not PLAIN_DECIMAL.fullmatch(text):
        return False
    value = float(text)
    r = RULES[rule]
    if not math.isfinite(value) or (r.integer and not value.is_integer()):
        return False
    low_ok = value > r.low if r.low_open else value >= r.low
    high_ok = value < r.high if r.high_open else value <= r.high
    return low_ok and high_ok


#: (command, arguments before the option, option, rule, arguments after it). The other
#: arguments name a store or source that does not exist, so a value that passes goes on
#: to a quick "no such store/file" error.
OPTIONS = [
    (fit.main, ["missing.gtx", "--store", "out"], "--tolerance", "tolerance_m", []),
    (fit.main, ["missing.gtx", "--store", "out"], "--h0", "h0", []),
    (fit.main, ["missing.gtx", "--store", "out"], "--max-level", "max_level", []),
    (fit.main, ["missing.gtx", "--store", "out"], "--order", "order", []),
    (fit.main, ["missing.gtx", "--store", "out"], "--workers", "workers", []),
    (fit.main, ["missing.gtx", "--store", "out"], "--sample-spacing", "sample_spacing_deg", []),
    (update.main, ["missing.gtx", "--store", "nostore", "--region", "10", "20", "30", "40"], "--blend-width",
     "blend_width_km", []),
    (update.main, ["missing.gtx", "--store", "nostore", "--region", "10", "20", "30", "40"], "--tolerance",
     "tolerance_m", []),
    (update.main, ["missing.gtx", "--store", "nostore", "--region", "10", "20", "30", "40"], "--workers",
     "workers", []),
    (update.main, ["missing.gtx", "--store", "nostore", "--region", "10", "20", "30", "40"], "--wait",
     "wait_seconds", []),
    (info.main, ["--store", "nostore", "--check-against", "missing.gfc"], "--points", "points", []),
    (export.main, ["--store", "nostore", "--out", "x.gtx"], "--spacing", "spacing_deg", []),
    (plot.main, ["--store", "nostore", "--out", "x.png"], "--spacing", "plot_spacing_deg", []),
    (plot.main, ["--store", "nostore", "--out", "x.png"], "--dpi", "dpi", []),
    (query.main, ["--store", "nostore"], "--precision", "precision", ["10", "20"]),
    (query.main, ["--store", "nostore", "--height-in", "ellipsoidal"], "--height-column", "height_column",
     ["10", "20", "5"]),
]

values = st.one_of(
    st.floats().map(repr),
    st.floats().map(lambda v: f"{v:g}"),
    st.integers(-10**20, 10**20).map(str),
    st.text(max_size=8),
    st.sampled_from(["inf", "-inf", "nan", "NaN", "1e-300", "1e400", "0", "-0", "1_0", "\u0663", "\uff11",
                     "0x10", " 5 ", "2.0", "2.5", "1e3", "-1", "", "12", "13", "0.5", "1e-4", "1e-9"]),
)


def run(command, args):
    result = CliRunner().invoke(command, args, prog_name=command.name)
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    errors = [line for line in result.stderr.splitlines() if line.startswith("ERROR:")]
    assert "Traceback" not in result.stderr + result.stdout
    return result, errors


@pytest.mark.parametrize("command, before, option, rule, after", OPTIONS,
                         ids=[f"{c.name}{o}" for c, _, o, _, _ in OPTIONS])
@SETTINGS
@given(text=values)
def test_every_numeric_option_is_refused_with_its_range_or_goes_on(tmp_path, command, before, option, rule, after,
                                                                   text):
    args = before + [f"{option}={text}"] + after
    result, errors = run(command, [str(tmp_path / a) if a in ("out", "nostore", "x.gtx", "x.png") else a
                                   for a in args])
    assert result.exit_code in (1, 2) and len(errors) == 1, (result.exit_code, result.stderr)
    refused = f"Invalid value for '{option}'" in errors[0]
    assert refused == (not keeps_rule(text, rule)), errors[0]
    if refused:
        r = RULES[rule]
        assert result.exit_code == 2
        assert f"{r.low:g}, {r.high:g}" in errors[0]  # the range, in the message


@pytest.mark.parametrize("command, before", [
    (fit.main, ["missing.gtx", "--store", "out"]),
    (export.main, ["--store", "nostore", "--out", "x.gtx", "--spacing", "1"]),
    (plot.main, ["--store", "nostore", "--out", "x.png"]),
])
@SETTINGS
@given(text=values, slot=st.integers(0, 3))
def test_region_bounds_are_refused_with_their_range_or_go_on(tmp_path, command, before, text, slot):
    bounds = ["10", "20", "30", "40"]
    bounds[slot] = text
    if text.startswith("-") and not PLAIN_DECIMAL.fullmatch(text.strip()):
        return  # an option to click, not a bound ('-h' is help)
    result, errors = run(command, [str(tmp_path / a) if a in ("out", "nostore", "x.gtx", "x.png") else a
                                   for a in before] + ["--region", *bounds])
    assert result.exit_code in (1, 2) and len(errors) == 1, (result.exit_code, result.stderr)
    assert ("Invalid value for '--region'" in errors[0]) == (not keeps_rule(text, "region_bound_deg")), errors[0]


@pytest.mark.parametrize("text, words", [("nan", "finite"), ("1_0", "not numbers"), ("\u0661\u0660", "not numbers"),
                                         ("inf", "finite"), ("-Infinity", "finite"), ("1e999", "finite")])
def test_a_point_on_the_command_line_is_a_plain_decimal(small_store, text, words):
    """One point on the command line follows a CSV row's rules: one ERROR line, exit 1."""
    result, errors = run(query.main, ["--store", str(small_store.path), text, "30"])
    assert result.exit_code == 1 and len(errors) == 1 and words in errors[0], errors


# -- the same rules in Python -----------------------------------------------------------


@pytest.mark.parametrize("field, value", [
    ("tolerance_m", math.inf), ("tolerance_m", 0.0), ("h0", 0.0), ("h0", 1e-300), ("h0", math.nan),
    ("max_level", 2.5), ("max_level", 13), ("order", True), ("sample_spacing_deg", 1e-300),
])
def test_fit_parameters_refuse_what_the_options_refuse(field, value):
    with pytest.raises(OptionError, match=rf"{field} must be .* in [\[(]"):
        FitParameters(**{field: value})


def test_fit_refuses_bad_numbers_before_any_work(small_store, tmp_path):
    """The API's keyword arguments go through the same rules (choose=True computes
    with them first: log2(h0) was a math domain error)."""
    for kwargs in ({"h0": 0.0}, {"tolerance_m": math.inf}, {"h0": 1e-300}):
        with pytest.raises(OptionError):
            geoidspline.fit(small_store.grid, tmp_path / "s", region=small_store.region, choose=True, **kwargs)
    assert not (tmp_path / "s").exists()
    with pytest.raises(GeoidSplineError, match="workers must be"):
        Executor(workers=0)


@pytest.mark.parametrize("kwargs", [{"wait_seconds": math.nan}, {"wait_seconds": -1.0},
                                    {"blend_width_km": math.inf}, {"tolerance_m": 0.0}])
def test_update_refuses_bad_numbers_and_leaves_the_store(store_copy, small_store, kwargs):
    before = (store_copy / "manifest.json").read_bytes()
    with pytest.raises(OptionError):
        geoidspline.update(store_copy, small_store.grid, (15.0, 25.0, 25.0, 35.0), **kwargs)
    assert (store_copy / "manifest.json").read_bytes() == before


@given(st.floats(allow_nan=True, allow_infinity=True), st.sampled_from(sorted(RULES)))
@settings(max_examples=300, deadline=None)
def test_check_number_agrees_with_the_table(value, rule):
    r = RULES[rule]
    ok = keeps_rule(repr(value), rule)
    if ok:
        assert check_number("x", value, rule) == (int(value) if r.integer else value)
    else:
        with pytest.raises(OptionError, match="x must be"):
            check_number("x", value, rule)


def test_a_level_0_finer_than_the_data_is_refused(small_store, tmp_path):
    """h0 below half the data spacing ran for minutes in GBs; now one FitError."""
    from geoidspline.errors import FitError

    with pytest.raises(FitError, match=r"h0 0.001 is finer than 0.5 x the data spacing .* give h0 >= 0.01745"):
        geoidspline.fit(small_store.grid, tmp_path / "s", region=small_store.region, h0=0.001, max_level=0)


# -- CSV numbers --------------------------------------------------------------------------

ascii_decimal = st.builds(
    lambda sign, whole, frac, exp: f"{sign}{whole}{frac}{exp}",
    st.sampled_from(["", "+", "-"]), st.from_regex(r"[0-9]{1,2}", fullmatch=True),
    st.sampled_from(["", ".", ".5", ".25"]), st.sampled_from(["", "e0", "E+1", "e-1"]))
python_only = st.one_of(
    st.builds(lambda a, b: f"{a}_{b}", st.integers(1, 9), st.integers(0, 9)),  # float() reads 1_0
    st.text(alphabet="\u0660\u0661\u0662\u0663\u06f1\uff11\u0967", min_size=1, max_size=3),  # non-ASCII digits
    st.sampled_from(["nan", "inf", "-Infinity", "0x1p3", "1e400"]),
)


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(lat=st.one_of(ascii_decimal, python_only), fast=st.booleans())
def test_csv_latitudes_are_plain_ascii_decimals(small_store, lat, fast):
    """Rows with a plain decimal are answered; Python-only spellings (``-3_3.45``,
    Arabic-Indic digits, nan) are ERROR rows; the same in the vectorised path (64+ rows)
    and the row-by-row one."""
    rows = 64 if fast else 1
    text = "".join(f"{lat},30\n" for _ in range(rows))
    result = CliRunner().invoke(query.main, ["--store", str(small_store.path), "--input", "-", "--outside", "nan"],
                                input=text, prog_name="geoid-query")
    lines = result.stdout.splitlines()
    if PLAIN_DECIMAL.fullmatch(lat) and math.isfinite(float(lat)) and abs(float(lat)) <= 90:
        assert result.exit_code == 0 and len(lines) == rows
        assert all(line.startswith(f"{lat},30,") for line in lines)
    else:
        assert result.exit_code == 1 and len(lines) == rows
        assert all(line.startswith("ERROR: line ") for line in lines), lines[:2]
