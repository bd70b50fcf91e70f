"""Fitting: hierarchical overlays of ambient B-splines, solved block by block.

The algorithm (Lehmann 2013, §3-4 and §5.2; summarised in METHOD.md):

1. Level 0 takes every cell of spacing ``h0`` that meets the unit sphere over the
   region ("active cells", :mod:`geoidspline.bspline.domain`) and every B-spline
   touching one of them.
2. Data sites are rays (:mod:`geoidspline.fitting.sites`).
3. The level is fitted to the residual of the levels before it by sparse least
   squares (:mod:`geoidspline.fitting.least_squares`), or level 0 by quasi-interpolation
   of an exact source (:mod:`geoidspline.fitting.interpolation`).
4. The residual on the sphere is measured at every data node of the region; level
   ``ℓ + 1`` takes the B-splines the refinement strategy selects
   (:class:`geoidspline.hierarchy.overlays.OverlayRefinement`) and is fitted on every
   site where those B-splines are non-zero, so each level is a C^(n-2) spline on R³.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time

import numpy as np

from ..bspline.domain import active_cells
from ..bspline.keys import touching_keys
from ..bspline.level import LevelSpline, add_levels
from ..errors import FitError
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.overlays import OverlayRefinement
from ..sphere.coverage import Coverage
from ..sphere.region import GLOBAL, Region
from .executors import Executor
from .interpolation import interpolate_level, lattice_spacing, sample_nodes
from .least_squares import local_problems
from .parameters import MIN_H_PER_DATA_SPACING, FitParameters
from .progress import as_progress
from .result import FitResult, LevelReport
from .sites import DataNodes, sites_for_level

log = logging.getLogger(__name__)


def solve_level(problems, executor: Executor, progress=None):
    """Solve a level's local problems with ``executor``; its own keys (sorted), their
    coefficients, and how many problems were solved."""
    results = executor.solve(problems, progress)
    keys = np.concatenate([r[0] for r in results]) if results else np.empty(0, np.int64)
    coefs = np.concatenate([r[1] for r in results]) if results else np.empty(0)
    order = np.argsort(keys)
    return keys[order], coefs[order], len(results)


def finer_data_hint(source) -> str:
    """How to get data finer than ``source``'s nodes, for its kind: a model is sampled
    finer (``sample_spacing_deg``), a grid's nodes are what they are."""
    if getattr(source.provenance, "kind", None) == "harmonic" and hasattr(source, "lattice_step"):
        return "sample the model finer with sample_spacing_deg"
    return f"a grid with finer nodes than {source.provenance.source}'s is needed for a finer level"


