"""A model's whole globe fitted band by band (geoidspline.fitting.bands, geoidspline.api.banded):
the bands give the whole-globe fit's coefficients bit for bit, each band is committed on
its own, an interrupted fit resumes to the same store, and a dask cluster of separate
worker processes over TCP writes the same store as this process."""

from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import random_synthesis
from test_interpolation import _write_gfc

from geoidspline.api import build_store, open_store
from geoidspline.errors import FitError, StoreError
from geoidspline.fitting.bands import Band, band_indices, band_margin_deg, band_spline, fit_band, uses_bands
from geoidspline.fitting.driver import _fit_by_interpolation
from geoidspline.fitting.executors import Executor
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sphere.region import GLOBAL, Region
from geoidspline.store.format import PROGRESS

#: A degree-48 model whose level 0 at h0 = 0.03 leaves 48 nodes above 0.14 m (0.157 m
#: max): a small level-1 overlay on the globe, tiled into blocks of 8 cells. The command
#: line's fit promises 0.155 m: its 20,000 check points see up to 0.153 m (between the
#: nodes, which the overlay brings within the tolerance).
PARAMS = dict(method="interpolation", order=4, h0=0.03, max_level=2, tolerance_m=0.14, block_cells=8)
CLI_OPTIONS = ["--preset", "generic", "--method", "interpolation", "--refinement", "overlays", "--order", "4",
               "--h0", "0.03", "--max-level", "2", "--sample-spacing", "0.625", "--tolerance", "0.155"]


@pytest.fixture(scope="module")
def model():
    return random_synthesis(48, 3, "toy48")


@pytest.fixture(scope="module")
def model_file(model, tmp_path_factory):
    return _write_gfc(tmp_path_factory.mktemp("model") / "toy48.gfc", model.model)


@pytest.fixture(scope="module")
def whole(model):
    """The whole globe in one call, its overlay blocks tiled as a band's are."""
    return _fit_by_interpolation(model, GLOBAL, FitParameters(**PARAMS), None, None, True, None)


def store_levels(path):
    """{level: (keys, coefficients)} of a store, read back tile by tile."""
    spline = open_store(path, lazy=False).spline
    levels = getattr(spline, "full", spline).levels
    return {lv.level: (lv.keys, lv.coefficients) for lv in levels}


def assert_same_store(a, b):
    """Two stores hold the same coefficients bit for bit, in the same tiles."""
    la, lb = store_levels(a), store_levels(b)
    assert la.keys() == lb.keys()
    for level in la:
        assert np.array_equal(la[level][0], lb[level][0])
        assert np.array_equal(la[level][1], lb[level][1])
    ma, mb = (json.loads((Path(p) / "manifest.json").read_text()) for p in (a, b))
    assert [t["tile"] for t in ma["tiles"]] == [t["tile"] for t in mb["tiles"]]
    assert [t["coefficients"] for t in ma["tiles"]] == [t["coefficients"] for t in mb["tiles"]]
    assert ma["accuracy"] == mb["accuracy"]


@pytest.mark.parametrize("reach, grouped", [(False, False), (True, False), (True, True)])
def test_bands_give_the_whole_globe_coefficients_bit_for_bit(model, whole, reach, grouped):
    """Level 0 (quasi-interpolated from a band of lattice rows) and the overlays (least
    squares in blocks) of the bands together are the whole-globe fit's, bit for bit, with
    the default margin and with one covering every overlay block's reach, with a slab a
    band or with slabs grouped (two near the equator)."""
    params = FitParameters(**PARAMS)
    margin = band_margin_deg(params, overlay_reach=reach)
    slabs = band_indices(params)
    assert len(slabs) == 6  # z slabs of 0.4 from -1.2 to 1.2
    groups = [Band(-3, -3), Band(-2, -2), Band(-1, 0), Band(1, 1), Band(2, 2)] if grouped \
        else [Band(b, b) for b in slabs]
    bands = [fit_band(model, params, band, np.empty(0), np.empty(0), margin_deg=margin) for band in groups]
    banded = band_spline(bands, params)
    assert [lv.level for lv in whole.spline.levels] == [lv.level for lv in banded.levels] == [0, 1]
    assert len(whole.spline.levels[1]) > 50  # the overlay is not empty
    for a, b in zip(whole.spline.levels, banded.levels):
        assert np.array_equal(a.keys, b.keys)
        assert np.array_equal(a.coefficients, b.coefficients)
    # every node is some band's, once
    assert sum(b.node_count for b in bands) == whole.node_count


