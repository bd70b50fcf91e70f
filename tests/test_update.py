"""Regional updates: new data inside, old store outside, atomic and locked."""

import hashlib
import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

import geoidspline
from geoidspline.api import build_store
from geoidspline.errors import CoordinateError, StoreError
from geoidspline.geodesy.ellipsoids import KM_PER_DEGREE
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.base import Provenance
from geoidspline.sources.formats import write_gtx
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import GLOBAL, Region
from geoidspline.store.reader import verify_store
from geoidspline.api.regional import update_store

REGION = Region(0, 10, 20, 30)
BLEND_KM = 300.0
PARAMS = FitParameters(h0=0.2, max_level=3, tolerance_m=0.05, tile_size=0.4)


def base_field(lat, lon):
    p, l = np.radians(lat), np.radians(lon)
    return 20 * np.sin(2 * p) * np.cos(l) + 10 * np.cos(p) ** 2 * np.sin(2 * l) + 5


def bump(lat, lon):
    return 3 * np.exp(-((lat - 10) ** 2 + (lon - 20) ** 2) / 20)


def grid(field, name, step=1.0, **prov):
    lat = np.arange(-90, 90 + 1e-9, step)
    lon = np.arange(-180, 180 - 1e-9, step)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    values = field(lat2, lon2).astype(np.float32).astype(float)
    return GeoidGrid(lat, lon, values, Provenance(source=name, model=name, tide_system="tide_free", **prov))


@pytest.fixture(scope="module")
def base_store(tmp_path_factory):
    path = tmp_path_factory.mktemp("update") / "base"
    build_store(grid(base_field, "base"), path, GLOBAL, PARAMS)
    return path


@pytest.fixture
def store(base_store, tmp_path):
    import shutil

    path = tmp_path / "store"
    shutil.copytree(base_store, path)
    return path


def new_grid(step=1.0):
    return grid(lambda la, lo: base_field(la, lo) + bump(la, lo), "new", step=step)


def snapshot(path):
    """Every file's sha256 but the lock file's (its pid is for messages only)."""
    return {p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(path).rglob("*")) if p.is_file() and p.name != ".lock"}


#: A small regional store for the tests that kill writers in subprocesses: few tiles
#: (tile size 1), a 2° grid, so each killed update costs a second, not half a minute.
SMALL_REGION = Region(-10, 0, 30, 40)
SMALL_PARAMS = FitParameters(h0=0.2, max_level=2, tolerance_m=0.05, tile_size=1.0)


@pytest.fixture(scope="module")
def small_base(tmp_path_factory):
    path = tmp_path_factory.mktemp("update_small") / "base"
    build_store(grid(base_field, "base", step=2.0), path, SMALL_REGION, SMALL_PARAMS)
    return path


@pytest.fixture
def small(small_base, tmp_path):
    import shutil

    return Path(shutil.copytree(small_base, tmp_path / "small"))


@pytest.fixture(scope="module")
def updated(base_store, tmp_path_factory):
    import shutil

    path = tmp_path_factory.mktemp("updated") / "store"
    shutil.copytree(base_store, path)
    before = geoidspline.open_store(path).manifest
    record = update_store(path, new_grid(), REGION, blend_width_km=BLEND_KM)
    return path, before, record


def test_values_inside_follow_the_new_data(updated):
    path, _, record = updated
    store = geoidspline.open_store(path)
    assert record["converged"] and record["max_error_m"] <= PARAMS.tolerance_m
    rng = np.random.default_rng(1)
    lat, lon = rng.uniform(0, 20, 3000), rng.uniform(10, 30, 3000)
    truth = base_field(lat, lon) + bump(lat, lon)
    # between the 1° nodes a little more than the node tolerance
    assert np.abs(store.undulation(lat, lon) - truth).max() < 2 * PARAMS.tolerance_m


