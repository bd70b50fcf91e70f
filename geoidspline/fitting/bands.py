"""A global fit of a model band by band: a bounded working set, each band on its own.

The globe is cut into bands made of slabs of storage tiles (thesis §4: "solve local
problems and put them together"): the band of slabs ``a .. b`` owns the B-splines whose
support centre has ``z`` in ``[a t, (b + 1) t)`` (``t`` = ``FitParameters.tile_size``,
the store's tile side on the unit sphere, so a band's coefficients are whole tile files)
and the data nodes and check points whose direction has ``z`` there (the tile a node's
statistics go to). Slabs of equal height hold equal areas of the sphere (Archimedes), but not equal
lattice rows: a slab near a pole spans many more latitudes, each a full circle of the
lattice. So a band is a run of consecutive slabs (:class:`Band`): one near the poles,
several near the equator, as many as the memory allows
(:func:`~geoidspline.fitting.memory.band_slabs`), so that fewer bands synthesise and
quasi-interpolate their margins again; a smaller ``tile_size`` gives smaller bands.

A band is fitted by :func:`fit_band`, a pure function of the source, the parameters and
the band's slabs, on the latitudes of its slabs grown by :func:`band_margin_deg`:

1. the lattice of the synthesis is sampled over those latitudes (and the lookups'
   stencil), level 0 of every B-spline there is quasi-interpolated
   (:func:`~geoidspline.fitting.interpolation.interpolate_level`): each coefficient
   depends on lattice values within a few cells only and the lookups give a point the
   whole lattice's bits, so a band's level-0 coefficients are bitwise those of one
   whole-globe computation;
2. its nodes are checked and overlays are fitted where nodes exceed the tolerance, by the
   overlay least squares of :func:`~geoidspline.fitting.driver.fit_nodes` in blocks
   (always tiled, so that a block's problem does not depend on how many unknowns a
   band holds);
3. the band keeps the coefficients it owns, and measures its own nodes and check
   points on the quantised spline it will store.

The blocks of an overlay level reach ``(block_cells + 2 margin_cells + order)`` cells
of their level around a coefficient: where a band's margin covers that reach for every
level (:func:`band_margin_deg` with ``overlay_reach=True``) the overlays are those of one
whole-globe fit too; the default margin covers level 0's support and the margin of one
overlay block, and the band decomposition (``tile_size``, and the slabs grouped,
which are a function of the parameters) is then part of the parameters: the same parameters give the same store bit for bit whichever process or
machine fits a band, in whichever order, across an interrupted and resumed fit.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from .._kernels.query import query_order
from ..bspline.domain import active_cells
from ..bspline.keys import pack_keys, touching_keys, unpack_keys
from ..bspline.level import LevelSpline, cube_of_support_centres, tiles_of_directions
from ..errors import FitError
from ..hierarchy.ambient import AmbientSpline
from ..sphere.coordinates import directions
from ..sphere.region import Region
from .interpolation import interpolate_level, lattice_spacing
from .parameters import FitParameters
from .progress import as_progress

__all__ = ["band_indices", "band_latitudes", "band_margin_deg", "fit_band", "BandResult", "uses_bands",
           "band_of_directions", "Rounding", "band_step", "Band"]


class Band(NamedTuple):
    """A band of the globe: the tile slabs ``first`` .. ``last`` (``z`` indices of the
    storage tiles, inclusive) whose B-splines, nodes and check points it owns; named
    by its first slab."""

    first: int
    last: int

    def owns(self, slabs) -> np.ndarray:
        """Whether each slab index of ``slabs`` is the band's."""
        slabs = np.asarray(slabs)
        return (slabs >= self.first) & (slabs <= self.last)

    def latitudes(self, tile_size: float) -> tuple[float, float]:
        """(south, north) latitudes (degrees) of the sphere's points in the band."""
        return band_latitudes(self.first, tile_size)[0], band_latitudes(self.last, tile_size)[1]


def uses_bands(params: FitParameters, region: Region) -> bool:
    """Whether a fit is made band by band: a model's quasi-interpolated level 0 with
    overlays, over the whole globe."""
    return (params.method == "interpolation" and params.refinement == "overlays"
            and region.south <= -90.0 and region.north >= 90.0 and region.longitude_span >= 360.0)