def fit_nodes(sample, region: Region, params: FitParameters, refinement=None, progress=None,
              force_tiles=False, base_is_overlay=False, first_level=None,
              executor: Executor | None = None, interpolant=None, started=None,
              finer_hint: str = "finer data are needed for a finer level", cell_centres: bool = False) -> FitResult:
    """Fit the nodes of a :class:`~geoidspline.sphere.sample.NodeSample` over ``region``.

    ``sample`` must cover the region plus the support margin of level 0 (see
    :func:`fit_source`, which asks the source for exactly that). ``progress``: a
    :class:`~geoidspline.fitting.progress.Progress` told of each level's blocks and
    node errors, or a callable given the number of local problems just solved. With
    ``base_is_overlay`` the sample holds residuals of an existing spline (a regional
    update) and level 0 is refined and regularised like any overlay. ``first_level``, a
    :class:`LevelSpline` computed already (by quasi-interpolation), stands as level 0;
    ``(level, seconds, lattice points)`` of it go into its report. ``interpolant``: the
    hierarchical quasi-interpolant of an exact source
    (:mod:`geoidspline.fitting.hierarchical_interpolation`) gives the hierarchical basis's
    coefficients instead of least squares. ``started``: the ``time.perf_counter()`` the
    fit's seconds count from (work done before this call, e.g. synthesising the sample).
    ``cell_centres``: the sample is a grid's nodes, whose cell centres keep a hierarchical
    fit near the grid's interpolants between them (:mod:`geoidspline.fitting.cell_centres`).
    """
    # the hierarchical basis (§5.3) replaces the overlays of a new fit; an update (a
    # strategy given, or residuals on a base) adds overlays to any store
    hierarchical = (params.refinement == "hierarchical" and refinement is None and not base_is_overlay
                    and first_level is None)
    refinement = refinement or OverlayRefinement(params.refine_radius)
    executor = executor or Executor()
    progress = as_progress(progress)
    start = started if started is not None else \
        time.perf_counter() - (first_level[1] if first_level is not None else 0.0)
    nodes = DataNodes.from_sample(sample, region)
    try:
        coverage = Coverage.from_sample(sample, region)
    except ValueError as exc:
        raise FitError(str(exc)) from None
    if not np.any(nodes.in_region):
        raise FitError(f"no data nodes inside the region {region.as_tuple()}")
    if (first_level is None and not base_is_overlay
            and params.h0 < MIN_H_PER_DATA_SPACING * nodes.spacing_rad):
        # level 0 finer than the data: its B-splines are not determined between the
        # nodes, and there are (spacing / h0)² times more of them than nodes to pay for
        raise FitError(f"h0 {params.h0:.4g} is finer than {MIN_H_PER_DATA_SPACING:g} x the data spacing "
                       f"({nodes.spacing_rad:.4g} on the unit sphere): give h0 >= "
                       f"{MIN_H_PER_DATA_SPACING * nodes.spacing_rad:.4g}, or a finer source")
    fallback = None
    if hierarchical:
        from .hierarchical import BasisTooLarge, centre_reach_deg, fit_hierarchical  # §5.3: one basis over all levels

        try:
            centres = None
            if cell_centres and interpolant is None:
                from .cell_centres import cell_centre_nodes

                centres = cell_centre_nodes(sample, region, centre_reach_deg(params, nodes))
            result = fit_hierarchical(nodes, coverage, region, params, progress, force_tiles, start,
                                      interpolant=interpolant, memory_budget=executor.memory_budget,
                                      centres=centres)
            # the promise is kept, not given up: local passes take the nodes (and cell centres) left above
            result = complete_at_finest_level(result, nodes, region, params, force_tiles, executor, progress,
                                              centres)
            return result
        except BasisTooLarge as exc:  # a result in bounded memory rather than none
            fallback = f"{exc}: fitted by overlays instead"
            log.warning("%s", fallback)
            params = dataclasses.replace(params, refinement="overlays")
    region_dirs = nodes.directions[nodes.in_region]
    errors = nodes.values[nodes.in_region].copy()  # residual N - S at region nodes
    levels: list[LevelSpline] = []
    reports: list[LevelReport] = []
    converged = False
    violating = region_dirs[np.abs(errors) > params.node_target_m] if base_is_overlay else region_dirs
    # a level much finer than the data spacing is not determined between the nodes
    data_spacing = nodes.spacing_rad
    data_limited = False
    for level in range(params.max_level + 1):
        t0 = time.perf_counter()
        h = params.spacing(level)
        if level > 0 and h < MIN_H_PER_DATA_SPACING * data_spacing:
            data_limited = True
            log.warning(
                "stopping at level %d: level %d (h=%.4g) would be finer than %.1f x the data spacing "
                "(%.4g on the unit sphere); %s",
                level - 1, level, h, MIN_H_PER_DATA_SPACING, data_spacing, finer_hint,
            )
            break
        if level == 0 and first_level is not None:
            lv, seconds_before, site_count = first_level
            t0 -= seconds_before
            marked, solved = 0, 0
        else:
            keys, marked, site_cells = refinement.level_keys(level, h, params.order, region, violating)
            if keys.size == 0:
                if violating.size == 0:
                    converged = True
                    break
                continue  # no B-spline of this level may be used there (a regional update's zone)
            lv, site_count, solved = fit_level(nodes, levels, level, h, keys, site_cells, params, force_tiles,
                                               level > 0 or base_is_overlay, executor, progress)
        levels.append(lv)
        subtract_level(errors, lv, region_dirs, progress, f"level {level} node errors")
        above = np.abs(errors) > params.node_target_m
        violating = region_dirs[above]
        report = LevelReport(
            level=level, h=h, coefficients=len(lv), marked_cells=int(marked), sites=int(site_count),
            blocks_solved=solved, max_error_m=float(np.abs(errors).max()),
            rms_error_m=float(np.sqrt(np.mean(errors**2))), nodes_above_tolerance=int(above.sum()),
            seconds=time.perf_counter() - t0,
        )
        reports.append(report)
        log.info(
            "level %d: h=%.6g, %d coefficients, %d sites, max |error| %.4f m, %d nodes above %.4g m (%.1f s)",
            level, h, len(lv), site_count, report.max_error_m, report.nodes_above_tolerance,
            params.node_target_m, report.seconds,
        )
        if not above.any():
            converged = True
            break
    if not converged and levels and params.spacing(levels[-1].level + 1) < MIN_H_PER_DATA_SPACING * data_spacing:
        # the last level is the finest the data determine (whether the next was refused
        # or max_level was chosen there): it takes the residual it left again
        data_limited = True
        violating, converged = _finest_level_passes(
            nodes, levels, reports, errors, region_dirs, violating, refinement, region, params,
            force_tiles, executor, progress)
    spline = AmbientSpline(levels)
    return FitResult(
        spline=spline, parameters=params, region=region, levels=reports,
        node_count=int(errors.size), node_max_error_m=float(np.abs(errors).max()),
        node_rms_error_m=float(np.sqrt(np.mean(errors**2))), converged=converged,
        seconds=time.perf_counter() - start, node_directions=region_dirs, node_errors=errors,
        data_limited=data_limited, coverage=coverage, refinement_fallback=fallback,
    )


