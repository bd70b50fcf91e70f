"""Property-based tests of geoid-query's rows (hypothesis).

Random CSV input (numbers in and out of range and coverage, junk, byte-order marks,
blank lines, CR LF, quotes, extra columns, huge/NaN/inf values, bytes that are not
UTF-8) through ``geoid-query --input``: every non-blank line after an optional header
gives exactly one output line, in order: the row with its value, or an
``ERROR: line N: ...`` row for that line; never a traceback; the exit status is 1
exactly when there is an ERROR row. The expected outcome of each line comes from an
oracle written from the documented rules (README, ``geoid-query --help``), not from
the parser. The session's small store covers 10..30 N, 20..40 E.
"""

from __future__ import annotations

import json
import math
import re

import numpy as np
import pytest
from click.testing import CliRunner

hypothesis = pytest.importorskip("hypothesis", reason="hypothesis is not installed (pip install -e '.[test]')")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402

import geoidspline  # noqa: E402
from geoidspline.cli.query import main as query_main  # noqa: E402
from geoidspline.sphere.region import Region  # noqa: E402

REGION = Region(10.0, 20.0, 30.0, 40.0)  # conftest.STORE_REGION
MAX_LON = 1e6
BOM = b"\xef\xbb\xbf"
NAME = re.compile(r"[^\W\d][\w .\-]*?(\s*[(\[][^()\[\]]*[)\]])?")
HEMISPHERE_FIRST = re.compile(r"[NSEWnsew]\s*[-+]?[0-9.]")
PROPERTY_SETTINGS = settings(max_examples=150, deadline=None,
                             suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])


# -- the oracle: the documented rules ---------------------------------------------------


def unquote(field):
    field = field.strip()
    if len(field) >= 2 and field[0] == field[-1] == '"':
        field = field[1:-1].strip()
    return field


#: What README documents as a number in a row: a plain ASCII decimal (optional sign,
#: digits, optional fraction, optional exponent); not 1_000, non-ASCII digits, nan, inf.
PLAIN_DECIMAL = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?")


def as_number(field):
    text = unquote(field)
    return float(text) if PLAIN_DECIMAL.fullmatch(text) else None


def python_float(text):
    """Whether Python's float() reads ``text`` (nan, inf, 1_0 are never column names)."""
    try:
        float(text)
        return True
    except ValueError:
        return False


def is_name(field):
    text = unquote(field)
    return not python_float(text) and bool(NAME.fullmatch(text)) and not HEMISPHERE_FIRST.match(text)


def expected_point(row):
    """(lat, lon) the row must be answered at, or None when it must be an ERROR row."""
    fields = row.split(",")
    if len(fields) < 2:
        return None
    lat, lon = as_number(fields[0]), as_number(fields[1])
    if lat is None or lon is None or not (math.isfinite(lat) and math.isfinite(lon)):
        return None
    if abs(lat) > 90.0 or abs(lon) > MAX_LON or not REGION.contains(lat, lon):
        return None
    return lat, lon


def expected_lines(data: bytes):
    """(header line or None, [(line number, row text, point or None)]) for the input."""
    if data.startswith(BOM):
        data = data[len(BOM):]
    header = None
    rows = []
    for number, raw in enumerate(data.split(b"\n"), start=1):
        if number == len(data.split(b"\n")) and raw == b"":
            break  # the newline ending the last line
        row = raw.decode("utf-8", "replace").rstrip("\r")
        if not row.strip():
            continue
        fields = row.split(",")
        if not rows and header is None and len(fields) >= 2 and is_name(fields[0]) and is_name(fields[1]):
            header = row
            continue
        rows.append((number, row, expected_point(row)))
    return header, rows


# -- random rows ------------------------------------------------------------------------

finite = st.floats(allow_nan=False, allow_infinity=False)
inside_lat = st.floats(10.0, 30.0)
inside_lon = st.floats(20.0, 40.0)
any_number = st.one_of(finite, st.just(float("nan")), st.just(float("inf")), st.just(float("-inf")),
                       st.floats(-1e7, 1e7), st.sampled_from([1e308, -1e308, 90.0, -90.0, 90.0000001, 1e6, -1e6,
                                                              1e6 + 0.5, 0.0, -0.0]))
junk_text = st.text(alphabet=st.characters(blacklist_characters="\n", blacklist_categories=("Cs",)), max_size=12)


def spelled(value):
    """A number as a user might write it."""
    return st.sampled_from([repr(value), f"{value:.6f}", f"{value:g}", f" {value} ", f'"{value}"', f"{value:e}"])


@st.composite
def number_field(draw, values):
    value = draw(values)
    if isinstance(value, float) and not math.isfinite(value):
        return draw(st.sampled_from([str(value), str(value).upper(), f'"{value}"', "1e999" if value > 0 else "-1e999"]))
    return draw(spelled(value))