def test_only_a_models_whole_globe_is_fitted_by_bands():
    params = FitParameters(**PARAMS)
    assert uses_bands(params, GLOBAL)
    assert not uses_bands(params, Region(-60, -180, 60, 180))
    assert not uses_bands(FitParameters(**{**PARAMS, "method": "least-squares"}), GLOBAL)


def test_a_banded_store_holds_the_whole_fit_and_measures_it(model, whole, tmp_path):
    result, info = build_store(model, tmp_path / "s", params=FitParameters(**PARAMS), check_count=2000)
    levels = store_levels(tmp_path / "s")
    manifest = json.loads((tmp_path / "s" / "manifest.json").read_text())
    start, steps = manifest["spline"]["value_step_m"], manifest["fit"]["bands"]["value_steps_m"]
    assert all(start / step in (1, 2, 4, 8, 16) for step in steps)  # each band's nests in the store's
    for lv in whole.spline.levels:  # the whole fit's coefficients, each rounded to its band's step
        keys, coefs = levels[lv.level]
        assert np.array_equal(keys, lv.keys)
        assert np.abs(coefs - lv.coefficients).max() <= start  # half a step, a step where nudged
        assert np.all(np.isclose(coefs / min(steps), np.rint(coefs / min(steps)), rtol=0, atol=1e-6))
    assert info["converged"] and info["nodes"] == whole.node_count and info["check_points"] == 2000
    # the store keeps the tolerance at the nodes and the random check points (exact synthesis)
    assert info["node_max_error_m"] <= 0.14 and info["max_error_m"] <= 0.14
    assert not (tmp_path / "s" / PROGRESS).exists()
    assert manifest["fit"]["bands"]["count"] == 6 and result.spline is None


def info_step(path):
    return json.loads((Path(path) / "manifest.json").read_text())["spline"]["value_step_m"]


def test_bands_group_slabs_where_the_memory_allows(model):
    """Slabs near the equator hold fewer lattice rows than those near the poles: a band
    takes consecutive slabs while its need stays within the largest one-slab band's (the
    memory the tiles were sized for); every slab is one band's."""
    from geoidspline.fitting.memory import band_need, band_slabs

    # a lattice of many nodes for its level-0 coefficients (as EGM2008's 0.82' at h0 0.0009)
    params = FitParameters(**{**PARAMS, "tile_size": 0.1, "h0": 0.01, "sample_spacing_deg": 0.05})
    slabs = band_indices(params)
    largest = max(band_need(model, params, Band(b, b))[0] for b in slabs)
    bands = band_slabs(model, params)
    assert [b for band in bands for b in range(band.first, band.last + 1)] == slabs
    assert all(band_need(model, params, band)[0] <= largest for band in bands)
    assert len(bands) < len(slabs)
    equator = next(band for band in bands if band.first <= 0 <= band.last)
    below = next(band for band in bands if band.first <= -9 <= band.last)  # z -0.9..-0.8, 64..53 S
    assert equator.last - equator.first >= 2 > below.last - below.first


def test_the_memory_plan_names_the_largest_band(model, tmp_path):
    with pytest.raises(FitError, match="largest band"):
        build_store(model, tmp_path / "s", params=FitParameters(**PARAMS), executor=Executor(max_memory_bytes=1e7))
    assert not (tmp_path / "s").exists()


def _fit_command(model_file, store, *extra):
    """``geoid-fit`` of the model into ``store``, quiet unless ``-v`` is among ``extra``."""
    quiet = [] if "-v" in extra else ["-q"]
    return [sys.executable, "-m", "geoidspline", "fit", str(model_file), *CLI_OPTIONS, "--store", str(store),
            *quiet, *extra]


