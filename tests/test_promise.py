"""Every fit keeps its promise (issue 21): the tolerance the user typed holds in the
store read back, or the fit is refused before the work, naming the figure."""

import dataclasses
import json
import math

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

import geoidspline
from geoidspline.api import run_fit
from geoidspline.bspline.level import LevelSpline
from geoidspline.cli.fit import main as fit_main
from geoidspline.errors import FitError
from geoidspline.fitting.choose import choose_parameters
from geoidspline.fitting.driver import complete_at_finest_level
from geoidspline.fitting.hierarchical import finest_admissible_level, fit_hierarchical
from geoidspline.fitting.sites import DataNodes
from geoidspline.sphere.coverage import Coverage
from geoidspline.fitting.memory import check_plan
from geoidspline.fitting.parameters import FitParameters, quantisation_reserve
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.sources.base import NodeSample, Provenance
from geoidspline.sources.formats import write_gtx
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.coordinates import directions
from geoidspline.sphere.region import Region
from geoidspline.store.codec import node_safe_step, quantisation_change

from types import SimpleNamespace


def model(degree):
    """A stand-in for a spherical-harmonic source: what the parameter rule reads of one."""
    return SimpleNamespace(provenance=SimpleNamespace(kind="harmonic", source="m", model="m"), max_degree=degree,
                           lattice_step=lambda s=None: s)


def invoke(args):
    return CliRunner().invoke(fit_main, [str(a) for a in args])


def regional_grid(step=0.5, south=-10.0, north=10.0, west=0.0, east=20.0) -> GeoidGrid:
    """A regional grid (part of the globe) of a field with a narrow peak at (2N, 12E)."""
    lat = np.arange(south, north + step / 2, step)
    lon = np.arange(west, east + step / 2, step)
    la, lo = np.meshgrid(lat, lon, indexing="ij")
    values = (20 * np.sin(np.radians(2 * la)) * np.cos(np.radians(lo)) + 5
              + 1.5 * np.exp(-((la - 2) ** 2 + (lo - 12) ** 2) / 0.5))
    values = values.astype(np.float32).astype(np.float64)
    return GeoidGrid(lat, lon, values, Provenance(source="regional", model="synthetic", kind="grid"))


def read_back_node_max(store_path, grid: GeoidGrid, region: Region) -> float:
    """The store's largest |error| at the grid's nodes in the region, read back from disk
    and compared with the grid's own values (numpy, independent of the fit)."""
    store = geoidspline.open_store(store_path, lazy=False)
    la, lo = np.meshgrid(grid.latitude, grid.longitude, indexing="ij")
    inside = region.contains(la, lo)
    return float(np.abs(store.undulation(la[inside], lo[inside]) - grid.values[inside]).max())


# -- one meaning of tolerance ---------------------------------------------------------


def test_a_model_tolerance_is_the_one_typed_with_the_measured_level_0():
    """No hidden 0.8 T: the nodes are fitted to T; level 0's spacing is the one the
    measured fits were made with (h0 0.0045-0.0046 for EGM96 at 2 mm); the whole globe,
    fitted band by band, keeps T with level 0 alone (a finer h0: 0.00416)."""
    choice = choose_parameters(model(360), 0.002, Region(-80, -180, 80, 180))
    assert choice.parameters.tolerance_m == 0.002
    assert 0.0045 <= choice.parameters.h0 <= 0.0046
    assert 0.0041 <= choose_parameters(model(360), 0.002).parameters.h0 <= 0.0042
    assert "0.8" not in choice.reasons["tolerance_m"] and "check points" in choice.reasons["tolerance_m"]
    expert = {"method": "interpolation", "order": 6, "h0": 0.0045, "max_level": 1}  # README's, no sample spacing
    assert choose_parameters(model(360), 0.0015, given=expert).parameters.tolerance_m == 0.0015


def test_a_regional_grid_defaults_to_its_own_extent(tmp_path):
    grid = regional_grid()
    path = write_gtx(tmp_path / "regional.gtx", grid)
    result = invoke([path, "--store", tmp_path / "s", "--tolerance", 0.05, "--json", "-q"])
    assert result.exit_code == 0, result.output
    data = json.loads(result.stdout)
    assert data["region"] == [-10.0, 0.0, 10.0, 20.0]
    assert data["promise"]["kept"] is True and data["promise"]["node_max_m"] <= 0.05