@st.composite
def row(draw):
    kind = draw(st.sampled_from(["inside", "inside", "inside", "outside", "numbers", "junk", "short", "hemisphere",
                                 "wrapped", "blank"]))
    if kind == "blank":
        return draw(st.sampled_from(["", " ", "\t", "  \t "]))
    if kind == "short":
        return draw(number_field(any_number))
    if kind == "junk":
        return draw(junk_text) + draw(st.sampled_from(["", ",", ",30", ",abc,1"]))
    if kind == "hemisphere":
        lat, lon = draw(inside_lat), draw(inside_lon)
        return f"{lat:.2f}{draw(st.sampled_from('NS'))},{lon:.2f}{draw(st.sampled_from('EW'))}"
    if kind == "inside":
        lat, lon = draw(number_field(inside_lat)), draw(number_field(inside_lon))
    elif kind == "wrapped":
        lat = draw(number_field(inside_lat))
        lon = draw(number_field(st.builds(lambda x, k: x + 360.0 * k, inside_lon, st.integers(-2777, 2776))))
    elif kind == "outside":
        lat, lon = draw(number_field(st.floats(-90, 90))), draw(number_field(st.floats(-180, 19.9)))
    else:
        lat, lon = draw(number_field(any_number)), draw(number_field(any_number))
    extra = draw(st.lists(st.text(alphabet=st.characters(blacklist_characters=",\n\r", blacklist_categories=("Cs",)),
                                  max_size=6), max_size=3))
    return ",".join([lat, lon, *extra])


@st.composite
def csv_input(draw):
    rows = draw(st.lists(row(), min_size=0, max_size=30))
    if draw(st.booleans()):  # sometimes a long run of good rows: the vectorised parser's path
        rows += [f"{draw(inside_lat)},{draw(inside_lon)}" for _ in range(draw(st.integers(64, 80)))]
        rows.insert(draw(st.integers(0, len(rows))), draw(row()))
    header = draw(st.sampled_from([None, None, "lat,lon", "Latitude,Longitude,name", '"lat","lon"', "y (deg),x (deg)"]))
    if header is not None:
        rows.insert(0, header)
    ending = draw(st.sampled_from(["\n", "\r\n"]))
    text = ending.join(rows) + draw(st.sampled_from(["", ending]))
    data = text.encode("utf-8", "surrogatepass")
    if draw(st.booleans()):
        data = BOM + data
    if draw(st.integers(0, 9)) == 0:  # bytes that are not UTF-8 somewhere
        at = draw(st.integers(0, len(data)))
        data = data[:at] + b"\xff\xfe" + data[at:]
    return data


# -- the properties ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def api(small_store):
    """The small store, opened once and handed to every geoid-query run of this module
    (opening reads its tiles again each time: 0.1-1 s a run, most of these tests' time)."""
    store = geoidspline.open_store(small_store.path, lazy=False)
    opened = geoidspline.open_store
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(geoidspline, "open_store",
                      lambda path, **kw: store if str(path) == str(small_store.path) else opened(path, **kw))
        yield store


def run(small_store, data, *args, via_file=None):
    if via_file is not None:
        via_file.write_bytes(data)
        return CliRunner().invoke(query_main, ["--store", str(small_store.path), "--input", str(via_file), *args])
    return CliRunner().invoke(query_main, ["--store", str(small_store.path), "--input", "-", *args], input=data)


def check_no_traceback(result):
    assert result.exception is None or isinstance(result.exception, SystemExit), result.exception
    assert "Traceback" not in result.stdout + result.stderr


@PROPERTY_SETTINGS
@given(data=csv_input(), through_file=st.booleans())
def test_every_line_is_a_value_row_or_an_error_row_in_order(small_store, api, tmp_path, data, through_file):
    result = run(small_store, data, via_file=tmp_path / "rows.csv" if through_file else None)
    check_no_traceback(result)
    header, rows = expected_lines(data)
    out = result.stdout.split("\n")
    assert out[-1] == ""  # every line ends with a newline
    out = out[:-1]
    if header is not None:
        assert out[0] == header.rstrip() + ",undulation_m"
        out = out[1:]
    assert len(out) == len(rows), (out, rows)
    for line, (number, text, point) in zip(out, rows):
        if point is None:
            assert line.startswith(f"ERROR: line {number}: "), (line, text)
        else:
            assert line == f"{text.rstrip()},{api.undulation(*point):.4f}", (line, text)
    bad = sum(point is None for _, _, point in rows)
    assert result.exit_code == (1 if bad else 0)
    if bad:
        assert f"{bad} row(s) could not be processed" in result.stderr


@PROPERTY_SETTINGS
@given(data=csv_input())
def test_jsonl_gives_one_record_per_row_with_the_same_outcome(small_store, api, data):
    result = run(small_store, data, "--format", "jsonl", "--with-error")
    check_no_traceback(result)
    _, rows = expected_lines(data)
    records = [json.loads(line) for line in result.stdout.splitlines()]
    assert [r["line"] for r in records] == [number for number, _, _ in rows]
    for record, (_, _, point) in zip(records, rows):
        if point is None:
            assert record["error"] and record["undulation_m"] is None and record["error_bound_m"] is None
        else:
            assert record["error"] is None
            assert record["undulation_m"] == round(float(api.undulation(*point)), 4)
            assert record["error_bound_m"] > 0
    assert result.exit_code == (1 if any(p is None for _, _, p in rows) else 0)


@PROPERTY_SETTINGS
@given(lat=any_number, lon=any_number)
def test_one_point_is_a_value_or_one_error_line(small_store, api, lat, lon):
    result = CliRunner().invoke(query_main, ["--store", str(small_store.path), repr(lat), repr(lon)])
    check_no_traceback(result)
    point = expected_point(f"{lat!r},{lon!r}")
    if point is None:
        assert result.exit_code == 1 and result.stdout == ""
        assert result.stderr.startswith("ERROR: ") and len(result.stderr.splitlines()) == 1
    else:
        assert result.exit_code == 0 and result.stdout == f"{api.undulation(*point):.4f}\n"
        assert np.isfinite(api.undulation(*point))