def test_the_record_gives_the_errors_of_what_the_store_holds(updated):
    """The update's errors in the region are those of the stored spline (a format-2
    store rounds coefficients to its step), not of the unrounded fit."""
    path, _, record = updated
    store = geoidspline.open_store(path)
    assert store.manifest["spline"].get("value_step_m")  # a format-2 store: rounding happened
    source = new_grid()
    lat2, lon2 = np.meshgrid(source.latitude, source.longitude, indexing="ij")
    inside = REGION.contains(lat2, lon2)
    errors = source.values[inside] - store.undulation(lat2[inside], lon2[inside])
    assert record["nodes_in_region"] == inside.sum()
    assert record["max_error_m"] == pytest.approx(np.abs(errors).max(), abs=1e-9)


def test_an_update_finer_than_the_store_rounds_its_tiles_finer(store):
    """A format-2 store rounds coefficients to its step (here 67 mm, sized for the fit's
    5 cm); an update asking 1 cm rewrites its tiles with that step halved as often as
    its nodes need, so the stored spline meets 1 cm there, and the untouched tiles
    (multiples of every such step) stay byte-identical."""
    from geoidspline.store.codec import decode_tile
    from geoidspline.store.format import steps_nest

    before = json.loads((store / "manifest.json").read_text())
    store_step = before["spline"]["value_step_m"]
    record = update_store(store, national_grid(REGION, BLEND_KM, offset_m=0.0), REGION, blend_width_km=BLEND_KM,
                          tolerance_m=0.01)
    after = json.loads((store / "manifest.json").read_text())
    assert after["spline"]["value_step_m"] == store_step and verify_store(store) == []
    old_files = {e["file"] for e in before["tiles"]}
    steps = {e["file"]: decode_tile((store / e["file"]).read_bytes())[0]["value_step_m"] for e in after["tiles"]}
    rewritten = {f: st for f, st in steps.items() if f not in old_files}
    assert len(rewritten) == record["tiles_rewritten"] > 0
    assert all(st == store_step for f, st in steps.items() if f in old_files)
    finer = set(rewritten.values())
    assert len(finer) == 1 and finer.pop() < store_step / 2 and all(steps_nest(st, store_step) for st in steps.values())
    # what the store holds meets the update's tolerance at the source's nodes
    source = national_grid(REGION, BLEND_KM, offset_m=0.0)
    lat2, lon2 = np.meshgrid(source.latitude, source.longitude, indexing="ij")
    inside = REGION.contains(lat2, lon2)
    errors = source.values[inside] - geoidspline.open_store(store).undulation(lat2[inside], lon2[inside])
    assert record["max_error_m"] == pytest.approx(np.abs(errors).max(), abs=1e-9)
    assert record["converged"] == (np.abs(errors).max() <= 0.01)
    assert np.abs(errors).max() <= 0.0105


def test_steps_nest():
    from geoidspline.store.format import steps_nest

    step = 0.066666
    assert steps_nest(step, step) and steps_nest(step / 2, step) and steps_nest(step / 2**20, step)
    assert not steps_nest(step / 3, step) and not steps_nest(2 * step, step) and not steps_nest(0.0, step)


def test_far_values_and_tiles_are_unchanged(updated, base_store):
    path, before, record = updated
    after = geoidspline.open_store(path).manifest
    old = {tuple(e["tile"]): (e["file"], e["sha256"]) for e in before["tiles"]}
    new = {tuple(e["tile"]): (e["file"], e["sha256"]) for e in after["tiles"]}
    changed = [t for t in new if new[t] != old.get(t)]
    assert 0 < len(changed) == record["tiles_rewritten"] < len(old) / 4
    # a changed tile's cube lies within reach of the blend zone: its B-splines are
    # centred in the zone, and a tile owns those whose support centre it holds
    size = after["spline"]["tile_size"]
    reach = np.degrees(np.sqrt(3) * size + 2 * PARAMS.h0)
    zone = REGION.expanded(BLEND_KM / 111.195 + reach)
    for tile in changed:
        centre = (np.array(tile) + 0.5) * size
        centre /= np.linalg.norm(centre)
        lat = np.degrees(np.arcsin(centre[2]))
        lon = np.degrees(np.arctan2(centre[1], centre[0]))
        assert zone.contains(lat, lon), tile
    # every unchanged tile file is byte-identical to the original
    for tile, (name, digest) in new.items():
        if tile not in changed:
            assert hashlib.sha256((path / name).read_bytes()).hexdigest() == digest
            assert (base_store / name).read_bytes() == (path / name).read_bytes()
    # and far from the region the geoid is the old one, to rounding
    rng = np.random.default_rng(2)
    lat, lon = rng.uniform(-60, 60, 5000), rng.uniform(-180, 180, 5000)
    far = ~REGION.expanded(40).contains(lat, lon)
    old_store = geoidspline.open_store(base_store)
    np.testing.assert_allclose(geoidspline.open_store(path).undulation(lat[far], lon[far]),
                               old_store.undulation(lat[far], lon[far]), atol=1e-12)