def band_indices(params: FitParameters) -> list[int]:
    """The tile slabs of the globe: every slab a B-spline touching the sphere can have
    its support centre in (centres lie within ``order h0`` of the sphere)."""
    reach = 1.0 + params.order * params.h0
    return list(range(math.floor(-reach / params.tile_size), math.floor(reach / params.tile_size) + 1))


def band_latitudes(band: int, tile_size: float) -> tuple[float, float]:
    """(south, north) latitudes (degrees) of the sphere's points in tile slab ``band``."""
    low = min(1.0, max(-1.0, band * tile_size))
    high = min(1.0, max(-1.0, (band + 1) * tile_size))
    return math.degrees(math.asin(low)), math.degrees(math.asin(high))


def band_of_directions(dirs, tile_size: float) -> np.ndarray:
    """The tile slab of each unit direction (M, 3): the ``z`` index of its storage tile
    (:func:`~geoidspline.bspline.level.tiles_of_directions`), from ``z`` alone (a polar
    band's 22 M nodes: no (M, 3) temporaries)."""
    return np.floor(np.asarray(dirs)[:, 2] / tile_size).astype(np.int64)


def band_margin_deg(params: FitParameters, overlay_reach: bool = False) -> float:
    """Latitudes (degrees) a band's fit reaches beyond its slab: level 0's support
    (so that every node of the slab sees all of its B-splines) and one overlay block's
    margin and support at level 1; with ``overlay_reach`` the reach of an overlay
    block's problem at every level (block, margins and support: its coefficients are
    then those of a whole-globe fit)."""
    support = params.order * params.h0 * math.sqrt(3.0)
    if overlay_reach:
        cells = params.block_cells + 2 * params.margin_cells + params.order
        reach = sum(cells * params.spacing(level) for level in range(1, params.max_level + 1))
    else:
        reach = (params.margin_cells + params.order) * params.spacing(1)
    return math.degrees(support + reach)


#: What the floating-point rounding of an evaluation can move a node's error by (metres):
#: a band's node errors after rounding are its fit's minus the spline of the rounding's
#: changes, which the store read back sums in another order (measured: 2e-16 m at 0.15 m).
EVALUATION_ROUNDING_M = 1e-9


class Rounding(NamedTuple):
    """How a store rounds a band's coefficients: ``round(values, step)`` gives the
    stored values; a band takes ``start_step`` halved as often as its own nodes need to
    stay within ``tolerance_m`` (steps nest: a coarser step's multiples are multiples of
    the finer ones)."""

    start_step: float
    tolerance_m: float
    round: object
    rms_m: float | None = None  # the stored spline's RMS error at the nodes at most (None: not checked)


@dataclass
class BandResult:
    """What a band's fit gives the store: the coefficients it owns (level, h, keys,
    coefficients), the step its tiles are rounded to, per tile the statistics of its
    nodes and check points on the rounded spline, and its part of the fit's account."""

    band: Band
    levels: list  # [(level, h, keys, coefficients)], owned B-splines only
    value_step_m: float | None  # the step the band's tiles are rounded to (None: not rounded)
    tile_stats: dict  # packed tile key -> (node errors, check errors) of the stored spline
    node_count: int
    node_max_error_m: float  # the stored spline's, at most (see :func:`band_step`)
    node_sum_squares: float
    fit_node_max_error_m: float  # the fit's, before rounding
    check_errors: np.ndarray  # truth - stored spline at the band's check points
    level_reports: list
    converged: bool
    data_limited: bool
    seconds: float
    sample_rows: int = 0  # lattice rows the band synthesised (its margin included)