def test_an_interrupted_fit_resumes_to_the_uninterrupted_store(model_file, tmp_path):
    """A fit killed (like SIGKILL) right after its second band was committed leaves an
    unfinished fit; a new fit there is refused, --resume fits the other four bands only
    and writes the store an uninterrupted fit writes."""
    whole_store = tmp_path / "whole"
    done = subprocess.run(_fit_command(model_file, whole_store), capture_output=True, text=True)
    assert done.returncode == 0, done.stderr
    store = tmp_path / "killed"
    env = {**os.environ, "GEOIDSPLINE_CRASH_AT": "band-committed", "GEOIDSPLINE_CRASH_AFTER": "2"}
    killed = subprocess.run(_fit_command(model_file, store), capture_output=True, text=True, env=env)
    assert killed.returncode == 77, killed.stderr
    record = json.loads((store / PROGRESS).read_text())
    assert len(record["bands"]) == 2 and not (store / "manifest.json").exists()
    with pytest.raises(StoreError, match="unfinished fit"):
        open_store(store)
    again = subprocess.run(_fit_command(model_file, store), capture_output=True, text=True)
    assert again.returncode == 1 and "unfinished fit (2 bands committed)" in again.stderr and "--resume" in again.stderr
    assert "resume=True" not in again.stderr  # the command line names its options
    resumed = subprocess.run(_fit_command(model_file, store, "--resume", "-v"), capture_output=True, text=True)
    assert resumed.returncode == 0, resumed.stderr
    assert "resuming: 2 of 6 bands committed already" in resumed.stderr
    assert resumed.stderr.count("INFO: band ") == 4
    assert_same_store(whole_store, store)
    assert not (store / PROGRESS).exists()


def test_a_resumed_fit_must_be_the_same_fit(model_file, tmp_path):
    store = tmp_path / "s"
    env = {**os.environ, "GEOIDSPLINE_CRASH_AT": "band-committed"}
    assert subprocess.run(_fit_command(model_file, store), capture_output=True, env=env).returncode == 77
    other = [a if a != "2" else "1" for a in _fit_command(model_file, store, "--resume")]  # --max-level 1
    refused = subprocess.run(other, capture_output=True, text=True)
    assert refused.returncode == 1 and "not this one" in refused.stderr and "parameters" in refused.stderr


def test_progress_shows_every_phase_and_quiet_silences_it(model_file, tmp_path):
    loud = subprocess.run(_fit_command(model_file, tmp_path / "a", "-v"), capture_output=True, text=True)
    assert loud.returncode == 0, loud.stderr
    for stage in ("bands: 6 bands", "synthesis:", "lookups:", "prefilter:", "level 0 node errors:",
                  "level 1 blocks:", "check points:", "write:", "bands: 6/6 bands in"):
        assert f"progress: {stage}" in loud.stderr, stage
    quiet = subprocess.run(_fit_command(model_file, tmp_path / "b"), capture_output=True, text=True)
    assert quiet.returncode == 0 and quiet.stderr == ""