#: Passes a data-limited finest level may take in all (the first included).
FINEST_LEVEL_PASSES = 3

#: Radial offsets of an extra pass's sites: the nodes themselves (see :func:`_finest_level_passes`).
ON_THE_SPHERE = (0.0,)


def fit_level(nodes, levels, level, h, keys, site_cells, params: FitParameters, force_tiles, overlay,
              executor, progress, node_mask=None, radial_offsets=None, name=None):
    """Least squares of ``keys`` (one level, spacing ``h``) to the residual of ``levels``
    at the rays of the nodes (those of ``node_mask`` only, when given; ``radial_offsets``:
    the parameters' unless given); (the level's :class:`LevelSpline`, sites, blocks solved)."""
    ray_mask = nodes.thinned(h, params.rays_per_cell)
    if node_mask is not None:
        ray_mask &= node_mask
    offsets = params.radial_offsets if radial_offsets is None else radial_offsets
    points, node_of_site = sites_for_level(nodes, ray_mask, h, params.order, keys, offsets, site_cells)
    # the same bits for a site whatever else is fitted with it (a band's fit, the globe's)
    values = nodes.values[node_of_site] - AmbientSpline(levels).evaluate_points(points, any_batch=True) if levels \
        else nodes.values[node_of_site].copy()
    problems = list(local_problems(level, h, params, keys, points, values, force_tiles, overlay=overlay))
    name = name or f"level {level}"
    with progress.stage(f"{name} blocks", len(problems), "block") as advance:
        own_keys, own_coefs, solved = solve_level(problems, executor, advance)
    if own_keys.size != keys.size:
        raise FitError(f"{name}: tiles returned {own_keys.size} of {keys.size} coefficients")
    return LevelSpline(level, h, params.order, own_keys, own_coefs), points.shape[0], solved


def _finest_level_passes(nodes, levels, reports, errors, region_dirs, violating, refinement, region,
                         params: FitParameters, force_tiles, executor, progress):
    """Fit the finest level the data determine again to the residual it left, where nodes
    are still above the tolerance, and add each pass to that level (same h and order: the
    union of keys, coefficients summed), so the fit keeps one spline per level.

    A finer level would not be determined between the nodes; what the finest level's
    first pass leaves at a few nodes (a small island, a narrow peak) is taken by the same
    level again, on the keys its own rule admits there (``refinement.level_keys``: a
    regional update's stay inside its blend zone). A pass's sites are the region's nodes,
    on the sphere (:data:`ON_THE_SPHERE`), where the tolerance is measured: off the sphere
    the residual also holds the coarser levels' radial variation, which at this spacing
    pulled a pass away from the values at the nodes (with the level's own rays a second
    pass raised the largest error); and beyond the region the nodes are never refined, so
    their residual (decimetres, for a grid fitted over part of it) made a pass straddling
    the region's edge oscillate between the edge rows. Stops when no node is above the
    tolerance, when a pass does not lower the largest error (that pass is dropped), or
    after :data:`FINEST_LEVEL_PASSES` passes in all. Updates ``levels[-1]``,
    ``reports[-1]`` and ``errors`` in place; returns (violating directions, converged).
    """
    finest = levels[-1]
    report = reports[-1]
    while report.passes < FINEST_LEVEL_PASSES:
        t0 = time.perf_counter()
        name = f"level {finest.level} pass {report.passes + 1}"
        keys, marked, site_cells = refinement.level_keys(finest.level, finest.h, params.order, region, violating)
        if keys.size == 0:
            break
        if not report.pass_max_error_m:  # a pass is tried: the errors after the first
            report.pass_max_error_m = [report.max_error_m]
            report.pass_nodes_above_tolerance = [report.nodes_above_tolerance]
        extra, site_count, solved = fit_level(nodes, levels, finest.level, finest.h, keys, site_cells, params,
                                              force_tiles, True, executor, progress, node_mask=nodes.in_region,
                                              radial_offsets=ON_THE_SPHERE, name=name)
        trial = errors.copy()
        subtract_level(trial, extra, region_dirs, progress, f"{name} node errors")
        largest = float(np.abs(trial).max())
        if not largest < report.max_error_m:
            log.info("%s: max |error| %.4f m, not below %.4f m: pass dropped", name, largest, report.max_error_m)
            break
        errors[:] = trial
        levels[-1] = add_levels(levels[-1], extra)
        above = np.abs(errors) > params.node_target_m
        violating = region_dirs[above]
        report.passes += 1
        report.coefficients = len(levels[-1])
        report.marked_cells += int(marked)
        report.sites += int(site_count)
        report.blocks_solved += solved
        report.max_error_m = largest
        report.rms_error_m = float(np.sqrt(np.mean(errors**2)))
        report.nodes_above_tolerance = int(above.sum())
        report.pass_max_error_m.append(largest)
        report.pass_nodes_above_tolerance.append(report.nodes_above_tolerance)
        report.seconds += time.perf_counter() - t0
        log.info("%s: %d coefficients, %d sites, max |error| %.4f m, %d nodes above %.4g m (%.1f s)",
                 name, len(extra), site_count, largest, report.nodes_above_tolerance, params.node_target_m,
                 time.perf_counter() - t0)
        if not above.any():
            return violating, True
    return violating, False