def test_smooth_across_the_region_edge(updated):
    """No step at the edge: value and gradient change in proportion to the step across
    it (a stacked-grid lookup would jump by the bump's size there)."""
    path, _, _ = updated
    spline = geoidspline.open_store(path).spline
    lat = np.linspace(2, 18, 9)
    edge = directions(lat, np.full(lat.size, 30.0))  # east edge of the region
    east = directions(lat, np.full(lat.size, 30.0 + 1e-6)) - edge
    jumps = []
    for delta in (1.0, 0.1):
        a = spline.evaluate_points(edge - delta * east, nderiv=1)
        b = spline.evaluate_points(edge + delta * east, nderiv=1)
        jumps.append(np.abs(b - a))
    assert np.all(jumps[0] > 0)
    np.testing.assert_allclose(jumps[0] / jumps[1], 10.0, rtol=0.05)


def test_manifest_records_the_update(updated):
    path, before, record = updated
    after = geoidspline.open_store(path).manifest
    assert after["store_version"] == before["store_version"] + 1
    last = after["history"][-1]
    assert last["action"] == "update" and last["source"] == "new"
    assert last["region"] == list(REGION.as_tuple()) and last["previous_version"] == before["store_version"]
    assert last["time"] and "sha256" in last
    assert after["spline"]["coefficients"] == sum(lv["coefficients"] for lv in after["spline"]["levels"])
    assert verify_store(path) == []


@pytest.mark.parametrize("change, error, match", [
    (dict(ellipsoid="GRS80"), StoreError, "ellipsoid"),
    (dict(tide_system="mean_tide"), StoreError, "tide"),
])
def test_incompatible_sources_are_refused_before_writing(store, change, error, match):
    before = snapshot(store)
    source = new_grid()
    source.provenance = Provenance(**{**source.provenance.as_dict(), "notes": (), **change})
    with pytest.raises(error, match=match):
        update_store(store, source, REGION)
    assert snapshot(store) == before


def test_region_outside_the_source_is_refused(store):
    before = snapshot(store)
    lat = np.arange(-10, 30.01, 1.0)
    lon = np.arange(0, 40.01, 1.0)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    regional = GeoidGrid(lat, lon, base_field(lat2, lon2), Provenance(source="regional", tide_system="tide_free"))
    with pytest.raises(CoordinateError, match="not inside the extent"):
        update_store(store, regional, Region(40, 10, 50, 30))
    assert snapshot(store) == before


def national_grid(region, blend_km, offset_m=1.0, margin_deg=1.0, step=0.25):
    """A national grid: the new geoid (the bump, and a datum offset) on a lattice four
    times finer than the store's source, covering the region's blend zone and
    ``margin_deg`` more, nothing beyond."""
    s, w, n, e = region.expanded(blend_km / KM_PER_DEGREE).expanded(margin_deg).as_tuple()
    lat = np.arange(np.floor(s), np.ceil(n) + 1e-9, step)
    lon = np.arange(np.floor(w), np.ceil(e) + 1e-9, step)
    lat2, lon2 = np.meshgrid(lat, lon, indexing="ij")
    values = base_field(lat2, lon2) + bump(lat2, lon2) + offset_m
    return GeoidGrid(lat, lon, values, Provenance(source="national", model="national", tide_system="tide_free"))