def _free_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_a_dask_cluster_over_tcp_writes_the_local_store(model_file, tmp_path):
    """``dask scheduler`` and two ``dask worker`` processes on this machine, over TCP, as
    dask's documentation starts them: the bands are fitted on the workers and the store
    is the local fit's, bit for bit."""
    pytest.importorskip("dask.distributed")
    from distributed import Client

    dask_cli = shutil.which("dask", path=str(Path(sys.executable).parent)) or shutil.which("dask")
    if dask_cli is None:
        pytest.skip("the dask command is not installed")
    port = _free_port()
    address = f"tcp://127.0.0.1:{port}"
    processes = [subprocess.Popen([dask_cli, "scheduler", "--host", "127.0.0.1", "--port", str(port),
                                   "--no-dashboard"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]
    try:
        for name in ("w1", "w2"):
            processes.append(subprocess.Popen([dask_cli, "worker", address, "--nthreads", "1", "--name", name,
                                               "--no-dashboard"], stdout=subprocess.DEVNULL,
                                              stderr=subprocess.DEVNULL))
        with Client(address, timeout="60s") as client:
            client.wait_for_workers(2, timeout=120)
            assert len(client.scheduler_info()["workers"]) == 2
        local = subprocess.run(_fit_command(model_file, tmp_path / "local"), capture_output=True, text=True)
        assert local.returncode == 0, local.stderr
        farmed = subprocess.run(_fit_command(model_file, tmp_path / "dask", "--scheduler", address),
                                capture_output=True, text=True)
        assert farmed.returncode == 0, farmed.stderr
        assert_same_store(tmp_path / "local", tmp_path / "dask")
    finally:
        for process in processes[::-1]:
            process.terminate()
        for process in processes:
            process.wait(timeout=60)


def test_bands_are_made_smaller_until_the_largest_fits_the_memory(model):
    from geoidspline.fitting.memory import SMALLEST_BAND_TILE, banded_parameters, plan

    params = FitParameters(**PARAMS)
    need = plan(model, GLOBAL, params).bytes
    smaller = banded_parameters(model, GLOBAL, params, 0.9 * need)
    assert smaller.tile_size == 0.2 and plan(model, GLOBAL, smaller).bytes <= 0.9 * need
    assert len(band_indices(smaller)) == 12  # z from -1.2 to 1.2 (support centres lie off the sphere)
    assert banded_parameters(model, GLOBAL, params, need) == params  # fits: unchanged
    assert banded_parameters(model, GLOBAL, params, 1.0).tile_size >= SMALLEST_BAND_TILE  # then refused by the plan
    regional = Region(-60, -180, 60, 180)
    assert banded_parameters(model, regional, params, 1.0) == params  # not fitted by bands


def test_the_stores_node_figures_hold_for_the_store_read_back(model, tmp_path):
    """Each band measured its nodes with its own rounding and bounded its neighbours' at
    its edges: at every lattice node the store read back is within the node maximum
    its manifest states; its RMS is measured with the neighbours' coefficients
    unrounded near a band's edges (here a step of 26.7 cm moves it by 0.4 %)."""
    params = FitParameters(**{**PARAMS, "tolerance_m": 0.15})  # a coarser step: rounding shows
    build_store(model, tmp_path / "s", params=params, check_count=500)
    manifest = json.loads((tmp_path / "s" / "manifest.json").read_text())
    sample = model.nodes(GLOBAL, spacing_deg=0.625)
    lat, lon = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")  # -180 and 180 both, as the fit
    keep = (np.abs(lat) < 90) | (lon == lon[0, 0])  # a pole is one node
    errors = sample.undulation[keep] - open_store(tmp_path / "s").undulation(lat[keep], lon[keep])
    assert errors.size == manifest["accuracy"]["nodes"]
    assert np.abs(errors).max() <= manifest["accuracy"]["node_max_error_m"] <= 0.15
    assert np.sqrt(np.mean(errors ** 2)) == pytest.approx(manifest["accuracy"]["node_rms_error_m"], rel=6e-3)


def _random_band_spline(rng, latitudes_deg, count, h, order):
    """``count`` random node directions at latitudes ``latitudes_deg`` (low, high) and
    longitudes -10..10 degrees, a one-level spline of random coefficients on the
    B-splines touching them, and the band's owned mask (tile slab 0)."""
    from geoidspline.bspline.keys import touching_keys
    from geoidspline.bspline.level import LevelSpline, cube_of_support_centres
    from geoidspline.hierarchy.ambient import AmbientSpline
    from geoidspline.sphere.coordinates import directions

    dirs = directions(rng.uniform(*latitudes_deg, count), rng.uniform(-10, 10, count))
    keys = touching_keys(np.unique(np.floor(dirs / h).astype(np.int64), axis=0), order)
    spline = AmbientSpline([LevelSpline(0, h, order, keys, rng.normal(0.0, 1.0, keys.size))])
    owned = [cube_of_support_centres(spline.levels[0].indices, h, order, 1.0)[:, 2] == 0]
    return dirs, spline, owned


def test_a_bands_rounding_is_corrected_at_the_nodes_it_takes_over_the_tolerance():
    """Rounding to the start step takes one node over the tolerance: before halving the
    step, the band moves the B-spline nearest that node one step the other way; the
    stored values stay multiples of the step within a step of the fit's, and the node
    errors returned are those of the stored spline."""
    from geoidspline.fitting.bands import Rounding, band_step
    from geoidspline.store.codec import quantisation_change, stored_values

    rng = np.random.default_rng(5)
    h, order, start, tolerance = 0.05, 4, 0.2, 0.1
    dirs, spline, owned = _random_band_spline(rng, (25, 35), 3000, h, order)  # z 0.42-0.57: no edge
    assert owned[0].all()
    change = quantisation_change(spline, start, dirs)
    worst = int(np.argmax(np.abs(change)))
    fit_errors = rng.uniform(-0.03, 0.03, dirs.shape[0])
    # rounded, this node is 5 mm over the tolerance
    fit_errors[worst] = -np.sign(change[worst]) * (tolerance + 0.005 - abs(change[worst]))
    assert np.abs(fit_errors - change).max() > tolerance
    step, stored, errors, largest = band_step(spline, owned, dirs, fit_errors, Rounding(start, tolerance, stored_values),
                                              Band(0, 0), 1.0)
    assert step == start and largest <= tolerance  # corrected, not halved
    exact, kept = spline.levels[0].coefficients, stored.levels[0].coefficients
    moved = np.abs(kept - stored_values(exact, start)) > 0
    assert 1 <= moved.sum() <= 10 and np.abs(kept - exact).max() <= start
    np.testing.assert_array_equal(kept, stored_values(kept, start))  # multiples of the step, bitwise
    truth = fit_errors + spline.evaluate_points(dirs)
    np.testing.assert_allclose(errors, truth - stored.evaluate_points(dirs), atol=1e-12)
    assert np.abs(errors).max() <= tolerance


def test_a_node_its_neighbours_rounding_takes_over_does_not_halve_a_bands_step():
    """A node at a band's edge that the neighbour's rounding alone takes over the tolerance
    (its own values exact) is reported, not chased: halving the band's own step cannot
    bring it back, and the step stays the one its other nodes need."""
    from geoidspline.bspline.level import LevelSpline
    from geoidspline.fitting.bands import Rounding, band_step
    from geoidspline.hierarchy.ambient import AmbientSpline
    from geoidspline.store.codec import stored_values

    rng = np.random.default_rng(6)
    h, order, start, tolerance = 0.05, 4, 0.2, 0.1
    dirs, spline, owned = _random_band_spline(rng, (70, 84), 2000, h, order)  # z 0.94-0.99, by the edge at 1
    assert 0 < owned[0].sum() < len(spline.levels[0])
    lv = spline.levels[0]
    theirs = AmbientSpline([LevelSpline(0, h, order, lv.keys[~owned[0]],
                                        stored_values(lv.coefficients[~owned[0]], start) - lv.coefficients[~owned[0]])])
    moved = theirs.evaluate_points(dirs)  # the neighbour's change if it keeps the start step
    node = int(np.argmax(np.abs(moved)))
    fit_errors = np.zeros(dirs.shape[0])
    fit_errors[node] = -np.sign(moved[node]) * (tolerance - 0.5 * abs(moved[node]))
    step, _, _, largest = band_step(spline, owned, dirs, fit_errors, Rounding(start, tolerance, stored_values),
                                    Band(0, 0), 1.0)
    assert largest > tolerance  # reported as it is
    assert step >= start / 8  # not halved towards 1 µm for it


def test_a_bands_step_is_halved_while_its_rounding_lifts_the_rms_above_its_budget():
    """Every node within the tolerance at the first step, but the rounding's noise lifts
    the nodes' RMS above ``Rounding.rms_m``: the step is halved until it does not (and
    without a budget the first step is kept)."""
    from geoidspline.fitting.bands import Rounding, band_step
    from geoidspline.store.codec import quantisation_change, stored_values

    rng = np.random.default_rng(7)
    h, order, start, tolerance = 0.05, 4, 0.2, 0.15
    dirs, spline, owned = _random_band_spline(rng, (25, 35), 3000, h, order)  # no edge
    fit_errors = np.zeros(dirs.shape[0])
    noise = float(np.sqrt(np.mean(quantisation_change(spline, start, dirs) ** 2)))
    assert 0.0 < noise and np.abs(quantisation_change(spline, start, dirs)).max() <= tolerance
    step, _, errors, _ = band_step(spline, owned, dirs, fit_errors, Rounding(start, tolerance, stored_values),
                                   Band(0, 0), 1.0)
    assert step == start
    budget = 0.4 * noise
    step, _, errors, largest = band_step(spline, owned, dirs, fit_errors,
                                         Rounding(start, tolerance, stored_values, budget), Band(0, 0), 1.0)
    assert step <= start / 4  # the rounding noise goes as the step
    assert np.sqrt(np.mean(errors ** 2)) <= budget and largest <= tolerance
    assert np.sqrt(np.mean(quantisation_change(spline, 2 * step, dirs) ** 2)) > budget  # halved no further than needed


def test_a_whole_globe_samples_its_lattice_by_ducc0_when_installed(model, monkeypatch):
    """A banded fit reads a copy of the model whose lattices ducc0 computes (each group
    of rows once for the bands that share it); the caller's model keeps its engine, and
    GEOIDSPLINE_LATTICE_ENGINE, when set, decides."""
    pytest.importorskip("ducc0")
    from geoidspline.api.banded import global_lattice_engine

    monkeypatch.delenv("GEOIDSPLINE_LATTICE_ENGINE", raising=False)
    assert model.lattice_engine == "exact"
    fast = global_lattice_engine(model)
    assert fast.lattice_engine == "sht" and model.lattice_engine == "exact" and fast.model is model.model
    region = Region(-10.0, -180.0, 10.0, 180.0)
    assert np.abs(fast.nodes(region, 2.5).undulation - model.nodes(region, 2.5).undulation).max() < 1e-9
    monkeypatch.setenv("GEOIDSPLINE_LATTICE_ENGINE", "exact")
    assert global_lattice_engine(model) is model


def test_bands_are_committed_in_order_behind_the_fit_and_a_failed_fit_keeps_the_committed():
    from geoidspline.api.banded import _commit_behind

    events = []

    def fitted(fail_after=None):
        for band in range(4):
            if band == fail_after:
                raise FitError(f"band {band} failed")
            events.append(("fitted", band))
            yield band, f"result {band}"

    def commit(band, result):
        assert result == f"result {band}"
        events.append(("committed", band))

    _commit_behind(fitted(), commit, lambda: events.append(("counted",)))
    committed = [e[1] for e in events if e[0] == "committed"]
    assert committed == [0, 1, 2, 3] and events.count(("counted",)) == 4
    # band b is committed before band b + 2 is fitted (one waits at most)
    for band in range(2, 4):
        assert events.index(("committed", band - 2)) < events.index(("fitted", band))
    events.clear()
    with pytest.raises(FitError, match="band 2 failed"):
        _commit_behind(fitted(fail_after=2), commit, lambda: None)
    assert [e[1] for e in events if e[0] == "committed"] == [0, 1]  # band 1's commit completed all the same

    def broken(band, result):
        if band == 1:
            raise StoreError("disk full")

    with pytest.raises(StoreError, match="disk full"):
        _commit_behind(fitted(), broken, lambda: None)


def test_a_directions_band_is_its_storage_tiles_slab_on_and_between_slab_edges():
    """The slab of a direction (from ``z`` alone) is the ``z`` index of its storage tile,
    for directions on slab edges, at the poles and between."""
    from geoidspline.bspline.keys import unpack_keys
    from geoidspline.bspline.level import tiles_of_directions
    from geoidspline.fitting.bands import band_of_directions
    from geoidspline.sphere.coordinates import directions

    tile = 0.05
    rng = np.random.default_rng(8)
    lat = np.concatenate([rng.uniform(-90, 90, 5000), [-90.0, 90.0, 0.0],
                          np.degrees(np.arcsin(np.arange(-20, 21) * tile))])  # z on the slab edges
    dirs = directions(lat, rng.uniform(-180, 180, lat.size))
    slabs = band_of_directions(dirs, tile)
    np.testing.assert_array_equal(slabs, unpack_keys(tiles_of_directions(dirs, tile))[:, 2])
    assert slabs.min() == -20 and slabs.max() == 20  # the poles' own slabs


def test_a_bands_node_errors_are_the_stored_splines_bit_for_bit_with_many_nodes():
    """Above the evaluation's ordering threshold (20,000 points) the band sorts its nodes
    once for every rounding it measures: the node errors it returns are, bit for bit,
    the fit's minus its stored change evaluated at the nodes as they come."""
    from geoidspline.bspline.level import LevelSpline
    from geoidspline.fitting.bands import Rounding, band_step
    from geoidspline.hierarchy.ambient import AmbientSpline
    from geoidspline.store.codec import stored_values

    rng = np.random.default_rng(9)
    h, order, start, tolerance = 0.05, 4, 0.02, 0.1
    count = 30_000
    dirs, spline, owned = _random_band_spline(rng, (25, 35), count, h, order)  # no edge
    fit_errors = rng.uniform(-0.03, 0.03, count)
    _, stored, errors, largest = band_step(spline, owned, dirs, fit_errors,
                                           Rounding(start, tolerance, stored_values), Band(0, 0), 1.0)
    lv, kept = spline.levels[0], stored.levels[0].coefficients
    change = AmbientSpline([LevelSpline(0, h, order, lv.keys[owned[0]], kept[owned[0]] - lv.coefficients[owned[0]])])
    np.testing.assert_array_equal(errors, fit_errors - change.evaluate_points(dirs, any_batch=True))
    assert np.abs(errors - fit_errors).max() > 0.0 and largest <= tolerance


def test_a_step_plainly_too_noisy_is_halved_on_its_estimate_with_the_same_result(monkeypatch):
    """A band with many nodes estimates each step's rounding noise on every
    ``SCREEN_STRIDE``-th node first: a step whose estimate is plainly over the RMS
    budget is halved without measuring every node, and the band ends with the step,
    stored values and node errors of measuring them all."""
    from geoidspline.fitting import bands
    from geoidspline.hierarchy.ambient import AmbientSpline
    from geoidspline.store.codec import quantisation_change, stored_values

    rng = np.random.default_rng(10)
    h, order, start, tolerance = 0.05, 4, 0.2, 0.15
    dirs, spline, owned = _random_band_spline(rng, (25, 35), 4000, h, order)  # no edge
    fit_errors = rng.uniform(-0.002, 0.002, dirs.shape[0])
    budget = 0.3 * float(np.sqrt(np.mean(quantisation_change(spline, start, dirs) ** 2)))
    rounding = bands.Rounding(start, tolerance, stored_values, budget)
    measured_all = []
    evaluate = AmbientSpline.evaluate_points

    def counted(self, points, *args, **kwargs):
        measured_all.append(np.asarray(points).shape[0] == dirs.shape[0])
        return evaluate(self, points, *args, **kwargs)

    monkeypatch.setattr(AmbientSpline, "evaluate_points", counted)
    exact = bands.band_step(spline, owned, dirs, fit_errors, rounding, bands.Band(0, 0), 1.0)
    exact_count = sum(measured_all)
    monkeypatch.setattr(bands, "SCREEN_NODES_MIN", 1000)
    monkeypatch.setattr(bands, "SCREEN_STRIDE", 4)
    measured_all.clear()
    screened = bands.band_step(spline, owned, dirs, fit_errors, rounding, bands.Band(0, 0), 1.0)
    assert exact[0] <= start / 4 and screened[0] == exact[0]  # halved twice or more, to the same step
    assert sum(measured_all) == exact_count - 1  # the first step not measured node by node
    np.testing.assert_array_equal(screened[1].levels[0].coefficients, exact[1].levels[0].coefficients)
    np.testing.assert_array_equal(screened[2], exact[2])
    assert screened[3] == exact[3] and np.sqrt(np.mean(screened[2] ** 2)) <= budget
