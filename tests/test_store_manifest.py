"""Contained, validated stores (issue 10 item 4): the manifest's schema, tile names and
files, tiles in the wrong place, and property-based mutations of a valid manifest.

Every refusal is a :class:`StoreError` naming the file and the rule; nothing here may
raise another exception, hang, or answer with a value the fitted spline does not give.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import stat
import threading
from pathlib import Path

import netCDF4
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import geoidspline
from geoidspline.api import build_store
from geoidspline.errors import StoreCorruptError, StoreError
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sphere.region import Region
from geoidspline.store.format import (
    MAX_MANIFEST_BYTES,
    integrity_digest,
    manifest_text,
    read_tile_file,
    write_tile_file,
)
from geoidspline.store.reader import TileStore, verify_store
from geoidspline.store.writer import write_store

#: A store of few tiles (tile size 1 on the unit sphere), so that reading every tile is cheap.
TINY_REGION = Region(10.0, 20.0, 30.0, 40.0)
TINY_PARAMS = FitParameters(h0=0.2, max_level=1, tolerance_m=0.01, tile_size=1.0)

#: Points where the tests query: inside the region, near it and far away.
LAT = np.array([20.0, 12.5, 29.0, 31.0, -40.0, 48.85])
LON = np.array([30.0, 21.0, 39.5, 30.0, 100.0, 2.35])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory, synthetic_grid):
    path = tmp_path_factory.mktemp("tiny") / "store"
    result, _ = build_store(synthetic_grid, path, TINY_REGION, TINY_PARAMS)
    return path, result


@pytest.fixture
def copy(tiny, tmp_path):
    return Path(shutil.copytree(tiny[0], tmp_path / "store"))


def _manifest(root: Path) -> dict:
    return json.loads((root / "manifest.json").read_text())


def _hostile_write(root: Path, manifest: dict):
    """An edit that recomputes the manifest's integrity digest (a deliberate one)."""
    (root / "manifest.json").write_bytes(manifest_text(manifest))


def _fix_entry(root: Path, entry: dict):
    """Make a manifest entry's size and sha256 match its file (what a hostile editor does)."""
    data = (root / entry["file"]).read_bytes()
    entry["bytes"] = len(data)
    entry["sha256"] = hashlib.sha256(data).hexdigest()


