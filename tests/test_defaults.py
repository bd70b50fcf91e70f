"""Parameters chosen from the tolerance (geoidspline.fitting.choose) and honest progress
(geoidspline.fitting.progress): the rule, the overrides, the manifest, the stages."""

from __future__ import annotations

import io
import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from geoidspline.cli.fit import main as fit_main
from geoidspline.fitting import choose
from geoidspline.fitting.choose import MEASURED, choose_parameters, region_area
from geoidspline.fitting.progress import LineProgress, Progress, as_progress, for_terminal
from geoidspline.sphere.region import GLOBAL, Region
from geoidspline.store.format import load_manifest

#: The hand-tuned EGM96 store (README, benchmarks scenario egm96-mm).
HAND_TUNED_COEFFICIENTS = 5_586_925


def model(degree):
    """A stand-in for a spherical-harmonic source: what the rule reads of one."""
    return SimpleNamespace(provenance=SimpleNamespace(kind="harmonic", source="m", model="m"), max_degree=degree,
                           lattice_step=lambda s=None: s)


def level0_estimate(params, region=GLOBAL):
    return MEASURED[params.order].density * region_area(region) / params.h0**2


# -- the rule -----------------------------------------------------------------------


#: Nearly the globe, but not fitted band by band (the whole globe aims level 0 lower:
#: choose.BANDED_LEVEL0_OVER_TOLERANCE).
NEARLY_GLOBAL = Region(-89, -180, 89, 180)


def test_egm96_at_2_mm_takes_the_measured_quintic_route_with_fewer_coefficients():
    choice = choose_parameters(model(360), 0.002, NEARLY_GLOBAL)
    p = choice.parameters
    assert (p.method, p.order, p.max_level) == ("interpolation", 6, 1)
    assert p.tolerance_m == pytest.approx(0.002)  # the tolerance typed, at nodes and check points
    # h0 at or just above the hand-tuned 0.0045 (level 0 at 1.73 x the node tolerance)
    assert 0.0045 <= p.h0 <= 0.0046
    assert level0_estimate(p) <= HAND_TUNED_COEFFICIENTS
    assert p.sample_spacing_deg == pytest.approx(1 / 12)
    assert set(choice.reasons) == set(choose.CHOSEN_FIELDS)
    assert "measured" in choice.reasons["h0"] and "EGM96" in choice.reasons["h0"]


def test_spacing_scales_with_the_degree():
    h360 = choose_parameters(model(360), 0.001).parameters.h0
    h120 = choose_parameters(model(120), 0.001).parameters.h0
    assert h120 * 120 == pytest.approx(h360 * 360, rel=1e-2)  # h N constant, up to h0 rounded down to 3 digits


def test_a_region_changes_no_parameter_only_the_count():
    small = Region.from_bounds(-40, -80, -20, -60)
    assert choose_parameters(model(360), 0.002, small).parameters == \
        choose_parameters(model(360), 0.002, NEARLY_GLOBAL).parameters
    # the whole globe (fitted band by band) only aims level 0 lower
    globe = choose_parameters(model(360), 0.002).parameters
    assert globe.h0 < choose_parameters(model(360), 0.002, small).parameters.h0
    assert region_area(GLOBAL) == pytest.approx(4 * math.pi)
    assert region_area(small) == pytest.approx(math.radians(20) * (math.sin(math.radians(-20)) - math.sin(math.radians(-40))))


@settings(max_examples=40, deadline=None)
@given(st.floats(2e-4, 0.3), st.floats(1.05, 3.0), st.sampled_from([120, 360, 720]))
def test_a_looser_tolerance_never_costs_more_coefficients(tolerance, factor, degree):
    tight = choose_parameters(model(degree), tolerance).parameters
    loose = choose_parameters(model(degree), tolerance * factor).parameters
    assert level0_estimate(loose) <= level0_estimate(tight) * 1.001
    assert tight.tolerance_m < loose.tolerance_m


def test_the_order_is_the_one_with_fewer_coefficients():
    for tolerance in (0.0005, 0.002, 0.01, 0.05, 0.2):
        p = choose_parameters(model(360), tolerance).parameters
        other = choose_parameters(model(360), tolerance, given={"order": 10 - p.order}).parameters
        assert level0_estimate(p) <= level0_estimate(other)