#: Local passes :func:`complete_at_finest_level` may take after a hierarchical fit.
COMPLETION_PASSES = 12


def complete_at_finest_level(result: FitResult, nodes, region: Region, params: FitParameters, force_tiles=False,
                             executor: Executor | None = None, progress=None, centres=None) -> FitResult:
    """Take what a hierarchical fit left above the tolerance by local passes at the
    finest admissible level (``max_level``, and not finer than half the data spacing).

    The hierarchical refinement stops when a step adds nothing near the remaining bad
    nodes (their nearest B-spline refined already, or their leaf at the finest level),
    often one level before the finest the data allow. Each pass is a least-squares
    overlay at that level of the B-splines around the nodes still above
    :attr:`FitParameters.node_target_m`, fitted on the region's nodes on the sphere to
    the residual (as :func:`_finest_level_passes` does for overlays), and added to the
    spline's level of that spacing.

    ``centres``: a grid's cell centres (:class:`~geoidspline.fitting.cell_centres.CellCentres`),
    held to the same target outside the interval of the grid's interpolants: a centre
    of the region outside it by more marks its B-splines as a bad node does, and every
    centre of the region in a pass's cells is a site there, valued at the point of its
    interval nearest the spline (the residual is how far the spline must move to enter
    it: nothing where it is inside). Without them a pass at a level as fine as the nodes
    is free between them, and the centres the hierarchical steps left outside (Andes
    0.01 m: 12 at 1.6 T) stay there.

    Passes stop when nothing is above, when a pass lowers neither the largest excess
    (nodes' error, centres' distance) nor the count above (that pass is dropped), or
    after :data:`COMPLETION_PASSES`; should the passes end with nodes above the target
    that an earlier pass (or the fit) kept, that earlier spline is the result (the
    nodes' promise first). Returns the result with the passes' levels, errors and one
    :class:`LevelReport` per pass (its ``coefficients`` the spline's total)."""
    from .hierarchical import finest_admissible_level

    executor = executor or Executor()
    progress = as_progress(progress)
    level = finest_admissible_level(params, nodes)
    h = params.spacing(level)
    refinement = OverlayRefinement(params.refine_radius)
    levels = list(result.spline.levels)
    region_dirs = result.node_directions
    errors = result.node_errors.copy()
    reports = list(result.levels)
    target = params.node_target_m
    region_nodes = nodes.subset(nodes.in_region)
    if centres is not None:
        centres = centres.subset(centres.in_region)
        centre_values = result.spline.evaluate_points(centres.directions, any_batch=True)
    else:
        centre_values = np.empty(0)

    def excess(node_errors, values):
        """(largest excess, count above the target, nodes above) of a state."""
        node_above = np.abs(node_errors) > target
        outside = centres.outside(values) if centres is not None else np.empty(0)
        largest = max(float(np.abs(node_errors).max()), float(outside.max(initial=0.0)))
        return largest, int(node_above.sum() + (outside > target).sum()), node_above, outside > target

    largest, count, above, centre_above = excess(errors, centre_values)
    if count == 0:
        return result
    node_kept = None if above.any() else (levels, errors, centre_values, reports)  # the nodes' promise first
    for number in range(1, COMPLETION_PASSES + 1):
        t0 = time.perf_counter()
        name = f"level {level} local pass {number}"
        marks = region_dirs[above] if centres is None else \
            np.concatenate([region_dirs[above], centres.directions[centre_above]])
        keys, marked, site_cells = refinement.level_keys(level, h, params.order, region, marks)
        if keys.size == 0:
            break
        sites = region_nodes
        if centres is not None:  # each valued where the spline would enter its interval
            sites = region_nodes.joined(dataclasses.replace(
                centres, values=np.clip(centre_values, centres.low, centres.high)))
        extra, site_count, solved = fit_level(sites, levels, level, h, keys, site_cells, params, force_tiles, True,
                                              executor, progress, radial_offsets=ON_THE_SPHERE, name=name)
        trial = errors.copy()
        subtract_level(trial, extra, region_dirs, progress, f"{name} node errors")
        trial_values = centre_values.copy()
        if centres is not None:
            trial_values += AmbientSpline([extra]).evaluate_points(centres.directions, any_batch=True)
        trial_largest, trial_count, trial_above, trial_centre_above = excess(trial, trial_values)
        if not (trial_largest < largest or (trial_count < count and trial_largest <= largest)):
            log.info("%s: largest excess %.4f m, %d nodes and centres above: no better, pass dropped", name,
                     trial_largest, trial_count)
            break
        errors, centre_values = trial, trial_values
        largest, count, above, centre_above = trial_largest, trial_count, trial_above, trial_centre_above
        at = next((i for i, lv in enumerate(levels) if lv.level == level), None)
        levels = list(levels)
        if at is None:
            levels.append(extra)
            levels.sort(key=lambda lv: lv.level)
        else:
            levels[at] = add_levels(levels[at], extra)
        reports = reports + [LevelReport(
            level=level, h=h, coefficients=sum(len(lv) for lv in levels), marked_cells=int(marked),
            sites=int(site_count), blocks_solved=solved, max_error_m=float(np.abs(errors).max()),
            rms_error_m=float(np.sqrt(np.mean(errors ** 2))), nodes_above_tolerance=int(above.sum()),
            seconds=time.perf_counter() - t0,
        )]
        log.info("%s: %d coefficients, max |error| %.4f m, %d nodes above %.4g m%s (%.1f s)", name, len(extra),
                 reports[-1].max_error_m, int(above.sum()), target, "" if centres is None else
                 f"; cell centres at most {float(centres.outside(centre_values).max(initial=0.0)):.4f} m outside "
                 f"the interval, {int(centre_above.sum())} above", reports[-1].seconds)
        if not above.any():
            node_kept = (levels, errors, centre_values, reports)
        if count == 0:
            break
    if above.any() and node_kept is not None:
        log.info("%s: %d nodes above %.4g m after the passes: the spline that kept every node is the result",
                 f"level {level} local passes", int(above.sum()), target)
        levels, errors, centre_values, reports = node_kept
        above = np.abs(errors) > target
    return dataclasses.replace(
        result, spline=AmbientSpline(levels), levels=reports, node_errors=errors,
        node_max_error_m=float(np.abs(errors).max()), node_rms_error_m=float(np.sqrt(np.mean(errors ** 2))),
        converged=not above.any(), data_limited=result.data_limited or level < params.max_level,
    )