def test_outside_the_blend_zone_the_store_is_unchanged(store):
    """The update's B-splines lie inside the blend zone, so beyond it the store keeps its
    values (to the rounding of summing the levels in another order), even where the national grid has no nodes at all (beyond its extent
    nothing constrains a B-spline that would reach there: it used to move the store by
    decimetres hundreds of km away)."""
    before = geoidspline.open_store(store)
    record = update_store(store, national_grid(REGION, BLEND_KM), REGION, blend_width_km=BLEND_KM)
    assert record["converged"] and record["max_error_m"] <= PARAMS.tolerance_m
    after = geoidspline.open_store(store)
    zone = REGION.expanded(BLEND_KM / KM_PER_DEGREE)
    rng = np.random.default_rng(5)
    lat, lon = rng.uniform(-40, 60, 200_000), rng.uniform(-30, 70, 200_000)
    outside = ~zone.contains(lat, lon)
    assert outside.sum() > 150_000
    change = after.undulation(lat[outside], lon[outside]) - before.undulation(lat[outside], lon[outside])
    assert np.abs(change).max() <= 1e-12
    # and inside the region the national geoid, offset included
    inside = REGION.contains(lat, lon)
    truth = base_field(lat[inside], lon[inside]) + bump(lat[inside], lon[inside]) + 1.0
    assert np.abs(after.undulation(lat[inside], lon[inside]) - truth).max() < 2 * PARAMS.tolerance_m


def test_a_source_too_coarse_for_its_blend_is_reported_and_still_local(store):
    """A 2° source cannot fall to the store's values within 100 km: the update says so
    (not converged, with the reason) and still changes nothing outside its blend zone."""
    before = geoidspline.open_store(store)
    record = update_store(store, national_grid(REGION, 100.0, step=2.0), REGION, blend_width_km=100.0)
    assert not record["converged"] and "blend width (100 km) spans fewer than 4 node spacings" in record["hint"]
    after = geoidspline.open_store(store)
    zone = REGION.expanded(100.0 / KM_PER_DEGREE)
    lat, lon = np.meshgrid(np.arange(-40, 60, 0.7), np.arange(-30, 70, 0.7), indexing="ij")
    outside = ~zone.contains(lat, lon)
    assert np.abs(after.undulation(lat[outside], lon[outside]) - before.undulation(lat[outside], lon[outside])).max() \
        <= 1e-12


def test_a_blend_zone_beyond_the_source_is_refused_with_the_region_that_fits(store):
    before = snapshot(store)
    source = national_grid(REGION, BLEND_KM, margin_deg=0.0)  # just the zone, rounded out to 1°
    wide = Region(REGION.south - 1.0, REGION.west, REGION.north, REGION.east)
    with pytest.raises(CoordinateError, match=r"blend zone reaches beyond the extent of national.*the largest is") as error:
        update_store(store, source, wide, blend_width_km=BLEND_KM)
    assert snapshot(store) == before
    bounds = str(error.value).split("the largest is ")[1].split(")")[0].split()
    assert bounds[0::2] == ["S", "W", "N", "E"]
    suggested = Region(*map(float, bounds[1::2]))
    assert suggested.south >= source.extent.south and suggested.north <= source.extent.north
    record = update_store(store, source, suggested, blend_width_km=BLEND_KM)  # the region offered is accepted
    assert record["store_version"] == 2