def test_beyond_the_memory_cap_level_0_is_capped_and_overlays_go_deeper():
    half = Region.from_bounds(0, -180, 90, 180)  # not the whole globe: fitted in one piece
    choice = choose_parameters(model(360), 1e-5, half)
    assert level0_estimate(choice.parameters, half) <= choose.MAX_LEVEL0_COEFFICIENTS * 1.01
    assert choice.parameters.max_level == 2
    assert "capped" in choice.reasons["h0"]


def test_the_whole_globe_is_not_capped_it_is_fitted_band_by_band():
    capped = choose_parameters(model(360), 1e-5, Region.from_bounds(0, -180, 90, 180)).parameters
    choice = choose_parameters(model(360), 1e-5)
    p = choice.parameters
    assert p.h0 < capped.h0 and p.max_level == 1 and "capped" not in choice.reasons["h0"]
    assert level0_estimate(p) > choose.MAX_LEVEL0_COEFFICIENTS


def test_given_options_are_used_as_given_and_the_rest_chosen_around_them():
    choice = choose_parameters(model(360), 0.002, given={"order": 4})
    assert choice.parameters.order == 4 and choice.reasons["order"] == "given"
    assert choice.parameters.h0 < 0.0045  # cubics need a finer level 0 for the same error
    everything = {"method": "interpolation", "order": 6, "h0": 0.0045, "max_level": 1, "sample_spacing_deg": None}
    expert = choose_parameters(model(360), 0.0015, given=everything)
    assert expert.parameters.tolerance_m == 0.0015  # no margin taken off an expert's tolerance
    assert expert.parameters.sample_spacing_deg is None
    # the refinement is not one of the expert's five options: overlays unless asked
    assert all(r.startswith("given") for name, r in expert.reasons.items() if name != "refinement")
    assert expert.parameters.refinement == "overlays" and expert.reasons["refinement"].startswith("overlays")


def test_the_hierarchical_refinement_is_fitted_by_least_squares_even_for_a_model():
    """Quasi-interpolation makes an overlay base; the hierarchical basis (§5.3) is one
    least-squares problem over all levels, so asking for it chooses least squares (its
    quasi-interpolant, §5.3.1, needed far more coefficients: benchmarks/README.md),
    unless the quasi-interpolant is asked for too."""
    choice = choose_parameters(model(360), 0.002, given={"refinement": "hierarchical"})
    assert (choice.parameters.method, choice.parameters.refinement) == ("least-squares", "hierarchical")
    assert choice.reasons["refinement"] == "given" and "hierarchical" in choice.reasons["method"]
    both = choose_parameters(model(360), 0.002, given={"refinement": "hierarchical", "method": "interpolation"})
    assert (both.parameters.method, both.parameters.refinement) == ("interpolation", "hierarchical")
    assert both.reasons["method"] == "given"


def test_a_grid_is_fitted_as_the_andes_headline_down_to_its_resolution(synthetic_grid):
    choice = choose_parameters(synthetic_grid, 0.5, Region.from_bounds(-60, -90, 15, -30))
    p = choice.parameters
    assert (p.method, p.order, p.h0, p.tolerance_m) == ("least-squares", 4, 0.1, 0.5)
    # 2-degree nodes: h = 0.1 / 2**L must stay >= 0.5 x 0.0349 x mean cos(lat)
    assert p.max_level == 2
    assert "data spacing" in choice.reasons["max_level"]


def test_a_grid_takes_the_hierarchical_basis_a_model_and_an_experts_command_overlays(synthetic_grid):
    """The hierarchical basis (fewer coefficients, closer between the nodes) is the
    default for least squares; a model's quasi-interpolated level 0 is an overlay base;
    an expert's full command keeps the overlays it always had."""
    andes = choose_parameters(synthetic_grid, 0.5, Region.from_bounds(-60, -90, 15, -30))
    assert andes.parameters.refinement == "hierarchical"
    assert andes.reasons["refinement"] == choose.HIERARCHICAL_REASON
    assert choose_parameters(model(360), 0.002).parameters.refinement == "overlays"
    everything = {"method": "least-squares", "order": 4, "h0": 0.1, "max_level": 2, "sample_spacing_deg": None}
    expert = choose_parameters(synthetic_grid, 0.5, Region.from_bounds(-60, -90, 15, -30), given=everything)
    assert expert.parameters.refinement == "overlays" and "expert" in expert.reasons["refinement"]


