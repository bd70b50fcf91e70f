"""The tile store: round trip, manifest content, info(), atomicity and corruption checks."""

from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

import numpy as np
import pytest
from conftest import stored_spline

import geoidspline
from geoidspline.api import build_store
from geoidspline.errors import GeoidSplineError, StoreCorruptError, StoreError
from geoidspline.fitting.check_points import check_points
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sphere.coordinates import directions
from geoidspline.store.codec import decode_tile
from geoidspline.store.format import FORMAT_NAME, FORMAT_VERSION, manifest_text, read_tile_file
from geoidspline.store.reader import TileStore
from geoidspline.store.writer import StoreLock, write_store


def _snapshot(root: Path) -> dict:
    """Every file under root (relative path -> bytes)."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _manifest(root: Path) -> dict:
    return json.loads((root / "manifest.json").read_text())


def _rewrite_manifest(root: Path, manifest: dict):
    """Write an edited manifest with a matching integrity digest (a deliberate edit)."""
    (root / "manifest.json").write_bytes(manifest_text(manifest))


def _random_points(region, n, seed):
    rng = np.random.default_rng(seed)
    lat = rng.uniform(region.south, region.north, n)
    lon = rng.uniform(region.west, region.east, n)
    return lat, lon


def _largest_tile(root: Path) -> dict:
    return max(_manifest(root)["tiles"], key=lambda e: e["coefficients"])


# -- round trip ----------------------------------------------------------------------


def test_round_trip_values_are_bitwise_equal(small_store):
    store = geoidspline.open_store(small_store.path)
    # inside the region, around it, and anywhere on the sphere
    lat, lon = _random_points(small_store.region, 3000, seed=1)
    rng = np.random.default_rng(2)
    lat = np.concatenate([lat, rng.uniform(0, 40, 500), rng.uniform(-90, 90, 500)])
    lon = np.concatenate([lon, rng.uniform(10, 50, 500), rng.uniform(-180, 180, 500)])
    got = store.undulation(lat, lon)
    want = small_store.stored.undulation(lat, lon)  # the fit, coefficients quantised
    assert got.dtype == np.float64
    inside = small_store.region.contains(lat, lon)
    assert inside[:3000].all() and not inside[3000:].all()
    # the fitted values where the store has data, NaN elsewhere (never a number there)
    assert np.array_equal(got[inside], want[inside])
    assert np.all(np.isnan(got[~inside]))
    bound = _manifest(small_store.path)["spline"]["value_error_bound_m"]
    assert np.abs(got[inside] - small_store.result.spline.undulation(lat, lon)[inside]).max() <= bound
    assert np.all(np.isfinite(got[:3000]))
    # the spline itself is stored everywhere, bit for bit
    assert np.array_equal(store.spline.full.undulation(lat, lon), want)


def test_round_trip_keeps_every_coefficient(small_store):
    store = geoidspline.open_store(small_store.path)
    fitted = small_store.stored.levels
    opened = store.spline.levels
    assert [lv.level for lv in opened] == [lv.level for lv in fitted]
    assert [lv.level for lv in opened] == list(range(len(opened)))
    for a, b in zip(opened, fitted):
        assert a.h == b.h and a.order == b.order
        assert np.array_equal(a.keys, b.keys)
        assert np.array_equal(a.coefficients, b.coefficients)


# -- manifest ------------------------------------------------------------------------


def test_manifest_header_provenance_and_spline(small_store):
    m = _manifest(small_store.path)
    assert m["format"] == FORMAT_NAME == "geoidspline-tile-store"
    assert m["format_version"] == FORMAT_VERSION == 4
    assert m["store_version"] == 1

    prov = m["provenance"]
    assert prov == small_store.grid.provenance.as_dict()
    assert prov["source"] == "synthetic.gtx"
    assert prov["kind"] == "grid"
    assert prov["sha256"] == hashlib.sha256(small_store.gtx.read_bytes()).hexdigest()
    assert m["history"][-1]["sha256"] == prov["sha256"]

    params = small_store.params
    assert m["region"] == [10.0, 20.0, 30.0, 40.0]
    assert m["spline"]["order"] == 4
    assert m["spline"]["h0"] == 0.2
    assert m["spline"]["tile_size"] == params.tile_size
    levels = m["spline"]["levels"]
    fitted = small_store.result.spline.levels
    assert [lv["level"] for lv in levels] == [lv.level for lv in fitted]
    assert [lv["h"] for lv in levels] == [0.2 / 2**lv["level"] for lv in levels]
    assert [lv["coefficients"] for lv in levels] == [len(lv) for lv in fitted]
    assert m["spline"]["coefficients"] == sum(lv["coefficients"] for lv in levels)
    assert m["fit"]["tolerance_m"] == params.tolerance_m
    assert m["fit"]["parameters"]["h0"] == 0.2
    assert m["fit"]["parameters"]["max_level"] == params.max_level
    assert m["fit"]["converged"] is small_store.result.converged
    assert m["accuracy"]["units"] == "m"


def test_manifest_tiles_describe_their_files(small_store):
    root = small_store.path
    m = _manifest(root)
    entries = m["tiles"]
    tile_size, h0, order = m["spline"]["tile_size"], m["spline"]["h0"], m["spline"]["order"]
    on_disk = sorted(p.name for p in (root / "tiles").iterdir())
    assert on_disk == sorted(Path(e["file"]).name for e in entries)
    assert len({tuple(e["tile"]) for e in entries}) == len(entries)
    per_level = {}
    for e in entries:
        path = root / e["file"]
        data = path.read_bytes()
        assert e["bytes"] == len(data)
        assert e["sha256"] == hashlib.sha256(data).hexdigest()
        header, _ = decode_tile(data)
        assert header["tile"] == e["tile"] and header["value_units"] == "m"
        assert header["value_step_m"] == m["spline"]["value_step_m"]
        index, level, values = read_tile_file(path, e, data, m)
        assert values.shape == (e["coefficients"],) and e["coefficients"] > 0
        assert index.shape == (e["coefficients"], 3)
        assert sorted(set(level.tolist())) == e["levels"]
        # every coefficient's support centre lies in this tile's cube
        h = h0 / 2.0 ** level[:, None]
        centre_tile = np.floor((index + order / 2.0) * h / tile_size).astype(np.int64)
        assert np.all(centre_tile == np.array(e["tile"]))
        for lv in level:
            per_level[int(lv)] = per_level.get(int(lv), 0) + 1
    assert per_level == {lv["level"]: lv["coefficients"] for lv in m["spline"]["levels"]}


def test_manifest_per_tile_check_point_errors(small_store):
    """Per-tile and total max/RMS at the check points, recomputed from the opened store."""
    m = _manifest(small_store.path)
    store = geoidspline.open_store(small_store.path)
    check = check_points(small_store.grid, small_store.region)
    # the check points of a grid are its cell centres inside the region: 10 x 10 here
    assert check.latitude.size == 100
    assert np.allclose(np.unique(check.latitude), np.arange(11.0, 30.0, 2.0))
    errors = check.truth - store.undulation(check.latitude, check.longitude)
    tile_size = m["spline"]["tile_size"]
    tiles = np.floor(directions(check.latitude, check.longitude) / tile_size).astype(np.int64)
    counted = 0
    for e in m["tiles"]:
        mine = errors[np.all(tiles == np.array(e["tile"]), axis=1)]
        assert e["check_points"] == mine.size
        counted += mine.size
        if mine.size:
            assert e["max_error_m"] == pytest.approx(np.abs(mine).max(), rel=1e-12)
            assert e["rms_error_m"] == pytest.approx(np.sqrt(np.mean(mine**2)), rel=1e-12)
        else:
            assert e["max_error_m"] is None and e["rms_error_m"] is None
    assert counted == errors.size  # no check point falls outside every tile
    acc = m["accuracy"]
    assert acc["check_points"] == errors.size
    assert acc["max_error_m"] == pytest.approx(np.abs(errors).max(), rel=1e-12)
    assert acc["rms_error_m"] == pytest.approx(np.sqrt(np.mean(errors**2)), rel=1e-12)
    assert 0 < acc["rms_error_m"] <= acc["max_error_m"]


def test_manifest_node_errors_respect_the_tolerance(small_store):
    m = _manifest(small_store.path)
    store = geoidspline.open_store(small_store.path)
    sample = small_store.grid.nodes(small_store.region)
    lat, lon = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    # node errors are the stored spline's, within value_error_bound_m of the fit's
    fitted = sample.undulation - small_store.result.spline.undulation(lat, lon)
    errors = sample.undulation - store.undulation(lat, lon)
    assert np.abs(errors - fitted).max() <= m["spline"]["value_error_bound_m"]
    acc = m["accuracy"]
    assert acc["nodes"] == errors.size == 11 * 11
    assert acc["node_max_error_m"] == pytest.approx(np.abs(errors).max(), rel=1e-9, abs=1e-12)
    assert acc["node_rms_error_m"] == pytest.approx(np.sqrt(np.mean(errors**2)), rel=1e-9)
    assert acc["fit_node_max_error_m"] == pytest.approx(np.abs(fitted).max(), rel=1e-9, abs=1e-12)
    # converged means every node of the region is within the tolerance
    assert m["fit"]["converged"] == (acc["node_max_error_m"] <= m["fit"]["tolerance_m"])
    assert sum(e["nodes"] for e in m["tiles"]) == errors.size


# -- info() --------------------------------------------------------------------------


def test_info_summary_and_bytes_on_disk(small_store):
    root = small_store.path
    info = geoidspline.open_store(root).info()
    assert info == small_store.info
    for key in ("coefficients", "levels", "tiles", "max_error_m", "rms_error_m", "bytes"):
        assert key in info
    assert info["levels"] and all(set(lv) >= {"h", "coefficients"} for lv in info["levels"])
    assert [lv["h"] for lv in info["levels"]] == [lv.h for lv in small_store.result.spline.levels]
    assert [lv["coefficients"] for lv in info["levels"]] == [len(lv) for lv in small_store.result.spline.levels]
    assert info["coefficients"] == sum(lv["coefficients"] for lv in info["levels"])
    assert info["coefficients"] == small_store.result.spline.coefficient_count
    assert info["tiles"] == len(list((root / "tiles").iterdir()))
    real = sum(p.stat().st_size for p in root.rglob("*") if p.is_file())
    assert info["bytes"] == real
    m = _manifest(root)
    assert info["max_error_m"] == m["accuracy"]["max_error_m"]
    assert info["rms_error_m"] == m["accuracy"]["rms_error_m"]
    assert info["format_version"] == 4 and info["order"] == 4 and info["h0"] == 0.2


def test_no_temporary_files_are_left(small_store):
    names = [p.name for p in small_store.path.rglob("*")]
    assert not [n for n in names if n.endswith(".tmp")]


# -- writing: refusal, overwrite, half-written directories ---------------------------


def test_existing_store_is_refused_and_left_unchanged(small_store, store_copy):
    before = _snapshot(store_copy)
    with pytest.raises(StoreError, match="already exists"):
        write_store(store_copy, small_store.result, small_store.grid.provenance)
    assert _snapshot(store_copy) == before
    assert geoidspline.open_store(store_copy).info()["store_version"] == 1


def test_overwrite_replaces_store_and_removes_old_tiles(small_store, store_copy):
    old = _manifest(store_copy)
    old_files = {store_copy / e["file"] for e in old["tiles"]}
    params = FitParameters(h0=0.2, max_level=0, tolerance_m=1.0)  # one level only
    result, info = build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    new = _manifest(store_copy)
    assert new["store_version"] == 2
    assert new["created"] == old["created"]
    assert [h["store_version"] for h in new["history"]] == [1, 2]
    assert [lv["level"] for lv in new["spline"]["levels"]] == [0]
    # the previous version's files stay one version longer, for readers that opened it
    assert all(f.exists() for f in old_files)
    store = geoidspline.open_store(store_copy)
    lat, lon = _random_points(small_store.region, 500, seed=3)
    assert np.array_equal(store.undulation(lat, lon), stored_spline(result.spline, store_copy).undulation(lat, lon))
    assert info["bytes"] == sum((store_copy / name).stat().st_size for name in (
        "manifest.json", ".geoidspline-store", ".lock")) + sum(
        (store_copy / e["file"]).stat().st_size for e in new["tiles"])
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    newer = _manifest(store_copy)
    assert not [f for f in old_files if f.exists()]
    on_disk = sorted(p.name for p in (store_copy / "tiles").iterdir())
    assert on_disk == sorted({Path(e["file"]).name for e in new["tiles"] + newer["tiles"]})


class SimulatedCrash(Exception):
    """Not an I/O fault: the writer leaves its files as a crash would."""


def _crash_after(monkeypatch, tiles_written):
    """Make write_store fail (as a crash would) after writing ``tiles_written`` tile files."""
    import geoidspline.store.writer as store_module

    real = store_module.write_tile_file
    calls = []

    def failing(*args, **kwargs):
        if len(calls) == tiles_written:
            raise SimulatedCrash("simulated crash")
        calls.append(args[0])
        return real(*args, **kwargs)

    monkeypatch.setattr(store_module, "write_tile_file", failing)
    return calls


def test_crash_during_overwrite_keeps_the_old_store(small_store, store_copy, monkeypatch):
    before = _snapshot(store_copy)
    written = _crash_after(monkeypatch, 5)
    params = FitParameters(h0=0.2, max_level=0, tolerance_m=1.0)
    with pytest.raises(SimulatedCrash, match="simulated crash"):
        build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    monkeypatch.undo()
    assert len(written) == 5 and all(p.exists() for p in written)  # new files, unnamed by the manifest
    after = _snapshot(store_copy)
    assert {k: v for k, v in after.items() if k in before} == before
    store = geoidspline.open_store(store_copy)
    lat, lon = _random_points(small_store.region, 300, seed=5)
    assert np.array_equal(store.undulation(lat, lon), small_store.stored.undulation(lat, lon))
    # the next successful write removes the orphans (keeping the previous version's files)
    previous = {Path(e["file"]).name for e in _manifest(store_copy)["tiles"]}
    build_store(small_store.grid, store_copy, small_store.region, params, overwrite=True)
    on_disk = sorted(p.name for p in (store_copy / "tiles").iterdir())
    assert on_disk == sorted({Path(e["file"]).name for e in _manifest(store_copy)["tiles"]} | previous)
    with StoreLock(store_copy):  # the lock file stays; nobody holds it
        pass


def test_crash_during_first_write_leaves_no_store(small_store, tmp_path, monkeypatch):
    target = tmp_path / "new"
    _crash_after(monkeypatch, 3)
    with pytest.raises(SimulatedCrash, match="simulated crash"):
        write_store(target, small_store.result, small_store.grid.provenance)
    monkeypatch.undo()
    assert len(list((target / "tiles").iterdir())) == 3
    assert not (target / "manifest.json").exists()
    with pytest.raises(StoreError, match="not a geoidspline store"):
        geoidspline.open_store(target)
    # its leftovers are recognised: refused without overwrite, cleared with it
    with pytest.raises(StoreError, match="leftovers.*overwrite"):
        write_store(target, small_store.result, small_store.grid.provenance)
    write_store(target, small_store.result, small_store.grid.provenance, overwrite=True)
    assert geoidspline.open_store(target).manifest["store_version"] == 1
    assert sorted(p.name for p in (target / "tiles").iterdir()) == sorted(
        Path(e["file"]).name for e in _manifest(target)["tiles"])


def test_directory_without_manifest_is_not_a_store(small_store, tmp_path):
    # a first write that crashed: tile files but no manifest
    half = tmp_path / "half"
    (half / "tiles").mkdir(parents=True)
    tile = _largest_tile(small_store.path)
    (half / tile["file"]).write_bytes((small_store.path / tile["file"]).read_bytes())
    with pytest.raises(StoreError, match=r"not a geoidspline store.*(did not finish|half)") as err:
        geoidspline.open_store(half)
    assert "manifest.json" in str(err.value)
    assert str(half) in str(err.value)


def test_half_written_directory_needs_overwrite_and_is_cleaned(small_store, tmp_path):
    half = tmp_path / "half"
    (half / "tiles").mkdir(parents=True)
    stray = half / "tiles" / ".t+0000+0000+0000.v1.nc.abc123.tmp"
    stray.write_bytes(b"partial tile")
    old_tile = half / "tiles" / "t+0002+0002-0002.v1.nc"
    old_tile.write_bytes(b"an old tile")
    with pytest.raises(StoreError, match="leftovers"):
        write_store(half, small_store.result, small_store.grid.provenance)
    assert stray.exists() and old_tile.exists()
    write_store(half, small_store.result, small_store.grid.provenance, overwrite=True)
    assert not stray.exists() and not old_tile.exists()
    store = geoidspline.open_store(half)
    lat, lon = _random_points(small_store.region, 200, seed=4)
    assert np.array_equal(store.undulation(lat, lon), small_store.stored.undulation(lat, lon))


def test_other_directories_and_files_are_refused(small_store, tmp_path):
    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("keep me")
    with pytest.raises(StoreError, match="not empty"):
        write_store(busy, small_store.result, small_store.grid.provenance)
    assert sorted(p.name for p in busy.iterdir()) == ["notes.txt"]
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    with pytest.raises(StoreError, match="not a directory"):
        write_store(a_file, small_store.result, small_store.grid.provenance)
    assert a_file.read_text() == "x"


def test_missing_store_directory(tmp_path):
    with pytest.raises(StoreError, match="no such store"):
        geoidspline.open_store(tmp_path / "nowhere")


# -- corruption ----------------------------------------------------------------------


def _truncate(path: Path):
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


def _alter_byte(path: Path):
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))


def _delete(path: Path):
    path.unlink()


def _point_needing(store, tile, region, seed=5):
    """A (lat, lon) in region whose query reads ``tile``."""
    lat, lon = _random_points(region, 2000, seed)
    for la, lo in zip(lat, lon):
        if tuple(tile) in store.spline.tiles_at(directions(la, lo)):
            return la, lo
    raise AssertionError(f"no point of {region} needs tile {tile}")


@pytest.mark.parametrize(
    "damage, words",
    [(_truncate, "bytes"), (_alter_byte, "sha256"), (_delete, "missing")],
    ids=["truncated", "altered-byte", "deleted"],
)
def test_damaged_tile_is_refused_naming_the_file(small_store, store_copy, damage, words):
    tile = _largest_tile(store_copy)
    path = store_copy / tile["file"]
    size = path.stat().st_size
    damage(path)
    if damage is _alter_byte:
        assert path.stat().st_size == size
    # read at once: opening fails
    with pytest.raises(StoreCorruptError, match=words) as err:
        TileStore.open(store_copy, lazy=False)
    assert Path(tile["file"]).name in str(err.value)
    assert isinstance(err.value, GeoidSplineError)
    if damage is not _alter_byte:
        # a missing or resized file is found by opening, even lazily
        with pytest.raises(StoreCorruptError, match=words) as err:
            geoidspline.open_store(store_copy)
        assert Path(tile["file"]).name in str(err.value)
        return
    # lazily, an altered tile is refused by every query that reads it, never used
    store = geoidspline.open_store(store_copy)
    lat, lon = _point_needing(store, tile["tile"], small_store.region)
    for _ in range(2):
        with pytest.raises(StoreCorruptError, match="sha256") as err:
            store.undulation(lat, lon)
        assert Path(tile["file"]).name in str(err.value)
    with pytest.raises(StoreCorruptError, match="sha256"):
        store.undulation(*_random_points(small_store.region, 5000, seed=6))  # a batch reads every tile


def test_coefficient_count_disagreeing_with_manifest_is_refused(small_store, store_copy):
    m = _manifest(store_copy)
    entry = max(m["tiles"], key=lambda e: e["coefficients"])
    entry["coefficients"] += 1
    (store_copy / "manifest.json").write_text(json.dumps(m))
    # an edit that leaves the counts inconsistent is refused by the schema
    with pytest.raises(StoreCorruptError, match="'tiles' hold .* coefficients"):
        geoidspline.open_store(store_copy)
    # a consistent deliberate edit (counts and digest) is refused by the tile itself
    m["spline"]["coefficients"] += 1
    m["spline"]["levels"][entry["levels"][0]]["coefficients"] += 1
    _rewrite_manifest(store_copy, m)
    with pytest.raises(StoreCorruptError, match="coefficients") as err:
        TileStore.open(store_copy, lazy=False)
    assert Path(entry["file"]).name in str(err.value)
    store = geoidspline.open_store(store_copy)
    with pytest.raises(StoreCorruptError, match="coefficients") as err:
        store.undulation(*_point_needing(store, entry["tile"], small_store.region))
    assert Path(entry["file"]).name in str(err.value)


def test_invalid_json_manifest_is_corrupt(store_copy):
    manifest = store_copy / "manifest.json"
    text = manifest.read_text()
    manifest.write_text(text[: len(text) // 2])  # a torn write
    with pytest.raises(StoreCorruptError, match="manifest.json.*not valid JSON"):
        geoidspline.open_store(store_copy)
    manifest.write_text("{not json")
    with pytest.raises(StoreCorruptError, match="manifest.json"):
        geoidspline.open_store(store_copy)


def test_binary_garbage_manifest_is_corrupt(store_copy):
    (store_copy / "manifest.json").write_bytes(b"\xff\xfe\x00\x01garbage\x80")
    with pytest.raises(StoreCorruptError, match="manifest.json"):
        geoidspline.open_store(store_copy)


@pytest.mark.parametrize(
    "content",
    ["[1, 2]", '"a string"', json.dumps({"format": FORMAT_NAME, "format_version": 1})],
    ids=["list", "string", "missing-keys"],
)
def test_manifest_of_the_wrong_shape_is_a_store_error(store_copy, content):
    (store_copy / "manifest.json").write_text(content)
    with pytest.raises(StoreError, match="manifest.json"):
        geoidspline.open_store(store_copy)


def test_foreign_or_newer_manifest_is_refused(store_copy):
    manifest = store_copy / "manifest.json"
    m = _manifest(store_copy)
    manifest.write_text(json.dumps({**m, "format_version": FORMAT_VERSION + 1}))
    with pytest.raises(StoreError, match="newer"):
        geoidspline.open_store(store_copy)
    manifest.write_text(json.dumps({**m, "format": "something-else"}))
    with pytest.raises(StoreError, match="not a geoidspline manifest"):
        geoidspline.open_store(store_copy)


def test_open_store_keeps_no_files_open(small_store):
    """Tiles are read whole when needed: the store object does not keep files open."""
    store = geoidspline.open_store(small_store.path)
    store.undulation(*_random_points(small_store.region, 3000, seed=4))  # reads every tile
    fd_dir = Path("/proc/self/fd")
    if not fd_dir.is_dir():
        pytest.skip("no /proc")
    open_files = {os.path.realpath(fd_dir / fd) for fd in os.listdir(fd_dir)}
    assert not [f for f in open_files if f.startswith(str(small_store.path))]
    assert np.isfinite(store.undulation(20.0, 30.0))