def test_no_data_nodes_fade_from_the_nearest_data_and_keep_the_store_beyond(store, monkeypatch):
    """A source with no data outside the region (a national grid, NaN over the sea): a
    no-data node gets the difference of the nearest node with data, faded out over the
    blend width, times the region's weight, so the change has no step at the coast and
    is 0 (the store's values) where either taper is; never NaN where the store has data."""
    import geoidspline.fitting.update as update_module

    def island(la, lo):
        return np.where(REGION.contains(la, lo), base_field(la, lo) + bump(la, lo) + 1.0, np.nan)

    captured = {}

    class Captured(Exception):
        """Not a fault the store turns into a StoreError: it stops the update here."""

    def capture(sample, *args, **kwargs):
        captured["sample"] = sample
        raise Captured

    monkeypatch.setattr(update_module, "fit_nodes", capture)
    with pytest.raises(Captured):
        update_store(store, grid(island, "island"), REGION, blend_width_km=BLEND_KM, tolerance_m=0.02)
    sample = captured["sample"]
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    weight = update_module.blend_weight(REGION, BLEND_KM / KM_PER_DEGREE, lat2, lon2)
    residual = sample.undulation
    assert np.all(np.isfinite(residual))  # the global store covers every node
    assert np.all(residual[weight == 0.0] == 0.0)
    inside = REGION.contains(lat2, lon2)
    old = geoidspline.open_store(store).undulation(lat2, lon2)
    # (the grid holds float32 values: rounding of 30 m values, ~2e-6 m)
    np.testing.assert_allclose(residual[inside], island(lat2, lon2)[inside] - old[inside], atol=1e-5)
    # just outside the east edge: the edge node's difference, tapered twice (region and data)
    row = np.argmin(np.abs(sample.latitude - 10.0))
    edge = np.argmin(np.abs(sample.longitude - REGION.east))
    diff_edge = residual[row, edge]
    for k in (1, 2):
        d_km = (sample.longitude[edge + k] - REGION.east) * KM_PER_DEGREE * np.cos(np.radians(10.0))
        taper = 0.5 * (1 + np.cos(np.pi * min(d_km / BLEND_KM, 1.0)))
        assert residual[row, edge + k] == pytest.approx(weight[row, edge + k] * taper * diff_edge, rel=0.05)
    assert 0 < abs(residual[row, edge + 1]) < abs(diff_edge)


def test_fade_into_no_data():
    from geoidspline.fitting.update import fade_into_no_data

    lat = np.arange(0.0, 10.01, 0.1)
    lon = np.arange(0.0, 10.01, 0.1)
    diff = np.full((lat.size, lon.size), np.nan)
    diff[:, :50] = 2.0  # data west of 5° E
    faded = fade_into_no_data(diff, lat, lon, 100.0)
    assert np.all(faded[:, :50] == 0.0)  # nodes with data are not faded
    km = (lon - lon[49]) * KM_PER_DEGREE * np.cos(np.radians(5.0))
    expected = np.where(km >= 100.0, 0.0, 1.0 + np.cos(np.pi * np.minimum(km / 100.0, 1.0)))
    np.testing.assert_allclose(faded[50, 50:], expected[50:], atol=1e-12)
    assert np.all(np.diff(faded[50, 50:]) <= 0)  # falling away from the data
    assert not fade_into_no_data(diff, lat, lon, 0.0).any()  # no blend: no fade
    assert not fade_into_no_data(np.full_like(diff, np.nan), lat, lon, 100.0).any()


def test_a_coast_is_no_step(store):
    """A national grid with no data east of a meridian inside the region ("sea"), 1 m
    above the store on land: across the coast the composite changes smoothly (steps per
    0.01° a small fraction of the 1 m a hard switch makes), and beyond the blend width
    out at sea the store keeps its values."""
    def land(la, lo):
        return np.where(lo <= 20.0, base_field(la, lo) + 1.0, np.nan)

    before = geoidspline.open_store(store)
    source = national_grid(REGION, BLEND_KM)
    lat2, lon2 = np.meshgrid(source.latitude, source.longitude, indexing="ij")
    coast = GeoidGrid(source.latitude, source.longitude, land(lat2, lon2), source.provenance)
    update_store(store, coast, REGION, blend_width_km=BLEND_KM)
    after = geoidspline.open_store(store)
    lon = np.arange(17.0, 26.0, 0.01)
    lat = np.full(lon.size, 10.0)
    change = after.undulation(lat, lon) - before.undulation(lat, lon)
    assert change[0] == pytest.approx(1.0, abs=PARAMS.tolerance_m)  # land: the new geoid
    assert np.abs(np.diff(change)).max() < 0.02  # a hard switch: a 1 m step
    beyond = lon > 20.0 + BLEND_KM / KM_PER_DEGREE / np.cos(np.radians(10.0)) + 0.5
    assert np.abs(change[beyond]).max() < PARAMS.tolerance_m