# -- the store keeps the promise --------------------------------------------------------


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31), st.floats(1e-4, 1.0), st.integers(1, 4))
def test_the_stored_spline_keeps_the_tolerance_the_fit_left_room_for(seed, tolerance, levels):
    """A fit within ``node_target_m`` (T less the quantisation reserve) is stored within T
    at every node, whatever its coefficients: the step halves down to one whose proven
    bound fits in the room left."""
    rng = np.random.default_rng(seed)
    lat, lon = rng.uniform(-30, 30, 400), rng.uniform(-30, 30, 400)
    dirs = directions(lat, lon)
    parts = []
    for lv in range(levels):
        h = 0.2 / 2 ** lv
        cells = np.unique(np.floor(dirs / h).astype(np.int64), axis=0)
        from geoidspline.bspline.keys import touching_keys

        keys = touching_keys(cells, 4)  # the cells (M, 3) themselves: packed keys gave a spline of 0
        parts.append(LevelSpline(lv, h, 4, keys, rng.normal(0, 30.0 / (lv + 1), keys.size)))
    spline = AmbientSpline(parts)
    room = quantisation_reserve(tolerance, levels)
    errors = rng.uniform(-1, 1, lat.size) * (tolerance - room)
    errors[rng.integers(lat.size)] = np.copysign(tolerance - room, errors[0])  # one node at the target
    step, stored = node_safe_step(spline, dirs, errors, tolerance)
    np.testing.assert_allclose(stored, errors - quantisation_change(spline, step, dirs), atol=1e-12)
    assert np.abs(stored).max() <= tolerance
    assert step >= 1e-6 and math.isclose(step / 1e-6, round(step / 1e-6), abs_tol=1e-6)


def test_the_stored_spline_keeps_the_cell_centres_the_fit_kept():
    """Points between the nodes with an interval each (a grid's cell centres): the step
    is also halved until the quantised spline is as far inside (within the tolerance of)
    every interval as the fit left it; chosen against the nodes alone it is not."""
    rng = np.random.default_rng(3)
    lat, lon = rng.uniform(-20, 20, 300), rng.uniform(-20, 20, 300)
    node_dirs = directions(lat, lon)
    from geoidspline.bspline.keys import touching_keys

    keys = touching_keys(np.unique(np.floor(node_dirs / 0.05).astype(np.int64), axis=0), 4)
    spline = AmbientSpline([LevelSpline(0, 0.05, 4, keys, rng.normal(0, 20.0, keys.size))])
    tolerance = 0.1
    centre_dirs = directions(rng.uniform(-20, 20, 2000), rng.uniform(-20, 20, 2000))
    fitted = spline.evaluate_points(centre_dirs)
    # wide intervals, and 50 single values 99.5 mm above the fit (its figure there, under T)
    low, high = fitted - 1.0, fitted + 1.0
    low[:50] = high[:50] = fitted[:50] + 0.0995
    errors = np.zeros(lat.size)
    nodes_step, _ = node_safe_step(spline, node_dirs, errors, tolerance)
    step, stored = node_safe_step(spline, node_dirs, errors, tolerance, between=(centre_dirs, low, high))
    moved = lambda s: fitted + quantisation_change(spline, s, centre_dirs)  # noqa: E731
    outside = lambda v: np.maximum(np.maximum(low - v, v - high), 0.0)  # noqa: E731
    assert outside(moved(nodes_step)).max() > tolerance  # the nodes' step moves a centre out
    assert step < nodes_step and outside(moved(step)).max() <= tolerance
    np.testing.assert_allclose(stored, -quantisation_change(spline, step, node_dirs), atol=1e-12)


def test_a_fit_aims_a_little_under_its_tolerance_for_the_rounding():
    p = FitParameters(tolerance_m=0.5, max_level=4)
    assert p.node_target_m == pytest.approx(0.495)
    assert FitParameters(tolerance_m=1e-5, max_level=3).node_target_m == pytest.approx(8e-6)  # 4 x 0.5 um kept


def test_a_tolerance_finer_than_the_store_can_keep_is_refused_up_front(synthetic_gtx, tmp_path):
    result = invoke([synthetic_gtx, "--store", tmp_path / "s", "--tolerance", 2e-6, "--h0", 0.2, "--max-level", 3,
                     "-q"])
    assert result.exit_code == 1, result.output
    assert "ERROR: --tolerance 2e-06 m is finer than a store of 4 levels can promise: 4e-06 m" in result.stderr
    assert not (tmp_path / "s").exists()


# -- kept or refused --------------------------------------------------------------------


