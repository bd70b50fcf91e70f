"""Error bounds from what a store measured when it was written (its manifest's per-tile
check-point and node errors), near any point.

Latitudes and longitudes are geodetic degrees, errors metres; scalars give scalars,
arrays broadcast, NaN gives NaN. The functions take a store
(:class:`geoidspline.store.TileStore`, whose :meth:`~geoidspline.store.TileStore.error_bound`
calls :func:`tile_error_bound`).
"""

from __future__ import annotations

import functools
import math

import numpy as np

from ..hierarchy.derived import _shaped
from ..sphere.coordinates import check_coordinates, directions

_TILE_OFFSET = 1 << 20

#: Safety factor of :func:`tile_error_bound` on the largest error measured near a point
#: (derivation and measurements: README, "--with-error"; benchmarks/README.md, "Error
#: bound").
ERROR_BOUND_FACTOR = 1.5


def _tile_codes(tiles):
    """One int64 per integer tile triple (M, 3) (|index| < 2**20)."""
    tiles = np.asarray(tiles, dtype=np.int64).reshape(-1, 3)
    shifted = tiles + _TILE_OFFSET
    return (shifted[:, 0] << 42) | (shifted[:, 1] << 21) | shifted[:, 2]


def _figure(*values):
    """The largest of the per-tile figures that were measured (None: not measured)."""
    known = [float(v) for v in values if v is not None and math.isfinite(float(v))]
    return max(known) if known else math.nan


@functools.lru_cache(maxsize=8)
def _tile_table_cached(key):
    tiles, figures, excess = key
    codes = _tile_codes(np.array(tiles, dtype=np.int64).reshape(-1, 3))
    order = np.argsort(codes)
    return codes[order], np.array(figures, dtype=np.float64)[order], np.array(excess, dtype=np.float64)[order]


def _tile_table(manifest):
    """Sorted tile codes; each tile's largest measured error (the maximum of its
    check-point and node errors, NaN for a tile with neither); and by how much its
    check-point maximum exceeds its node maximum (0 when not, NaN when unknown)."""
    tiles = []
    figures = []
    excess = []
    for entry in manifest["tiles"]:
        tiles.extend(int(v) for v in entry["tile"])
        check, node = entry.get("max_error_m"), entry.get("node_max_error_m")
        figures.append(_figure(check, node))
        excess.append(max(0.0, float(check) - float(node)) if check is not None and node is not None else math.nan)
    return _tile_table_cached((tuple(tiles), tuple(figures), tuple(excess)))


def _store_figure(manifest):
    """The store's largest measured error (check points and nodes), metres."""
    acc = manifest.get("accuracy", {})
    return _figure(acc.get("max_error_m"), acc.get("node_max_error_m"))


def _store_excess(manifest):
    acc = manifest.get("accuracy", {})
    check, node = acc.get("max_error_m"), acc.get("node_max_error_m")
    return max(0.0, float(check) - float(node)) if check is not None and node is not None else 0.0


def _nearby(store, latitude, longitude):
    """(largest measured error, largest check-over-node excess) over the tiles within
    reach of each point; flat arrays, NaN for NaN coordinates (see
    :func:`nearby_measured_error`)."""
    lat, lon = check_coordinates(latitude, longitude)
    lat_f, lon_f = lat.ravel(), lon.ravel()
    figure = np.full(lat_f.shape, np.nan)
    excess = np.full(lat_f.shape, np.nan)
    ok = np.isfinite(lat_f) & np.isfinite(lon_f)
    if not ok.any():
        return lat.shape, figure, excess
    manifest = store.manifest
    meta = manifest["spline"]
    size = float(meta["tile_size"])
    coarsest = max([float(meta["h0"])] + [float(lv["h"]) for lv in meta.get("levels", ())])
    reach = int(meta["order"]) * coarsest / 2.0
    codes, figures, excesses = _tile_table(manifest)
    u = directions(lat_f[ok], lon_f[ok])
    lo = np.floor((u - reach) / size - 1e-9).astype(np.int64)
    hi = np.floor((u + reach) / size + 1e-9).astype(np.int64)
    span = int((hi - lo).max()) + 1
    best = np.full(u.shape[0], np.nan)
    most = np.full(u.shape[0], np.nan)
    if codes.size:
        for offset in np.ndindex(span, span, span):
            tile = lo + np.array(offset)
            query = _tile_codes(tile)
            pos = np.minimum(np.searchsorted(codes, query), codes.size - 1)
            found = np.all(tile <= hi, axis=1) & (codes[pos] == query)
            best = np.fmax(best, np.where(found, figures[pos], np.nan))
            most = np.fmax(most, np.where(found, excesses[pos], np.nan))
    best[np.isnan(best)] = _store_figure(manifest)
    most[np.isnan(most)] = _store_excess(manifest)
    figure[ok] = best
    excess[ok] = most
    return lat.shape, figure, excess