def _no_hang(fn, seconds=20.0):
    """Run fn in a daemon thread; fail (instead of hanging the suite) if it blocks."""
    box = {}

    def run():
        try:
            box["value"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test
            box["error"] = exc

    thread = threading.Thread(target=run, daemon=True)
    thread.start()
    thread.join(seconds)
    assert not thread.is_alive(), f"{fn} hung"
    if "error" in box:
        raise box["error"]
    return box.get("value")


# -- the schema -----------------------------------------------------------------------


@pytest.mark.parametrize("edit, words", [
    (lambda m: m["spline"].pop("h0"), r"'spline\.h0' is missing"),
    (lambda m: m["spline"].__setitem__("order", "4"), r"'spline\.order' must be an integer, got str"),
    (lambda m: m["tiles"][0].__setitem__("bytes", None), r"'tiles\[0\]\.bytes' must be an integer, got null"),
    (lambda m: m["tiles"][0].__setitem__("tile", [0, 0]), r"'tiles\[0\]\.tile' must have 3\.\.3 items"),
    (lambda m: m.__setitem__("tiles", []), r"'tiles' must have 1\.\."),
    (lambda m: m.__setitem__("region", [10, 20, 30]), r"'region' must have 4\.\.4 items"),
    (lambda m: m["provenance"].__setitem__("notes", [[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[[]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]]),
     r"'provenance\.notes.*nested more than 32 deep"),
    (lambda m: m["tiles"][3].__setitem__("note", json.loads("[" * 40 + "]" * 40)),
     r"'tiles\[3\]\.note.*nested more than 32 deep"),
    (lambda m: m.__setitem__("store_version", 10**40), r"'store_version' must be within 1\.\.2147483648"),
    (lambda m: m["spline"]["levels"][0].__setitem__("h", 0.2000001), r"'spline\.levels\[0\]\.h' must be h0 / 2\*\*level"),
    (lambda m: m["tiles"].append(dict(m["tiles"][0])), r"'tiles\[\d+\]\.tile' repeats tile"),
    (lambda m: m["coverage"]["parts"][0].__setitem__("region", "everywhere"), r"'coverage\.parts\[0\]\.region' must be a list"),
], ids=["missing-key", "wrong-type", "null", "short-tile", "empty-tile-list", "short-region", "deep-nesting",
        "deep-nesting-in-a-tile", "huge-number", "h-not-h0-over-2-to-level", "duplicate-tile", "coverage-region"])
def test_schema_names_the_key_and_the_rule(copy, edit, words):
    m = _manifest(copy)
    edit(m)
    _hostile_write(copy, m)
    with pytest.raises(StoreCorruptError, match=words) as err:
        geoidspline.open_store(copy)
    assert str(copy / "manifest.json") in str(err.value)
    with pytest.raises(StoreCorruptError, match=words):
        verify_store(copy)  # an empty tile list is never "every tile matches"


def test_an_edit_without_its_digest_is_found(copy):
    m = _manifest(copy)
    m["accuracy"]["max_error_m"] = 0.001  # plausible, harmless-looking, and not what was measured
    (copy / "manifest.json").write_text(json.dumps(m))
    with pytest.raises(StoreCorruptError, match="altered after it was written"):
        geoidspline.open_store(copy)


@pytest.mark.parametrize("text, words", [
    (b"[" * 100_000, "not valid JSON"),
    (b'{"a": ' + b"1" * 5000 + b"}", "not valid JSON"),
    (b'{"format": "geoidspline-tile-store", "format_version": NaN}', "not valid JSON"),
    (b'{"format": "geoidspline-tile-store", "x": 1e999}', "not valid JSON"),
    (b"\xff\xfe\x00", "not UTF-8"),
], ids=["deep-brackets", "5000-digit-integer", "NaN", "1e999", "binary"])
def test_unparseable_manifests(copy, text, words):
    (copy / "manifest.json").write_bytes(text)
    with pytest.raises(StoreCorruptError, match=words):
        geoidspline.open_store(copy)


def test_manifest_that_is_not_a_regular_file_or_too_big(copy, tmp_path):
    manifest = copy / "manifest.json"
    manifest.unlink()
    os.mkfifo(manifest)
    with pytest.raises(StoreCorruptError, match="a FIFO"):
        _no_hang(lambda: geoidspline.open_store(copy))
    manifest.unlink()
    other = tmp_path / "other.json"
    other.write_text("{}")
    manifest.symlink_to(other)
    with pytest.raises(StoreCorruptError, match="symbolic link"):
        geoidspline.open_store(copy)
    manifest.unlink()
    with open(manifest, "wb") as fh:  # sparse: costs no disk
        fh.truncate(MAX_MANIFEST_BYTES + 1)
    with pytest.raises(StoreCorruptError, match="more than"):
        geoidspline.open_store(copy)


# -- containment: names, links, special files -----------------------------------------


@pytest.mark.parametrize("name", [
    "../../../../etc/passwd", "/etc/passwd", "tiles/../manifest.json", "tiles/../../x/t+0000+0000+0000.v1.nc",
    "tiles/sub/t+0000+0000+0000.v1.nc", "tiles/t+0000+0000+0000.v1.nc\x00.txt", "tiles/", "tiles/.", "manifest.json",
])
def test_tile_names_must_be_plain_names_inside_tiles(copy, name):
    m = _manifest(copy)
    m["tiles"][0]["file"] = name
    _hostile_write(copy, m)
    with pytest.raises(StoreCorruptError, match=r"'tiles\[0\]\.file' must be a plain tile file name"):
        geoidspline.open_store(copy)
    with pytest.raises(StoreCorruptError, match="plain tile file name"):
        verify_store(copy)


def _special(kind, path: Path, tiny_root: Path):
    path.unlink()
    if kind == "symlink-to-passwd":
        path.symlink_to("/etc/passwd")
    elif kind == "symlink-to-own-tile":
        other = sorted((tiny_root / "tiles").iterdir())[-1]
        path.symlink_to(other)
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "directory":
        path.mkdir()
    elif kind == "device":
        try:
            os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 5))  # /dev/zero's numbers
        except PermissionError:
            pytest.skip("creating a device node needs root")