@pytest.fixture(scope="module")
def peak_fit(tmp_path_factory):
    """The regional grid fitted with nothing but the tolerance (1 mm): the narrow peak
    needs the finest level the 0.5° nodes allow; the store written and read back."""
    base = tmp_path_factory.mktemp("peak")
    grid = regional_grid()
    path = write_gtx(base / "regional.gtx", grid)
    run = run_fit(path, base / "store", tolerance_m=0.001)
    return grid, run, base / "store"


def test_a_hierarchical_fit_takes_its_last_bad_nodes_at_the_finest_admissible_level(peak_fit):
    grid, run, store = peak_fit
    assert run.promise["kept"], run.promise
    assert run.result.converged
    assert read_back_node_max(store, grid, run.region) <= 0.001
    assert run.promise["node_max_m"] == pytest.approx(read_back_node_max(store, grid, run.region), abs=1e-9)


def test_the_cell_centre_figure_is_the_distance_from_the_interpolants_interval(peak_fit):
    """Reported in the manifest and the summary: the largest distance of the store, at
    the centres of the grid's cells, from the interval its bilinear and bicubic
    interpolants span there (computed here again from the store read back)."""
    grid, run, store = peak_fit
    lat = grid.latitude[:-1] + 0.25
    lon = grid.longitude[:-1] + 0.25
    la, lo = (a.ravel() for a in np.meshgrid(lat, lon, indexing="ij"))
    values = geoidspline.open_store(store, lazy=False).undulation(la, lo)
    cubic, linear = grid.undulation(la, lo), grid.undulation(la, lo, method="bilinear")
    outside = np.maximum(np.maximum(np.minimum(cubic, linear) - values, values - np.maximum(cubic, linear)), 0)
    manifest = json.loads((store / "manifest.json").read_text())
    assert manifest["accuracy"]["cell_centre_max_m"] == pytest.approx(outside.max(), rel=1e-9, abs=1e-12)
    assert run.promise["cell_centre_max_m"] == manifest["accuracy"]["cell_centre_max_m"]


def _noisy_grid_at_one_centimetre():
    """(grid, region, sample, nodes, params): a 0.25° grid with ±5 cm of noise on its
    nodes, fitted at 1 cm (hierarchical, level 4 the finest admissible), whose fits down
    to level 3 leave nodes and cell centres for the completion passes."""
    grid = regional_grid(step=0.25, south=-4, north=8, west=6, east=18)
    values = grid.values + np.random.default_rng(5).uniform(-0.05, 0.05, grid.values.shape)
    grid = GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance)
    region = Region(-2.0, 8.0, 6.0, 16.0)
    sample = grid.nodes(region.expanded(1.0))
    nodes = DataNodes.from_sample(sample, region)
    params = FitParameters(h0=0.05, max_level=4, tolerance_m=0.01, refinement="hierarchical")
    return grid, region, sample, nodes, params


def test_the_completion_passes_take_what_the_hierarchical_refinement_left():
    """A hierarchical fit that stops with nodes above the tolerance one level before the
    finest admissible one (here: refined to level 3 only, on nodes with ±5 cm of noise)
    goes on by local passes at that level (4, the finest at least half the 0.25° spacing):
    three passes take the 425 nodes above 1 cm to none, and the errors reported are the
    spline's own at the nodes."""
    grid, region, sample, nodes, params = _noisy_grid_at_one_centimetre()
    assert finest_admissible_level(params, nodes) == 4
    first = fit_hierarchical(nodes, Coverage.from_sample(sample, region), region,
                             dataclasses.replace(params, max_level=3))
    assert not first.converged and first.levels[-1].nodes_above_tolerance == 425
    done = complete_at_finest_level(first, nodes, region, params)
    passes = done.levels[len(first.levels):]
    assert done.converged and done.node_max_error_m <= params.node_target_m
    assert [p.level for p in passes] == [4, 4, 4] and passes[-1].nodes_above_tolerance == 0
    assert passes[-1].coefficients == done.spline.coefficient_count > first.spline.coefficient_count
    assert [lv.level for lv in done.spline.levels] == [lv.level for lv in first.spline.levels] + [4]
    la, lo = np.meshgrid(grid.latitude, grid.longitude, indexing="ij")
    inside = region.contains(la, lo)
    err = np.abs(grid.values[inside] - done.spline.undulation(la[inside], lo[inside]))
    assert err.max() == pytest.approx(done.node_max_error_m, rel=1e-9)