def test_a_hierarchical_fit_beyond_the_memory_available_is_fitted_by_overlays(synthetic_grid, tmp_path,
                                                                               monkeypatch):
    """Rather than no result (the OOM killer), a hierarchical fit whose step would not
    fit in memory is fitted by overlays, and the store says so."""
    import geoidspline.fitting.hierarchical as fitting_hierarchical
    from geoidspline.api import build_store
    from geoidspline.fitting.parameters import FitParameters

    monkeypatch.setattr(fitting_hierarchical, "WHOLE_MAX_UNKNOWNS", 0)  # every step takes the memory check
    monkeypatch.setattr(fitting_hierarchical, "available_bytes", lambda: 1.0)
    params = FitParameters(tolerance_m=0.5, max_level=1, refinement="hierarchical")
    result, info = build_store(synthetic_grid, tmp_path / "s", Region.from_bounds(10, 20, 30, 40), params)
    assert result.parameters.refinement == "overlays" and result.levels[0].level == 0
    assert "GB are available" in result.refinement_fallback
    fit_section = load_manifest(tmp_path / "s")["fit"]
    assert fit_section["parameters"]["refinement"] == "overlays"
    assert fit_section["refinement_fallback"] == result.refinement_fallback


# -- the command line ---------------------------------------------------------------


def fit(args):
    return CliRunner().invoke(fit_main, [str(a) for a in args])


def test_geoid_fit_says_what_it_chose_and_why_and_records_it(synthetic_gtx, tmp_path):
    store = tmp_path / "s"
    result = fit([synthetic_gtx, "--region", 10, 20, 30, 40, "--tolerance", 1.0, "--h0", 0.1, "--store", store])
    assert result.exit_code == 0, result.output
    lines = result.stdout.splitlines()
    chosen = {line.split()[1]: line for line in lines if line.startswith(("chosen", "given"))}
    assert set(chosen) == set(choose.CHOSEN_FIELDS)
    assert chosen["h0"].startswith("given")  # given explicitly, even though it equals the default
    assert chosen["order"].startswith("chosen") and "Andes" in chosen["order"]
    manifest = load_manifest(store)
    assert manifest["fit"]["choices"]["tolerance_asked_m"] == 1.0
    assert manifest["fit"]["choices"]["reasons"]["h0"] == "given"
    assert manifest["fit"]["parameters"]["max_level"] == 2


def test_an_expert_option_overrides_the_choice(synthetic_gtx, tmp_path):
    result = fit([synthetic_gtx, "--region", 10, 20, 30, 40, "--tolerance", 1.0, "--max-level", 0,
                  "--store", tmp_path / "s", "--json", "-q"])
    assert result.exit_code == 0, result.output
    info = json.loads(result.stdout)
    assert info["choices"]["reasons"]["max_level"] == "given"
    assert [lv["level"] for lv in info["levels"]] == [0]


def test_a_model_file_fit_chooses_quasi_interpolation(toy24, tmp_path):
    from geoidspline import api

    store = api.fit(toy24, tmp_path / "s", region=(10, 20, 20, 30), tolerance_m=0.05, choose=True)
    manifest = load_manifest(tmp_path / "s")
    params = manifest["fit"]["parameters"]
    assert params["method"] == "interpolation" and params["order"] == 6
    assert params["tolerance_m"] == pytest.approx(0.05)  # the tolerance typed (issue 21)
    assert "measured" in manifest["fit"]["choices"]["reasons"]["h0"]
    assert store.info()["coefficients"] > 0


# -- progress -----------------------------------------------------------------------