#: Nodes a step of the node-error stage evaluates (large enough for the compiled path).
ERROR_CHUNK = 1_000_000


def subtract_level(errors, level: LevelSpline, directions, progress, name):
    """``errors -= level`` at ``directions``, in chunks of :data:`ERROR_CHUNK` reported as
    a stage (the same values as one call, and as any other set of nodes: every chunk
    takes the compiled path)."""
    spline = AmbientSpline([level])
    bounds = list(range(0, errors.size, ERROR_CHUNK))[1:] + [errors.size]
    if len(bounds) > 1 and bounds[-1] - bounds[-2] < ERROR_CHUNK:
        bounds.pop(-2)  # no short last chunk: it would take the small-batch path
    with progress.stage(name, len(bounds), "chunk") as advance:
        start = 0
        for stop in bounds:
            errors[start:stop] -= spline.evaluate_points(directions[start:stop], any_batch=True)
            start = stop
            advance(1)


def support_margin_deg(params: FitParameters) -> float:
    """Angular reach (degrees) of the level-0 B-splines beyond the region's cells."""
    chord = params.order * params.h0 * math.sqrt(3.0)
    return math.degrees(2.0 * math.asin(min(1.0, chord / 2.0)))


def fit_source(source, region: Region | None = None, params: FitParameters | None = None,
               progress=None, force_tiles=False, executor: Executor | None = None) -> FitResult:
    """Fit a geoid source (grid or model) over ``region`` (default: global)."""
    params = params or FitParameters()
    region = region or GLOBAL
    data_region = region.expanded(support_margin_deg(params))
    spacing = params.sample_spacing_deg
    if params.method == "interpolation":
        return _fit_by_interpolation(source, region, params, spacing, progress, force_tiles, executor)
    if spacing is None and hasattr(source, "lattice_step"):
        # a model's own default (90/N degrees) can leave a low-degree model with a
        # handful of nodes: keep at least a few per level-0 cell
        spacing = min(source.lattice_step(None), math.degrees(params.h0) / 4.0)
    sample = sample_nodes(source, clip_to_extent(data_region, source), spacing, as_progress(progress))
    from .hierarchical import CELL_CENTRES_BY_DEFAULT

    # a grid is known at its nodes only: its cell centres can keep the spline near its interpolants
    grid_centres = CELL_CENTRES_BY_DEFAULT and not hasattr(source, "lattice_step")
    return fit_nodes(sample, region, params, progress=progress, force_tiles=force_tiles, executor=executor,
                     finer_hint=finer_data_hint(source), cell_centres=grid_centres)