def fit_band(source, params: FitParameters, band: Band, check_latitude, check_longitude,
             rounding: Rounding | None = None, margin_deg: float | None = None, executor=None,
             progress=None) -> BandResult:
    """Fit band ``band`` (:class:`Band`) of the globe (see the module's docstring).

    ``rounding``: how the store rounds the band's coefficients (:class:`Rounding`;
    default none), where the band measures its nodes and check points;
    ``check_latitude``/``check_longitude``: the whole fit's check points
    (degrees), of which the band measures those it owns by the exact synthesis.
    ``margin_deg``: how far the band's fit reaches beyond its slab (default
    :func:`band_margin_deg`). ``executor`` solves the overlay blocks (default: here).
    """
    from .check_points import exact_values
    from .driver import fit_nodes, finer_data_hint

    started = time.perf_counter()
    progress = as_progress(progress)
    margin = band_margin_deg(params) if margin_deg is None else float(margin_deg)
    band = Band(*band)
    south, north = band.latitudes(params.tile_size)
    reach = Region(max(-90.0, south - margin), -180.0, min(90.0, north + margin), 180.0)
    h = params.h0
    cells = active_cells(h, reach)
    if cells.size == 0:
        raise FitError(f"band {band}: no cells of spacing {h} meet the sphere over {reach.as_tuple()}")
    keys = touching_keys(cells, params.order)
    del cells
    spacing = lattice_spacing(source, h, params.sample_spacing_deg)
    coefficients, sample, lattice_points = interpolate_level(source, keys, h, params.order, spacing,
                                                             progress=progress)
    # thinning strides count rows of the whole lattice, not of the band's
    sample = dataclasses.replace(sample, first_row=round((float(sample.latitude[0]) + 90.0) / spacing))
    level0 = LevelSpline(0, h, params.order, keys, coefficients)
    result = fit_nodes(sample, reach, params, progress=progress, force_tiles=True, executor=executor,
                       first_level=(level0, time.perf_counter() - started, lattice_points),
                       finer_hint=finer_data_hint(source))
    rows = sample.latitude.size
    del sample, level0, keys, coefficients
    owned = [band.owns(cube_of_support_centres(lv.indices, lv.h, lv.order, params.tile_size)[:, 2])
             for lv in result.spline.levels]
    # the band's nodes and check points, on the spline as stored
    mine = band.owns(band_of_directions(result.node_directions, params.tile_size))
    node_dirs = result.node_directions[mine]
    fit_errors = result.node_errors[mine]
    step, stored, node_errors, node_bound = band_step(result.spline, owned, node_dirs, fit_errors, rounding, band,
                                                      params.tile_size)
    check_latitude = np.asarray(check_latitude, dtype=float)
    check_longitude = np.asarray(check_longitude, dtype=float)
    check_dirs = directions(check_latitude, check_longitude)
    own_checks = band.owns(band_of_directions(check_dirs, params.tile_size))
    check_lat, check_lon = check_latitude[own_checks], check_longitude[own_checks]
    truth = exact_values(source, check_lat, check_lon, progress)
    check_errors = truth - stored.undulation(check_lat, check_lon) if check_lat.size else np.empty(0)
    # the values as stored (the rounding's, corrected at the nodes: see band_step)
    owned_levels = [(lv.level, lv.h, lv.keys[m], lv.coefficients[m]) for lv, m in zip(stored.levels, owned)]
    tile_stats = _tile_stats(owned_levels, node_dirs, node_errors, check_dirs[own_checks], check_errors,
                             params)
    return BandResult(
        band=band, levels=owned_levels, value_step_m=step, tile_stats=tile_stats,
        node_count=int(node_errors.size), node_max_error_m=node_bound,
        node_sum_squares=float(np.sum(node_errors ** 2)),
        fit_node_max_error_m=float(np.abs(fit_errors).max()) if fit_errors.size else 0.0,
        check_errors=check_errors,
        level_reports=[vars(r) for r in result.levels], converged=bool(result.converged),
        data_limited=bool(result.data_limited), seconds=time.perf_counter() - started, sample_rows=rows,
    )


NUDGE_ROUNDS = 3
"""How many times a band corrects its rounding at the nodes that it takes over the
tolerance (:func:`_nudge`) before it halves its step (:func:`band_step`)."""

ROUNDING_RMS_OVER_TOLERANCE = 0.1
"""A banded model fit's stored spline keeps its RMS error at the nodes within this share
of the tolerance (:attr:`Rounding.rms_m`; or within 1.1 times the fit's own RMS where
that is larger): a step that keeps every node within the tolerance is still halved when
its rounding noise alone would lift the RMS above it. Issue 22 asks 0.1 mm RMS of a
1 mm global EGM2008 store; four times ``value_step``'s step kept the maxima but raised
the RMS of a 1 cm EGM2008 store from 0.86 to 1.82 mm and of the EGM96 2 mm store from
0.11 to 0.38 mm (benchmarks/README.md, "Store codec")."""