def test_the_completion_passes_take_the_cell_centres_the_refinement_left_outside():
    """The noisy grid fitted with its cell centres down to level 3 leaves nodes above 1 cm
    and centres up to 2.3 cm outside the interpolants' interval; local passes at level 4
    on the nodes alone meet every node and leave the centres there (2.4 cm), passes
    that take the centres as sites too (valued where the spline enters its interval)
    bring nodes and centres within the target."""
    from geoidspline.fitting.cell_centres import cell_centre_nodes
    from geoidspline.fitting.hierarchical import centre_reach_deg

    grid, region, sample, nodes, params = _noisy_grid_at_one_centimetre()
    centres = cell_centre_nodes(sample, region, centre_reach_deg(params, nodes))
    first = fit_hierarchical(nodes, Coverage.from_sample(sample, region), region,
                             dataclasses.replace(params, max_level=3), centres=centres)
    assert not first.converged and outside_interpolants(first.spline, grid, region).max() > 2 * params.node_target_m
    nodes_only = complete_at_finest_level(first, nodes, region, params)
    assert nodes_only.converged
    assert outside_interpolants(nodes_only.spline, grid, region).max() > 2 * params.node_target_m
    done = complete_at_finest_level(first, nodes, region, params, centres=centres)
    assert done.converged and done.node_max_error_m <= params.node_target_m
    assert outside_interpolants(done.spline, grid, region).max() <= params.node_target_m
    assert all(p.level == 4 for p in done.levels[len(first.levels):])


def test_a_fit_beyond_the_memory_allowed_is_refused_before_the_work_naming_the_figure(tmp_path):
    params = choose_parameters(model(360), 0.002).parameters
    # the globe is fitted band by band: the largest band is what must fit
    with pytest.raises(FitError, match=r"needs at least [\d.]+ GB .*largest band.*level-0 coefficients.*0.1 GB are "
                                       r"allowed"):
        check_plan(model(360), Region(-90, -180, 90, 180), params, 1e8)
    assert check_plan(model(360), Region(-90, -180, 90, 180), params, 1e12).bytes > 1e8
    with pytest.raises(FitError, match=r"needs at least [\d.]+ GB .*level-0 coefficients.*1 GB are allowed"):
        check_plan(model(360), Region(-80, -180, 80, 180), params, 1e9)  # not the globe: whole


def test_a_model_fit_beyond_max_memory_is_refused_before_anything_is_written(toy24, tmp_path):
    from geoidspline.cli._common import for_the_command_line

    with pytest.raises(FitError, match=r"needs at least [\d.]+ GB") as caught:
        geoidspline.api.fit(toy24, tmp_path / "s", tolerance_m=1e-4, max_memory_gb=0.01)
    assert not (tmp_path / "s").exists()
    assert "give --max-memory " in for_the_command_line(str(caught.value))


def test_an_expert_max_level_that_stops_early_is_named_but_never_advised_when_data_limited(tmp_path):
    grid = regional_grid()
    path = write_gtx(tmp_path / "regional.gtx", grid)
    result = invoke([path, "--store", tmp_path / "s", "--tolerance", 0.001, "--h0", 0.1, "--max-level", 0,
                     "--refinement", "overlays", "--method", "least-squares", "--order", 4, "-q"])
    assert result.exit_code == 3, result.output
    assert "NOT kept" in result.stdout and "--max-level" in result.stdout


# -- between the nodes ----------------------------------------------------------------

CATMULL_ROM_AT_CENTRE = np.array([-1.0, 9.0, 9.0, -1.0]) / 16.0


def outside_interpolants(spline, grid: GeoidGrid, region: Region) -> np.ndarray:
    """How far ``spline`` lies, at each centre of the grid's cells in ``region``, outside the
    interval of the grid's bilinear (corner mean) and Catmull-Rom bicubic values there
    (numpy on the grid's values; cells whose 4 x 4 stencil is inside the grid)."""
    step = grid.latitude[1] - grid.latitude[0]
    lat, lon = grid.latitude[:-1] + step / 2, grid.longitude[:-1] + step / 2
    rows = np.flatnonzero(region.contains(lat, np.full(lat.size, (region.west + region.east) / 2)))
    cols = np.flatnonzero((lon >= region.west) & (lon <= region.east))
    rows, cols = rows[(rows >= 1) & (rows + 2 < grid.latitude.size)], cols[(cols >= 1) & (cols + 2 < lon.size + 1)]
    block = grid.values[(rows[:, None] + np.arange(-1, 3))[:, None, :, None],
                        (cols[:, None] + np.arange(-1, 3))[None, :, None, :]]
    cubic = np.einsum("abij,i,j->ab", block, CATMULL_ROM_AT_CENTRE, CATMULL_ROM_AT_CENTRE)
    linear = block[:, :, 1:3, 1:3].mean(axis=(2, 3))
    la, lo = np.meshgrid(lat[rows], lon[cols], indexing="ij")
    values = spline.undulation(la.ravel(), lo.ravel()).reshape(la.shape)
    return np.maximum(np.maximum(np.minimum(cubic, linear) - values, values - np.maximum(cubic, linear)), 0.0)