def test_no_progress_on_a_non_terminal_without_v_and_stage_lines_with_v(synthetic_gtx, tmp_path):
    args = [synthetic_gtx, "--region", 10, 20, 30, 40, "--tolerance", 0.002, "--h0", 0.2, "--max-level", 1,
            "--refinement", "overlays"]  # the stages of overlays' levels
    quiet = fit([*args, "--store", tmp_path / "a"])
    assert quiet.exit_code in (0, 3), quiet.output
    assert "progress" not in quiet.stderr and "blocks" not in quiet.stderr
    silenced = fit([*args, "--store", tmp_path / "c", "-q", "-v"])
    assert silenced.stderr == ""
    verbose = fit([*args, "--store", tmp_path / "b", "-v"])
    assert verbose.exit_code in (0, 3), verbose.output
    stages = [line for line in verbose.stderr.splitlines() if line.startswith("progress: ")]
    names = {line[len("progress: "):].split(":")[0] for line in stages}
    assert {"read nodes", "level 0 blocks", "level 0 node errors", "level 1 blocks", "write"} <= names
    # every stage says its total when it starts and the count it reached when it ends
    start = next(line for line in stages if line.startswith("progress: level 0 blocks: "))
    total = int(start.split(": ")[2].split()[0].replace(",", ""))
    assert total >= 1
    unit = "block" if total == 1 else "blocks"
    assert f"progress: level 0 blocks: {total:,}/{total:,} {unit} in " in verbose.stderr


def test_line_progress_reports_count_and_eta():
    stream = io.StringIO()
    now = [0.0]
    progress = LineProgress(stream, interval=10.0, clock=lambda: now[0])
    with progress.stage("level 1 blocks", 40, "block") as advance:
        for _ in range(10):
            now[0] += 1.5
            advance(1)  # 15 s for 10 blocks: one line after 10 s
    lines = stream.getvalue().splitlines()
    assert lines[0] == "progress: level 1 blocks: 40 blocks"
    assert lines[1].startswith("progress: level 1 blocks: 7/40 blocks, 00:10 elapsed, ETA 00:")
    # 7 blocks in 10.5 s: 33 left at 1.5 s each
    assert lines[1].endswith("ETA 00:49")
    assert lines[-1] == "progress: level 1 blocks: 10/40 blocks in 15.0 s"


def test_line_progress_names_one_unit_in_the_singular_and_axes_in_the_plural():
    stream = io.StringIO()
    progress = LineProgress(stream, clock=lambda: 0.0)
    with progress.stage("write", 1, "store") as advance:
        advance(1)
    with progress.stage("prefilter", 3, "axis") as advance:
        advance(3)
    assert stream.getvalue().splitlines() == [
        "progress: write: 1 store", "progress: write: 1/1 store in 0.0 s",
        "progress: prefilter: 3 axes", "progress: prefilter: 3/3 axes in 0.0 s"]


def test_for_terminal_picks_bars_lines_or_nothing():
    class Tty(io.StringIO):
        def isatty(self):
            return True

    assert type(for_terminal(False, 0, Tty())).__name__ == "BarProgress"
    assert type(for_terminal(True, 2, Tty())) is Progress
    assert type(for_terminal(False, 1, io.StringIO())) is LineProgress
    assert type(for_terminal(False, 0, io.StringIO())) is Progress


def test_a_callable_still_counts_solved_blocks_only():
    counted = []
    progress = as_progress(counted.append)
    with progress.stage("synthesis", 5, "band") as advance:
        advance(1)
    with progress.stage("level 0 blocks", 3, "block") as advance:
        advance(1)
        advance(2)
    assert counted == [1, 2]
    with pytest.raises(TypeError):
        as_progress(3)