ROUNDING_RMS_GROWTH = 1.1
"""Where the fit's own RMS at the nodes is above ``rms_m``, the rounding may raise it by
this factor (:func:`band_step`)."""

NEIGHBOUR_STEPS_CHECKED = 3
"""How many of a neighbour band's possible steps (``start_step``, halved) a band's edge
nodes are checked against exactly (:func:`band_step`); finer ones are bounded."""


def band_step(spline: AmbientSpline, owned, node_dirs, fit_errors, rounding: Rounding | None,
              band: Band | None = None, tile_size: float | None = None):
    """(step, stored spline, node errors, largest node error at most) of a band.

    The band's own coefficients are rounded to ``rounding.start_step`` halved until its
    nodes stay within ``max(rounding.tolerance_m, the fit's own node max)`` (as
    :func:`geoidspline.store.codec.node_safe_step` does for a whole store). Its
    neighbours' coefficients that reach its nodes are rounded by them, to ``start_step``
    or a half, quarter, ... of it, chosen by their own nodes (so that bands are fitted
    in any order, or at once). Level 0's are the neighbours' own bit for bit (the
    quasi-interpolation's: see the module's docstring): a node is checked with them
    rounded to each of the first ``NEIGHBOUR_STEPS_CHECKED`` steps, exactly, and to a
    finer one by its bound (half that step times their B-splines' sum at the node); the
    overlays' in a band's margin are its own solution, not the neighbour's, and are
    bounded by ``start_step / 2`` times their B-splines' sum. The largest of these is
    the node's error for the test and for the largest error reported. (Bounding level 0
    too, by ``start_step / 2``, would take up to a third of a 1 cm tolerance at a
    band's edge at four times :func:`~geoidspline.store.codec.value_step`'s step.) Only
    nodes within a support of the band's edge see a neighbour: given ``band`` and
    ``tile_size``, the others are not evaluated. The node errors returned are those
    with the neighbours' coefficients unrounded: the fit's minus the rounding's change,
    the spline of the changes evaluated alone.

    Before a step is halved, its rounding is corrected up to ``NUDGE_ROUNDS`` times at
    the nodes it takes over the target (:func:`_nudge`: a few B-splines' values one step
    the other way; at four times ``value_step``'s step, 9 of the 14.7 M coefficients of
    a global EGM2008 1 cm band moved and its 20 nodes over 1 cm came within it). A
    stored coefficient is then within one step of the fit's, not half a step. A step is
    also halved while the nodes' RMS error is above ``rounding.rms_m``
    (:data:`ROUNDING_RMS_OVER_TOLERANCE`)."""
    if rounding is None:
        return None, spline, fit_errors, float(np.abs(fit_errors).max()) if fit_errors.size else 0.0
    start = float(rounding.start_step)
    edge = np.ones(node_dirs.shape[0], dtype=bool)
    first = spline.levels[0]
    movable = np.zeros(int(owned[0].sum()), dtype=bool)  # level 0's own B-splines no neighbour's node sees
    if band is not None:
        # a B-spline reaches order/2 of its spacings from its centre: nodes farther from
        # the slab's edges see owned B-splines only (one spacing more for the floor)
        near = (first.order / 2.0 + 1.0) * max(lv.h for lv in spline.levels)
        low, high = band.first * tile_size + near, (band.last + 1) * tile_size - near
        z = node_dirs[:, 2]
        edge = (z < low) | (z >= high)
        centre = (unpack_keys(first.keys[owned[0]])[:, 2] + first.order / 2.0) * first.h
        movable = (centre >= low) & (centre < high)
    edge_dirs = node_dirs[edge]
    neighbour_changes = []  # at the edge nodes, level 0's neighbours rounded to each checked step
    bound = bound_overlays = np.zeros(edge_dirs.shape[0])  # the rest of the neighbours' share at most
    if edge_dirs.size:
        def neighbours(values_of, level0):
            return AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys[~m], values_of(lv.coefficients[~m]))
                                  for lv, m in zip(spline.levels, owned) if (lv.level == 0) == level0])

        for k in range(NEIGHBOUR_STEPS_CHECKED):
            step_k = start / 2 ** k
            neighbour_changes.append(neighbours(lambda c, s=step_k: rounding.round(c, s) - c, True)
                                     .evaluate_points(edge_dirs, any_batch=True))
        finer = start / 2 ** NEIGHBOUR_STEPS_CHECKED
        bound = 0.5 * finer * neighbours(np.ones_like, True).evaluate_points(edge_dirs, any_batch=True)
        bound_overlays = 0.5 * start * neighbours(np.ones_like, False).evaluate_points(edge_dirs, any_batch=True) \
            if any(lv.level != 0 for lv in spline.levels) else np.zeros(edge_dirs.shape[0])
    fit_max = float(np.abs(fit_errors).max()) if fit_errors.size else 0.0
    target = max(float(rounding.tolerance_m), fit_max + EVALUATION_ROUNDING_M)

    # edge nodes over the target with the band's own values exact: no step of its own
    # brings them within it (its neighbours' roundings alone take them over), so the
    # search goes by the other nodes and the largest error reports them
    def with_neighbours(at_edge):
        """The edge nodes' largest errors with the neighbours' level-0 rounding (each
        step checked exactly, finer ones by their bound), given the band's own."""
        worst = np.abs(at_edge) + bound
        for moved in neighbour_changes:
            worst = np.maximum(worst, np.abs(at_edge - moved))
        return worst

    hopeless = np.zeros(node_dirs.shape[0], dtype=bool)
    if edge_dirs.size and fit_errors.size:
        hopeless[edge] = with_neighbours(fit_errors[edge]) + bound_overlays + EVALUATION_ROUNDING_M > target

    def measured(rounded):
        """(node errors, each node's largest error at most) of the band's rounded values."""
        change = AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys[m], r - lv.coefficients[m])
                                for lv, m, r in zip(spline.levels, owned, rounded)])
        errors = fit_errors - at_nodes(change) if node_dirs.size else np.empty(0)
        worst = np.abs(errors)
        if edge_dirs.size and errors.size:
            worst[edge] = with_neighbours(errors[edge]) + bound_overlays
        return errors, worst + EVALUATION_ROUNDING_M

    # every rounding is evaluated at the same nodes: sorted into the evaluation's
    # locality order once (the same values, bit for bit, as each evaluation sorting them
    # again; held for the search only, not while the neighbours' or the stored spline are made)
    visit = query_order(node_dirs) if node_dirs.size else np.empty(0, np.int64)
    visited_dirs = np.take(node_dirs, visit, axis=0)

    def at_nodes(change):
        values = np.zeros(node_dirs.shape[0])
        values[visit] += change.evaluate_points(visited_dirs, any_batch=True, ordered=True)
        return values

    fit_ms = float(np.mean(fit_errors ** 2)) if fit_errors.size else 0.0
    rms_target = None
    if rounding.rms_m is not None and fit_errors.size:
        rms_target = max(float(rounding.rms_m), ROUNDING_RMS_GROWTH * np.sqrt(fit_ms))

    def screened_ms(rounded):
        """The nodes' mean square error with ``rounded`` estimated on every
        ``SCREEN_STRIDE``-th node in the evaluation's order (None: too few nodes)."""
        if rms_target is None or node_dirs.shape[0] < SCREEN_NODES_MIN:
            return None
        change = AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys[m], r - lv.coefficients[m])
                                for lv, m, r in zip(spline.levels, owned, rounded)])
        sub = visit[::SCREEN_STRIDE]
        errors = fit_errors[sub] - change.evaluate_points(visited_dirs[::SCREEN_STRIDE], any_batch=True, ordered=True)
        return float(np.mean(errors ** 2))

    step = start
    while True:
        rounded = [rounding.round(lv.coefficients[m], step) for lv, m in zip(spline.levels, owned)]
        estimate = screened_ms(rounded) if step / 2.0 >= 1e-6 else None
        # a step whose noise is plainly above the budget is halved on the estimate: its
        # nodes are not measured one by one (nor nudged: noisy steps are not)
        screened = estimate is not None and estimate > SCREEN_MS_OVER_BUDGET * rms_target ** 2
        for nudges in range(0 if screened else NUDGE_ROUNDS + 1):
            errors, worst = measured(rounded)
            largest = float(worst.max()) if worst.size else 0.0
            over = (worst > target) & ~hopeless
            stored_ms = float(np.mean(errors ** 2)) if errors.size else 0.0
            noisy = rms_target is not None and stored_ms > rms_target ** 2
            # a step too noisy is halved whatever the nudges do (they move a few B-splines)
            if noisy or not over.any() or nudges == NUDGE_ROUNDS \
                    or not _nudge(first, owned[0], movable, rounded[0], step, rounding, node_dirs[over], errors[over]):
                break
        if screened:
            stored_ms, noisy = estimate, True
        elif (not over.any() and not noisy) or step / 2.0 < 1e-6:
            visit = visited_dirs = None
            stored = AmbientSpline([LevelSpline(lv.level, lv.h, lv.order, lv.keys, _owned_replaced(lv.coefficients, m, r))
                                    for lv, m, r in zip(spline.levels, owned, rounded)])
            return step, stored, errors, largest
        halvings = 1
        if noisy:
            # the rounding's noise is independent of the fit's errors and goes as the step:
            # go straight to the step it predicts (the next pass checks it)
            noise = np.sqrt(max(stored_ms - fit_ms, 0.0))
            room = np.sqrt(max(rms_target ** 2 - fit_ms, 1e-300))
            halvings = max(1, int(np.ceil(np.log2(noise / room))))
            while halvings > 1 and step / 2.0 ** halvings < 1e-6:
                halvings -= 1
        step /= 2.0 ** halvings