def check_method(source, params: FitParameters):
    """Raise :class:`FitError` when ``params.method`` cannot fit ``source``."""
    if params.method == "interpolation" and (
        getattr(source.provenance, "kind", None) != "harmonic" or not hasattr(source, "lattice_step")
    ):
        raise FitError(
            "fit method 'interpolation' needs a source exact everywhere (a spherical-harmonic "
            f"model); {source.provenance.source} is a {source.provenance.kind}: fit it by least squares"
        )


def _fit_by_interpolation(source, region, params, spacing, progress, force_tiles, executor):
    """Level 0 by quasi-interpolation of an exact source, then least-squares overlays;
    or, with the hierarchical basis, every level by its quasi-interpolant (§5.3.1)."""
    check_method(source, params)
    start = time.perf_counter()
    h = params.h0
    cells = active_cells(h, region)
    if cells.size == 0:
        raise FitError(f"no cells of spacing {h} meet the sphere over the region {region.as_tuple()}")
    if params.refinement == "hierarchical":  # §5.3.1: every level by the quasi-interpolant, no solve
        from .hierarchical_interpolation import hierarchical_interpolant

        band, interpolant = hierarchical_interpolant(source, cells, params, spacing, as_progress(progress))
        return fit_nodes(band, region, params, progress=progress, force_tiles=force_tiles, executor=executor,
                         interpolant=interpolant, started=start, finer_hint=finer_data_hint(source))
    keys = touching_keys(cells, params.order)
    spacing = lattice_spacing(source, h, spacing)
    coefficients, band, lattice_points = interpolate_level(source, keys, h, params.order, spacing,
                                                           progress=as_progress(progress))
    level0 = LevelSpline(0, h, params.order, keys, coefficients)
    # the band's lattice holds every node of the region: it is the nodes' sample too
    return fit_nodes(band, region, params, progress=progress, force_tiles=force_tiles,
                     first_level=(level0, time.perf_counter() - start, lattice_points), executor=executor,
                     finer_hint=finer_data_hint(source))


def clip_to_extent(region: Region, source) -> Region:
    extent = source.extent
    if extent.is_global:
        return region
    south = max(region.south, extent.south)
    north = min(region.north, extent.north)
    if region.longitude_span >= 360.0:
        return Region(south, extent.west, north, extent.east)
    west = region.west
    east = region.east
    ext_w, ext_e = extent.west, extent.east
    if extent.longitude_span < 360.0:
        # shift the region onto the extent's longitude branch before clipping
        shift = 360.0 * np.round(((west + east) / 2 - (ext_w + ext_e) / 2) / 360.0)
        west, east = max(west - shift, ext_w), min(east - shift, ext_e)
    return Region(south, west, north, east)