def test_a_grid_fit_stays_within_the_tolerance_of_its_interpolants_between_the_nodes():
    """Noisy nodes (±5 cm) fitted to 1 cm down to level 4 (h 0.72 x the 0.25° spacing):
    on the nodes alone the spline meets every node and swings 0.58 m off the interval of
    the grid's bilinear and bicubic interpolants between them; with the cell centres as
    sites on the levels finer than the nodes determine (and marking where they are
    outside), every centre is within the tolerance of it and every node still is within
    the tolerance."""
    from geoidspline.fitting.driver import fit_nodes

    grid = regional_grid(step=0.25, south=-4, north=8, west=6, east=18)
    values = grid.values + np.random.default_rng(5).uniform(-0.05, 0.05, grid.values.shape)
    grid = GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance)
    region = Region(-2.0, 8.0, 6.0, 16.0)
    sample = grid.nodes(region.expanded(1.0))
    params = FitParameters(h0=0.05, max_level=4, tolerance_m=0.01, refinement="hierarchical")
    nodes_only = fit_nodes(sample, region, params, cell_centres=False)
    assert nodes_only.node_max_error_m <= params.tolerance_m
    assert outside_interpolants(nodes_only.spline, grid, region).max() > 10 * params.tolerance_m
    kept = fit_nodes(sample, region, params, cell_centres=True)
    outside = outside_interpolants(kept.spline, grid, region)
    assert outside.size == 32 * 32
    assert kept.converged and outside.max() <= params.node_target_m
    la, lo = np.meshgrid(grid.latitude, grid.longitude, indexing="ij")
    inside = region.contains(la, lo)
    assert np.abs(kept.spline.undulation(la[inside], lo[inside]) - values[inside]).max() <= params.node_target_m


def test_a_grid_fit_takes_its_cell_centres_by_default():
    """`fit_source` (what `geoid-fit GRID --tolerance T` runs) keeps the same noisy grid's
    cell centres within the tolerance of its interpolants' interval, nothing asked."""
    from geoidspline.fitting.driver import fit_source

    grid = regional_grid(step=0.25, south=-4, north=8, west=6, east=18)
    values = grid.values + np.random.default_rng(5).uniform(-0.05, 0.05, grid.values.shape)
    grid = GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance)
    region = Region(-2.0, 8.0, 6.0, 16.0)
    params = FitParameters(h0=0.05, max_level=4, tolerance_m=0.01, refinement="hierarchical")
    result = fit_source(grid, region, params)
    assert result.node_max_error_m <= params.tolerance_m
    assert outside_interpolants(result.spline, grid, region).max() <= params.node_target_m


def test_the_exit_status_counts_the_cell_centres(tmp_path):
    """The promise holds at the nodes and the cell centres: the noisy grid fitted by
    overlays (which do not take the centres) meets every node but leaves centres 2.1 cm
    off the interpolants' interval at 1 cm: exit 3, naming the centres and the option;
    with the refinement chosen, exit 0 with both figures within 1 cm."""
    grid = regional_grid(step=0.25, south=-2, north=6, west=8, east=16)
    values = grid.values + np.random.default_rng(5).uniform(-0.05, 0.05, grid.values.shape)
    path = write_gtx(tmp_path / "noisy.gtx", GeoidGrid(grid.latitude, grid.longitude, values, grid.provenance))
    overlays = invoke([path, "--store", tmp_path / "o", "--tolerance", 0.01, "--refinement", "overlays", "-q"])
    assert overlays.exit_code == 3, overlays.output
    assert "at the nodes and cell centres NOT kept (cell centres up to 0.021" in overlays.stdout
    assert "overlays do not fit the cell centres, leave --refinement to be chosen" in overlays.stdout
    chosen = invoke([path, "--store", tmp_path / "c", "--tolerance", 0.01, "--json", "-q"])
    assert chosen.exit_code == 0, chosen.output
    promise = json.loads(chosen.stdout)["promise"]
    assert promise["kept"] is True and promise["node_max_m"] <= 0.01 and promise["cell_centre_max_m"] <= 0.01