SCREEN_STRIDE = 16
"""A band with many nodes first estimates a step's rounding noise on every this-many-th
of its nodes (in the evaluation's locality order: spread over the band)."""

SCREEN_NODES_MIN = 1_000_000
"""Nodes from which a band screens its steps (:data:`SCREEN_STRIDE`): 62,500 nodes or
more in the estimate."""

SCREEN_MS_OVER_BUDGET = 4.0
"""A step is halved on its estimate alone when the estimated mean square error at the
nodes is above this many times the budget's square (RMS twice the budget): far beyond
what a sample of 62,500 nodes or more can be wrong by. Closer to the budget, the step's
nodes are measured one by one as before. At 1 cm every band of the global EGM2008 fit
halves its first step twice (0.026664 to 0.006666 m): one evaluation of the rounding at
its tens of millions of nodes fewer."""


def _owned_replaced(values, owned, rounded):
    out = np.array(values, dtype=np.float64, copy=True)
    out[owned] = rounded
    return out


NUDGE_NODES_MAX = 100_000
"""More nodes over the target than this at a step: the step is halved without correcting
its rounding (a correction moves a B-spline for a node; this many are no correction)."""


def _nudge(level, owned, movable, rounded, step, rounding, dirs, errors) -> bool:
    """Move, by one step towards the truth, the rounded value (``rounded``, the owned
    coefficients' of ``level``, changed in place) of one B-spline for each node of
    ``dirs`` with the stored spline's error ``errors`` (truth − stored): of those there
    that are the band's, ``movable`` (no neighbour band's node sees it: the neighbours
    check their edges against values rounded to nearest) and whose value was rounded
    away from the truth (so that it stays within one step of the fit's), the one
    largest at the node. A B-spline moves once a round, for the first node that takes
    it. Whether any value moved."""
    from ..bspline.basis import bspline_weights

    keys = level.keys[owned]
    if not dirs.size or not keys.size or dirs.shape[0] > NUDGE_NODES_MAX:
        return False
    order, exact = level.order, level.coefficients[owned]
    position = dirs / level.h
    cell = np.floor(position)
    per_axis = [bspline_weights(position[:, d] - cell[:, d], order, 0)[0] for d in range(3)]  # (M, order) each
    weights = (per_axis[0][:, :, None, None] * per_axis[1][:, None, :, None]
               * per_axis[2][:, None, None, :]).reshape(dirs.shape[0], -1)
    offsets = np.stack(np.meshgrid(*[np.arange(order)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    candidates = pack_keys((cell.astype(np.int64)[:, None, :] - order + 1 + offsets[None]).reshape(-1, 3))
    at = np.minimum(np.searchsorted(keys, candidates), keys.size - 1)
    towards = np.repeat(np.sign(errors), offsets.shape[0])
    usable = (keys[at] == candidates) & movable[at] & (towards * (rounded[at] - exact[at]) <= 0) & (towards != 0)
    score = np.where(usable, weights.ravel(), -1.0).reshape(weights.shape)
    best = np.argmax(score, axis=1)
    chosen = np.flatnonzero(score[np.arange(best.size), best] > 0)
    if not chosen.size:
        return False
    pick = chosen * offsets.shape[0] + best[chosen]
    at, first = np.unique(at[pick], return_index=True)  # a B-spline moves once, for its first node
    moved = rounding.round(rounded[at] + towards[pick][first] * step, step)
    rounded[at] = moved
    return True


def _tile_stats(owned_levels, node_dirs, node_errors, check_dirs, check_errors, params):
    """{packed tile key: (node errors, check errors)} for the tiles of the band's coefficients."""
    tiles = [pack_keys(cube_of_support_centres(unpack_keys(keys), h, params.order, params.tile_size))
             for _, h, keys, _ in owned_levels if keys.size]
    if not tiles:
        return {}
    nodes = _by_tile(tiles_of_directions(node_dirs, params.tile_size), node_errors)
    checks = _by_tile(tiles_of_directions(check_dirs, params.tile_size), check_errors)
    empty = np.empty(0)
    return {int(key): (nodes.get(int(key), empty), checks.get(int(key), empty))
            for key in np.unique(np.concatenate(tiles))}


def _by_tile(tile_keys, values) -> dict:
    """{tile key: its values, in their order} by one stable sort (not a mask per tile:
    a polar band has 35 M nodes in hundreds of tiles)."""
    order = np.argsort(tile_keys, kind="stable")
    keys = tile_keys[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]]) if keys.size else np.empty(0, np.int64)
    parts = np.split(np.asarray(values)[order], starts[1:])
    return {int(keys[a]): part for a, part in zip(starts, parts)}


def level_reports(bands) -> list[dict]:
    """The fit's level reports from the bands' (``[(level reports, {level: coefficients})]``):
    counts added, the largest error kept (and the largest band's RMS: the RMS over every
    node is the manifest's accuracy)."""
    merged: dict[int, dict] = {}
    for reports, _ in bands:
        for report in reports:
            into = merged.setdefault(report["level"], {**report, "coefficients": 0, "marked_cells": 0, "sites": 0,
                                                       "blocks_solved": 0, "nodes_above_tolerance": 0,
                                                       "seconds": 0.0, "max_error_m": 0.0, "rms_error_m": 0.0})
            for key in ("marked_cells", "sites", "blocks_solved", "nodes_above_tolerance", "seconds"):
                into[key] += report[key]
            into["max_error_m"] = max(into["max_error_m"], report["max_error_m"])
            into["rms_error_m"] = max(into["rms_error_m"], report["rms_error_m"])
    for _, counts in bands:
        for level, count in counts.items():
            if int(level) in merged:
                merged[int(level)]["coefficients"] += int(count)
    return [merged[level] for level in sorted(merged)]


def band_spline(results, params: FitParameters) -> AmbientSpline:
    """The whole spline from the bands' owned coefficients (for tests and small fits:
    a global fit's spline is the store's, read tile by tile)."""
    by_level: dict[int, list] = {}
    for result in results:
        for level, h, keys, coefs in result.levels:
            by_level.setdefault(level, []).append((h, keys, coefs))
    levels = []
    for level in sorted(by_level):
        parts = by_level[level]
        keys = np.concatenate([p[1] for p in parts])
        coefs = np.concatenate([p[2] for p in parts])
        order = np.argsort(keys)
        levels.append(LevelSpline(level, parts[0][0], params.order, keys[order], coefs[order]))
    return AmbientSpline(levels)