def test_read_only_and_locked_stores_are_refused(store, monkeypatch):
    from geoidspline.store.writer import StoreLock

    with StoreLock(store):  # another open file description holds the lock
        before = snapshot(store)
        with pytest.raises(StoreError, match=rf"another writer \(pid {os.getpid()}\)"):
            update_store(store, new_grid(), REGION)
    assert snapshot(store) == before
    import geoidspline.store.update as update_module

    monkeypatch.setattr(update_module.os, "access", lambda *a, **k: False)
    with pytest.raises(StoreError, match="read-only"):
        update_store(store, new_grid(), REGION)
    assert snapshot(store) == before


def test_a_second_writer_waits_for_the_first_with_wait(store, monkeypatch):
    """--wait: an update finding the lock taken tries again until it is free (here the
    holder lets go at the first retry), or gives up once the time is spent, naming the
    holder and the wait, with nothing changed."""
    import geoidspline.store.writer as writer
    from geoidspline.store.writer import StoreLock

    holder = StoreLock(store)  # another open file description holds the lock
    holder.__enter__()
    before = snapshot(store)
    with pytest.raises(StoreError, match=rf"another writer \(pid {os.getpid()}\) is writing this store \(waited 0.3 s\).*--wait SECONDS"):
        update_store(store, new_grid(), REGION, blend_width_km=BLEND_KM, wait_seconds=0.3)
    assert snapshot(store) == before
    pauses = []

    def pause(seconds):
        pauses.append(seconds)
        if len(pauses) == 1:
            holder.__exit__(None, None, None)  # the first writer finishes

    monkeypatch.setattr(writer, "_pause", pause)
    record = update_store(store, new_grid(), REGION, blend_width_km=BLEND_KM, wait_seconds=600)
    assert len(pauses) == 1 and 0 < pauses[0] <= writer.LOCK_POLL_SECONDS
    assert record["store_version"] == 2 and verify_store(store) == []


UPDATE_SCRIPT = textwrap.dedent("""
    import sys
    sys.path.insert(0, {tests!r})
    from test_update import new_grid, REGION, BLEND_KM
    from geoidspline.api.regional import update_store
    update_store({store!r}, new_grid(step=2.0), REGION, blend_width_km=BLEND_KM)
""")


UPDATE_POINTS = ["after-lock", "before-tiles", "during-tiles", "after-tiles", "before-manifest", "manifest-written",
                 "after-manifest"]


@pytest.mark.parametrize("point", UPDATE_POINTS)
def test_an_update_killed_anywhere_leaves_the_old_or_the_new_store(small, point):
    old = geoidspline.open_store(small)
    old_version = old.manifest["store_version"]
    script = UPDATE_SCRIPT.format(tests=str(Path(__file__).parent), store=str(small))
    env = dict(os.environ, GEOIDSPLINE_CRASH_AT=point)
    run = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert run.returncode == 77, run.stderr  # died at the crash point, no clean-up
    assert verify_store(small) == []
    reopened = geoidspline.open_store(small)
    version = reopened.manifest["store_version"]
    assert version == (old_version + 1 if point == "after-manifest" else old_version)
    if version == old_version:
        lat, lon = np.array([10.0, -5.0]), np.array([20.0, 35.0])
        assert np.array_equal(reopened.undulation(lat, lon), old.undulation(lat, lon))
    # the dead writer's lock does not block the next update (the kernel released it)
    record = update_store(small, new_grid(step=2.0), REGION, blend_width_km=BLEND_KM)
    assert record["store_version"] == version + 1 and verify_store(small) == []
    assert (small / ".lock").exists()  # the lock file is never removed


@pytest.mark.parametrize("point", [p if p in ("after-lock", "during-tiles", "manifest-written") else pytest.param(
    p, marks=pytest.mark.slow)  # every point with --slow
    for p in UPDATE_POINTS if p != "after-manifest"])
def test_sigkill_during_an_update(small, point):
    """A real SIGKILL at a commit point (the writer stops itself there first): the store
    is the old version, opens and verifies, and the kernel has released the lock."""
    import signal

    old = geoidspline.open_store(small).manifest
    script = UPDATE_SCRIPT.format(tests=str(Path(__file__).parent), store=str(small))
    env = dict(os.environ, GEOIDSPLINE_STOP_AT=point)
    proc = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE)
    _, status = os.waitpid(proc.pid, os.WUNTRACED)
    assert os.WIFSTOPPED(status), proc.stderr.read()
    with pytest.raises(StoreError, match=rf"another writer \(pid {proc.pid}\)"):
        update_store(small, new_grid(step=2.0), REGION, blend_width_km=BLEND_KM)
    proc.send_signal(signal.SIGKILL)
    assert proc.wait(timeout=60) == -signal.SIGKILL
    assert verify_store(small) == []
    assert geoidspline.open_store(small).manifest == old
    record = update_store(small, new_grid(step=2.0), REGION, blend_width_km=BLEND_KM)
    assert record["store_version"] == old["store_version"] + 1 and verify_store(small) == []