@pytest.mark.parametrize("kind, words", [
    ("symlink-to-passwd", "symbolic link"), ("symlink-to-own-tile", "symbolic link"), ("fifo", "a FIFO"),
    ("directory", "a directory"), ("device", "a device"),
])
def test_tile_files_must_be_regular_files(tiny, copy, kind, words):
    entry = _manifest(copy)["tiles"][0]
    _special(kind, copy / entry["file"], tiny[0])
    for lazy in (True, False):
        with pytest.raises(StoreCorruptError, match=words) as err:
            _no_hang(lambda lazy=lazy: TileStore.open(copy, lazy=lazy))
        assert Path(entry["file"]).name in str(err.value)
    problems = _no_hang(lambda: verify_store(copy))
    assert len(problems) == 1 and words in problems[0] and Path(entry["file"]).name in problems[0]


def test_a_symlinked_tile_directory_is_refused(copy, tmp_path):
    shutil.move(copy / "tiles", tmp_path / "elsewhere")
    (copy / "tiles").symlink_to(tmp_path / "elsewhere")
    with pytest.raises(StoreCorruptError, match="not a directory of the store"):
        geoidspline.open_store(copy)


# -- tiles in the wrong place -----------------------------------------------------------


def test_a_tile_copied_from_another_store_is_refused(tiny, copy, tmp_path):
    """Same fit, same tile names, another store: even with the manifest's sha256 edited."""
    other = tmp_path / "other"
    write_store(other, tiny[1], _provenance(tiny[0]))
    m = _manifest(copy)
    entry = m["tiles"][0]
    shutil.copyfile(other / entry["file"], copy / entry["file"])
    _fix_entry(copy, entry)
    _hostile_write(copy, m)
    with pytest.raises(StoreCorruptError, match="belongs to another store") as err:
        TileStore.open(copy, lazy=False)
    assert Path(entry["file"]).name in str(err.value)
    problems = verify_store(copy)
    assert len(problems) == 1 and "another store" in problems[0]


def _provenance(root):
    from geoidspline.sources.base import Provenance

    prov = _manifest(root)["provenance"]
    return Provenance(**{**prov, "notes": tuple(prov["notes"])})


def test_two_swapped_tiles_are_refused(copy):
    m = _manifest(copy)
    a, b = m["tiles"][0], m["tiles"][1]
    data_a, data_b = (copy / a["file"]).read_bytes(), (copy / b["file"]).read_bytes()
    (copy / a["file"]).write_bytes(data_b)
    (copy / b["file"]).write_bytes(data_a)
    # before the manifest is edited, the digests catch it
    assert len(verify_store(copy)) == 2
    a["coefficients"], b["coefficients"] = b["coefficients"], a["coefficients"]
    a["levels"], b["levels"] = b["levels"], a["levels"]
    _fix_entry(copy, a)
    _fix_entry(copy, b)
    _hostile_write(copy, m)
    problems = verify_store(copy)
    assert len(problems) == 2 and all("not this tile's file" in p for p in problems)
    with pytest.raises(StoreCorruptError, match="not this tile's file"):
        TileStore.open(copy, lazy=False)


def test_a_tile_whose_coefficients_belong_elsewhere_is_refused(copy):
    """A file that says it is tile A but holds tile B's coefficients: the support
    centres give it away even when every attribute and digest was made to match."""
    m = _manifest(copy)
    a, b = m["tiles"][0], m["tiles"][1]
    idx, lvl, val = read_tile_file(copy / b["file"], b, (copy / b["file"]).read_bytes(), m)
    attrs = {"store_id": m["store_id"], "value_step_m": m["spline"]["value_step_m"],
             **{k: m["spline"][k] for k in ("order", "h0", "tile_size")}}
    old_levels = read_tile_file(copy / a["file"], a, (copy / a["file"]).read_bytes(), m)[1]
    (copy / a["file"]).unlink()
    write_tile_file(copy / a["file"], a["tile"], lvl.astype(np.int64), idx.astype(np.int64), val, attrs)
    # the editor makes every count add up
    for level in m["spline"]["levels"]:
        level["coefficients"] += int((lvl == level["level"]).sum() - (old_levels == level["level"]).sum())
    m["spline"]["coefficients"] += int(val.size) - a["coefficients"]
    a["coefficients"] = int(val.size)
    a["levels"] = sorted(set(lvl.tolist()))
    _fix_entry(copy, a)
    _hostile_write(copy, m)
    with pytest.raises(StoreCorruptError, match="support centre lies outside the tile's cube"):
        TileStore.open(copy, lazy=False)
    assert any("support centre" in p for p in verify_store(copy))