def nearby_measured_error(store, latitude, longitude):
    """The largest error measured when the store was written near each point (metres).

    The spline at a point depends only on the B-splines within ``reach = order · h0 / 2``
    of its direction u (per axis, h0 the coarsest spacing), and those were fitted to the
    data of the tiles meeting the cube ``u ± reach``. This is the largest per-tile
    figure (the maximum of the tile's check-point error ``max_error_m`` and node error
    ``node_max_error_m``) over those tiles; where none of them has figures (a tile
    rewritten by an update has node figures only; one holding coefficients only, none),
    the store's overall maximum. NaN for a NaN coordinate. Not restricted to the
    coverage: :func:`tile_error_bound` is.
    """
    shape, figure, _ = _nearby(store, latitude, longitude)
    return _shaped(figure, shape)


def grid_interpolation_uncertainty(store, latitude, longitude):
    """An estimate of how far the field a grid source samples may be from any smooth
    interpolation of its nodes, near each point (metres; 0 for a model source).

    A grid store's check points compare it with the grid's bicubic interpolation at the
    cell centres, the points farthest from the nodes. Where its check-point maximum
    exceeds its node maximum, the excess is how much two interpolants through the same
    nodes (within the fit's misfit) differ between them: the grid itself does not say
    which is right, so the field between the nodes is at least that uncertain. This is
    the largest such excess, ``max(0, max_error_m − node_max_error_m)``, over the tiles
    within reach of the point (as in :func:`nearby_measured_error`).
    """
    shape, _, excess = _nearby(store, latitude, longitude)
    if store.manifest.get("provenance", {}).get("kind") != "grid":
        excess = np.where(np.isnan(excess), np.nan, 0.0)
    return _shaped(excess, shape)


def tile_error_bound(store, latitude, longitude):
    """A bound on the store's error |N − truth| at each point (metres).

    ``ERROR_BOUND_FACTOR`` times the largest error measured near the point when the
    store was written (:func:`nearby_measured_error`: check points and data nodes of
    the tiles whose data fitted the B-splines non-zero at the point), plus for a grid
    source the grid's own interpolation uncertainty there
    (:func:`grid_interpolation_uncertainty`). The truth is the source: the exact
    synthesis of a model; for a grid its nodes and its interpolation between them.
    Measured on real stores, the bound held at more than 99.9 % of random points inside
    the coverage (README, "--with-error", has the derivation; benchmarks/README.md the
    measurements); it is a statistical bound, not a proof.

    NaN for a point outside the store's coverage (nothing was measured there: see
    :meth:`~geoidspline.store.TileStore.covers`) and for a NaN coordinate.
    """
    shape, figure, excess = _nearby(store, latitude, longitude)
    if store.manifest.get("provenance", {}).get("kind") != "grid":
        excess = np.zeros_like(excess)
    covered = np.asarray(store.covers(latitude, longitude), dtype=bool).reshape(-1)
    bound = np.where(covered, ERROR_BOUND_FACTOR * figure + excess, np.nan)
    return _shaped(bound, shape)