def test_cli_update_and_verify(store, tmp_path):
    source = write_gtx(tmp_path / "new.gtx", new_grid())
    run = subprocess.run([sys.executable, "-m", "geoidspline", "fit", str(source), "--update", str(store),
                          "--region", "0", "10", "20", "30", "--blend-width", "300", "--tolerance", "0.04",
                          "--json", "-q"],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode in (0, 3), run.stderr
    record = json.loads(run.stdout)
    assert record["store_version"] == 2 and record["tolerance_m"] == 0.04  # --tolerance applies to the update
    run = subprocess.run([sys.executable, "-m", "geoidspline", "info", str(store), "--verify"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0 and "every tile matches" in run.stdout
    live = sorted(e["file"] for e in json.loads((store / "manifest.json").read_text())["tiles"])
    victim = store / live[0]
    victim.write_bytes(victim.read_bytes()[:-10])
    run = subprocess.run([sys.executable, "-m", "geoidspline", "info", str(store), "--verify"],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 1 and victim.name in run.stdout and "truncated" in run.stdout
    assert "Traceback" not in run.stderr


def test_the_finest_level_the_national_data_determine_takes_its_residual_again(store, tmp_path, monkeypatch):
    """A national grid (0.25°) with a 0.5 m peak as narrow as its spacing: the update's
    finest level (6, level 7 being finer than half the spacing) leaves 11.8 mm at its
    nodes in one pass; further passes of that level, on its B-splines inside the blend
    zone, bring them within 1 cm, and outside the zone the store is still unchanged."""
    import shutil

    from geoidspline.fitting import driver

    source = national_grid(REGION, BLEND_KM)
    lat2, lon2 = np.meshgrid(source.latitude, source.longitude, indexing="ij")
    peak = 0.5 * np.exp(-((lat2 - 10) ** 2 + (lon2 - 20) ** 2) / 0.25**2)
    source = GeoidGrid(source.latitude, source.longitude, source.values + peak, source.provenance)
    one_pass = Path(shutil.copytree(store, tmp_path / "one_pass"))
    with monkeypatch.context() as patch:
        patch.setattr(driver, "FINEST_LEVEL_PASSES", 1)
        before = update_store(one_pass, source, REGION, blend_width_km=BLEND_KM, tolerance_m=0.01)
    assert before["max_error_m"] == pytest.approx(0.0118, abs=0.0005)  # at the national nodes in the region
    original = geoidspline.open_store(store)
    record = update_store(store, source, REGION, blend_width_km=BLEND_KM, tolerance_m=0.01)
    assert record["max_error_m"] <= 0.01
    finest = record["levels"][-1]
    assert finest["level"] == 6 and finest["passes"] > 1
    assert finest["pass_max_error_m"][0] == before["levels"][-1]["max_error_m"]
    assert [lv["level"] for lv in record["levels"]] == [lv["level"] for lv in before["levels"]]
    levels = [lv["level"] for lv in json.loads((store / "manifest.json").read_text())["spline"]["levels"]]
    assert levels == sorted(set(levels))  # one spline per level: the passes are in level 6
    after = geoidspline.open_store(store)
    zone = REGION.expanded(BLEND_KM / KM_PER_DEGREE)
    lat, lon = np.meshgrid(np.arange(-40, 60, 0.7), np.arange(-30, 70, 0.7), indexing="ij")
    outside = ~zone.contains(lat, lon)
    assert np.abs(after.undulation(lat[outside], lon[outside])
                  - original.undulation(lat[outside], lon[outside])).max() <= 1e-12
    assert verify_store(store) == []