def test_an_intact_store_verifies_and_a_format_1_store_keeps_opening(tiny, copy):
    assert verify_store(copy) == []
    want = geoidspline.open_store(copy).undulation(LAT, LON)
    _downgrade_to_format_1(copy)
    store = geoidspline.open_store(copy)
    assert store.manifest["format_version"] == 1 and verify_store(copy) == []
    np.testing.assert_array_equal(store.undulation(LAT, LON), want)
    assert list(store.covers(LAT, LON)) == list(TINY_REGION.contains(LAT, LON))  # its region


def _downgrade_to_format_1(root: Path):
    """What a store written before coverage, store ids, digests and format-2 tiles looks like."""
    m = _manifest(root)
    for entry in m["tiles"]:
        idx, lvl, val = read_tile_file(root / entry["file"], entry, (root / entry["file"]).read_bytes(), m)
        (root / entry["file"]).unlink()
        entry["file"] = entry["file"].replace(".gst", ".nc")
        write_tile_file(root / entry["file"], entry["tile"], lvl, idx, val,
                        {k: m["spline"][k] for k in ("order", "h0", "tile_size")}
                        | {"store_id": m["store_id"], "store_version": m["store_version"]}, format_version=1)
        with netCDF4.Dataset(root / entry["file"], "a") as ds:
            for name in ("store_id", "store_version", "levels", "coefficients", "support_centre_min",
                         "support_centre_max"):
                ds.delncattr(name)
            ds.setncattr("format_version", 1)
        _fix_entry(root, entry)
    for key in ("coverage", "store_id", "integrity"):
        m.pop(key)
    for key in ("value_step_m", "value_error_bound_m", "value_error_rule"):
        m["spline"].pop(key)
    m["format_version"] = 1
    (root / "manifest.json").write_text(json.dumps(m, indent=1))
    (root / ".geoidspline-store").unlink()


# -- property-based: random mutations of a valid manifest -----------------------------

_PATH_TRICKS = ["../../../../etc/passwd", "/etc/passwd", "tiles/../manifest.json", "tiles/t+0000+0000+0000.v1.nc\x00",
                "tiles/", "", "tiles/t+9999+9999+9999.v1.nc", "/dev/zero", "tiles/../../../dev/zero"]
_ODD_VALUES = [None, True, False, "", "x", -1, 0, 1, 2, 2**31, 2**63, 10**30, -(10**30), 1e308, -1e308, 0.5, 1e-300,
               [], {}, [0, 0, 0], {"a": 1}, "a" * 100_000] + _PATH_TRICKS


def _paths(value, prefix=()):
    """Every (path, value) in a JSON document, containers included."""
    yield prefix, value
    if isinstance(value, dict):
        for k, v in value.items():
            yield from _paths(v, prefix + (k,))
    elif isinstance(value, list):
        for i, v in enumerate(value):
            yield from _paths(v, prefix + (i,))


def _get(doc, path):
    for p in path:
        doc = doc[p]
    return doc


@st.composite
def mutations(draw, manifest):
    """(description, mutated manifest): drop a key, change a type or value, nest deeply,
    put a path trick or a huge number somewhere, duplicate or drop a list item."""
    doc = json.loads(json.dumps(manifest))
    paths = [p for p, _ in _paths(doc) if p]
    path = draw(st.sampled_from(paths))
    parent, key = _get(doc, path[:-1]), path[-1]
    kind = draw(st.sampled_from(["drop", "odd", "nest", "nudge", "list"]))
    if kind == "drop":
        del parent[key]
    elif kind == "odd":
        parent[key] = draw(st.sampled_from(_ODD_VALUES))
    elif kind == "nest":
        depth = draw(st.sampled_from([33, 200, 5000]))
        value = parent[key]
        for _ in range(depth):
            value = [value]
        parent[key] = value
    elif kind == "nudge":
        value = parent[key]
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            parent[key] = draw(st.sampled_from(_ODD_VALUES))
        elif isinstance(value, int):
            parent[key] = value + draw(st.sampled_from([-1, 1, 2**32]))
        else:
            parent[key] = value * (1 + draw(st.sampled_from([1e-12, -1e-9, 1e-3])))
    else:
        value = parent[key]
        if isinstance(value, list) and value:
            op = draw(st.sampled_from(["dup", "pop", "swap"]))
            if op == "dup":
                value.append(json.loads(json.dumps(value[0])))
            elif op == "pop":
                value.pop(draw(st.integers(0, len(value) - 1)))
            elif len(value) > 1:
                value[0], value[-1] = value[-1], value[0]
        else:
            parent[key] = [value]
    return f"{kind} at {'/'.join(map(str, path))}", path, doc