def test_stages_in_chunks_give_the_values_of_one_call(toy24, monkeypatch):
    from geoidspline.fitting import driver, interpolation
    from geoidspline.fitting.interpolation import sample_nodes

    region = Region.from_bounds(-90, -180, 90, 180)
    whole = toy24.nodes(region, spacing_deg=2.5)
    banded = sample_nodes(toy24, region, 2.5)
    np.testing.assert_array_equal(banded.latitude, whole.latitude)
    np.testing.assert_array_equal(banded.undulation, whole.undulation)

    from geoidspline.bspline.domain import active_cells
    from geoidspline.bspline.keys import touching_keys
    from geoidspline.bspline.level import LevelSpline

    keys = touching_keys(active_cells(0.3, GLOBAL), 4)
    level = LevelSpline(0, 0.3, 4, keys, np.random.default_rng(1).normal(size=keys.size))
    dirs = np.random.default_rng(2).normal(size=(10_000, 3))
    dirs /= np.linalg.norm(dirs, axis=1)[:, None]
    one = np.zeros(len(dirs))
    driver.subtract_level(one, level, dirs, Progress(), "x")
    monkeypatch.setattr(driver, "ERROR_CHUNK", 3_000)
    stream = io.StringIO()
    chunked = np.zeros(len(dirs))
    driver.subtract_level(chunked, level, dirs, LineProgress(stream), "x")
    np.testing.assert_array_equal(chunked, one)
    assert "x: 3/3 chunks" in stream.getvalue()  # 3000, 3000, 4000: no short last chunk
    monkeypatch.setattr(interpolation, "SYNTHESIS_STEPS", 7)
    np.testing.assert_array_equal(sample_nodes(toy24, region, 2.5).undulation, whole.undulation)


def test_bars_show_count_of_total():
    from geoidspline.fitting.progress import BarProgress

    stream = io.StringIO()
    with BarProgress(stream).stage("level 0 blocks", 3, "block") as advance:
        advance(1)
        advance(2)
    assert "level 0 blocks:   0%| | 0/3" in stream.getvalue().replace(" " * 10, " ")  # the total before the first block


def test_an_order_without_measured_convergence_needs_h0():
    """Orders 4 and 6 were measured; another order cannot have its h0 chosen: a FitError
    (a one-line ERROR on the command line) naming --h0, and with h0 given it is fitted."""
    from geoidspline.errors import FitError, GeoidSplineError

    assert 8 not in MEASURED
    with pytest.raises(FitError, match=r"order 8 .*give h0 \(--h0\) too") as err:
        choose_parameters(model(360), 0.002, given={"order": 8})
    assert isinstance(err.value, GeoidSplineError)
    choice = choose_parameters(model(360), 0.002, given={"order": 8, "h0": 0.02})
    assert (choice.parameters.order, choice.parameters.h0) == (8, 0.02)
    assert choice.reasons["order"] == choice.reasons["h0"] == "given"


# -- radial offsets: each refinement's own, and the parameters hold what is used ----------


def test_each_refinement_has_its_own_radial_offsets_and_an_explicit_choice_is_kept():
    from geoidspline.fitting.parameters import RADIAL_OFFSETS, FitParameters

    assert FitParameters().radial_offsets == RADIAL_OFFSETS["overlays"]
    assert len(RADIAL_OFFSETS["overlays"]) == 7 and max(RADIAL_OFFSETS["overlays"]) == 1.5
    assert FitParameters(refinement="hierarchical").radial_offsets == (0.0,)
    # an explicit choice is honoured, also when it equals another refinement's default
    overlays = RADIAL_OFFSETS["overlays"]
    assert FitParameters(refinement="hierarchical", radial_offsets=overlays).radial_offsets == overlays
    assert FitParameters(radial_offsets=[0, 0.5]).radial_offsets == (0.0, 0.5)


def test_a_manifest_from_before_0_3_refits_a_hierarchical_store_on_the_sphere():
    """Before 0.3.0 a hierarchical fit recorded the overlays' offsets but used its own."""
    from geoidspline.api.regional import _stored_parameters
    from geoidspline.fitting.parameters import RADIAL_OFFSETS, FitParameters

    def stored(software, refinement):
        params = FitParameters(refinement=refinement, radial_offsets=RADIAL_OFFSETS["overlays"]).as_dict()
        return _stored_parameters(SimpleNamespace(manifest={"software": software, "fit": {"parameters": params}},
                                                  path=None))

    assert stored("geoidspline 0.2.0", "hierarchical").radial_offsets == (0.0,)
    assert stored("geoidspline 0.3.0", "hierarchical").radial_offsets == RADIAL_OFFSETS["overlays"]
    assert stored("geoidspline 0.2.0", "overlays").radial_offsets == RADIAL_OFFSETS["overlays"]