def _dump(doc, hostile: bool) -> bytes:
    """The document as manifest bytes (a recomputed digest when ``hostile``); deep
    nesting needs a higher recursion limit to be written at all."""
    import sys

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 20_000))
    try:
        if hostile:
            doc = {k: v for k, v in doc.items() if k != "integrity"}
            doc["integrity"] = {"sha256": integrity_digest(doc)}
        return json.dumps(doc).encode()  # compact: the C encoder, fast at any depth
    finally:
        sys.setrecursionlimit(limit)


def _same_document(text: bytes, manifest: dict) -> bool:
    try:
        return json.loads(text) == manifest
    except (ValueError, RecursionError):
        return False


def _exercise(root: Path, spline_values, path):
    """Open, query, cover, summarise and verify: a StoreError naming the problem, or
    values that are the fitted spline's own (never another exception, never a number
    the spline does not give)."""
    try:
        store = geoidspline.open_store(root)
        values = store.undulation(LAT, LON)
        covered = store.covers(LAT, LON)
        store.coverage_reason(LAT, LON)
        store.info()
        repr(store)
        verify_store(root)
    except StoreError as exc:
        message = str(exc)
        assert str(root) in message, message
        assert "manifest" in message or "tile" in message, message
        return "refused"
    numbers = np.isfinite(values)
    np.testing.assert_array_equal(values[numbers], spline_values[numbers])
    assert np.array_equal(numbers, covered)
    if path[0] not in ("coverage", "region"):  # a deliberate edit of the coverage is the store's claim
        assert list(covered) == list(TINY_REGION.contains(LAT, LON))
    return "answered"


@pytest.fixture(scope="module")
def mutation_target(tiny, tmp_path_factory):
    root = Path(shutil.copytree(tiny[0], tmp_path_factory.mktemp("mutated") / "store"))
    # the values the store gives: the fit's coefficients quantised (format 2)
    return root, _manifest(root), geoidspline.open_store(root).spline.full.undulation(LAT, LON)


#: Examples per property test (counted in benchmarks/README.md "Trust").
MUTATION_EXAMPLES = 150


@settings(max_examples=MUTATION_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_mutated_manifests_are_refused_or_harmless(mutation_target, data):
    """A mutation written as it is (its integrity digest now stale)."""
    root, manifest, spline_values = mutation_target
    what, path, doc = data.draw(mutations(manifest))
    text = _dump(doc, hostile=False)
    (root / "manifest.json").write_bytes(text)
    outcome = _exercise(root, spline_values, path)
    if path[0] != "integrity" and not _same_document(text, manifest):
        assert outcome == "refused", what


@settings(max_examples=MUTATION_EXAMPLES, deadline=None, suppress_health_check=list(HealthCheck))
@given(data=st.data())
def test_deliberately_mutated_manifests_never_give_a_wrong_value(mutation_target, data):
    """A mutation whose integrity digest was recomputed: the schema, the containment
    rules and the tiles' own records must still refuse it, or it changes no value."""
    root, manifest, spline_values = mutation_target
    _, path, doc = data.draw(mutations(manifest))
    (root / "manifest.json").write_bytes(_dump(doc, hostile=True))
    _exercise(root, spline_values, path)


@settings(max_examples=60, deadline=None, suppress_health_check=list(HealthCheck))
@given(cut=st.integers(0, 10**6), junk=st.binary(min_size=0, max_size=16))
def test_torn_or_garbled_manifest_bytes_are_refused(mutation_target, cut, junk):
    root, manifest, spline_values = mutation_target
    text = manifest_text(manifest)
    cut = cut % len(text)
    garbled = text[:cut] + junk + text[cut + len(junk):]
    (root / "manifest.json").write_bytes(garbled)
    outcome = _exercise(root, spline_values, ("bytes",))
    if not _same_document(garbled, json.loads(text)):  # whitespace for whitespace is the same manifest
        assert outcome == "refused"
