"""Least-squares fit over the linearly independent hierarchical basis (thesis §5.3).

The driver of ``refinement="hierarchical"`` (Figure 5.7 of the thesis): fit the data
over the whole basis, measure the error at every data node of the region, refine the
active B-splines at the nodes above the tolerance (Algorithms 1 and 2,
:mod:`geoidspline.hierarchy.hierarchical`), and fit again, until no node is above the
tolerance, the next level would be finer than the data resolve, or ``max_level``.

Sites are rays, as for overlays, but each leaf cell takes them at its own level: the
nodes thinned to ``rays_per_cell`` per cell width of the leaf's level, at radii
``1 + ρ h`` of that level, kept inside the leaves of that level. Every fit is one
least-squares problem over all levels (no residual fitting, no ridge): the normal
equations of each leaf level (:func:`geoidspline.hierarchy.hierarchical.normal_matrix`),
a second-difference penalty per level that only decides coefficients the data leave
free. Small problems are solved by one factorisation (qdldl); larger ones by conjugate
gradients on the same whole problem, preconditioned by local problems on overlapping
cubes (§5.3.3's local solves, :class:`SchwarzPreconditioner`) and started from the
previous refinement step's spline (:func:`carry_over`).

Local solves alone (each cube keeping the coefficients whose support lay inside its
problem, the thesis's recipe) were tried first and left seams: with sites on the sphere
only, the thin basis has combinations that vanish on the sphere, which the whole
problem leaves to the penalty but each local problem decides its own way, so margins
had to reach two levels up (global EGM96 at 0.1 m: 8 times the basis in local unknowns,
over 30 minutes). As a preconditioner the local problems need only a narrow overlap,
and the iteration makes the pieces one spline (benchmarks/README.md).

The result is a normal :class:`geoidspline.fitting.result.FitResult`: each active B-spline of
level ℓ is a coefficient of level ℓ, and the sum of the levels is the spline, so stores
of either method are written, queried, updated and exported the same way.
"""

from __future__ import annotations

import logging
import math
import time

import numpy as np
import qdldl
import scipy.sparse as sp

from .._kernels.fitting import cholesky_packed, schwarz_apply
from .._memory import available_bytes
from ..bspline.basis import children
from ..bspline.keys import covered_cell_keys, cube_offsets, isin_sorted, pack_keys, unpack_keys
from ..errors import FitError
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.hierarchical import HierarchicalBasis, HierarchicalRefinement, normal_matrix
from ..sphere.region import Region
from .least_squares import _second_difference_penalty
from .parameters import MIN_H_PER_DATA_SPACING, FitParameters
from .progress import as_progress
from .result import FitResult, LevelReport
from .sites import DataNodes, sites_for_level

__all__ = ["fit_hierarchical", "leaf_sites", "solve_basis", "schwarz_blocks", "SchwarzPreconditioner",
           "conjugate_gradients", "carry_over", "BasisTooLarge"]

log = logging.getLogger(__name__)

#: Which active B-splines a node above the tolerance marks for refinement: those whose
#: support centre is within this many cells of it per axis. 0.5 is the one B-spline
#: centred nearest the node. The thesis marks every B-spline whose support holds the
#: node (``None``): that refines about twice the area for the same nodes (Andes, 0.5 m:
#: 27,518 coefficients against 21,472; the thesis's rules together gave 73,200).
MARK_RADIUS = 0.5

#: Thinning of the basis across the sphere (:class:`~geoidspline.hierarchy.hierarchical.Domain`):
#: B-splines whose support centre is within a cell (per axis) of the sphere, the rule
#: overlays use for their levels (``refine_radius`` 1). ``None`` keeps every B-spline
#: touching a leaf (the thesis's Ω): about twice as many for the same leaves (Andes:
#: 66,212 against 21,472). A subset of a linearly independent set stays independent,
#: so Theorems 5.3 and 5.6 hold for the thin basis too; it gives up polynomial
#: reproduction off the sphere, where no site and no query lies.
SHELL = 1.0

#: Up to this many coefficients the whole basis is one problem solved by one sparse
#: LDLᵀ factorisation (qdldl); above, by conjugate gradients preconditioned by local
#: solves (:func:`solve_basis`). The factorisation grows about as n^1.7 (global EGM96 at
#: 0.1 m: 15,082 unknowns 14 s, 60,298 unknowns 151 s); measured in benchmarks/README.md.
WHOLE_MAX_UNKNOWNS = 20_000

#: Side (unit-sphere units) of the cubes whose local problems precondition conjugate
#: gradients, and how far each problem reaches beyond its cube (its B-splines' supports
#: already reach beyond it). Andes at 0.1 m, last step, 35,000 unknowns: cubes of 0.1
#: with no extra reach 97,000 local unknowns, 31 iterations, 650 MB; reaching 0.0125
#: further 158,000, 15 iterations, 890 MB, no faster; cubes of 0.05 slower either way.
SCHWARZ_BLOCK = 0.1
SCHWARZ_OVERLAP = 0.0

#: Most unknowns in one local problem: a cube holding more (a level as fine as the
#: nodes over a whole cube: Andes at 0.01 m with the cell centres) is split in eight,
#: since its dense factor costs the cube of its size.
SCHWARZ_MAX_UNKNOWNS = 2_000

#: The type the cubes' packed Cholesky factors are held in (:class:`SchwarzPreconditioner`;
#: factorised in float64): float32, half the bytes of the largest part of a step's memory.
FACTOR_DTYPE = np.float32

#: Conjugate gradients stop when the fitted values at the sites are within this
#: fraction of the tolerance (RMS over the sites) of the whole problem's solution.
SOLVE_FRACTION = 0.01
MAX_ITERATIONS = 1_000

#: Entries of the cubes' packed Cholesky factors per unknown of a step (about 2.5 local
#: unknowns per unknown, a packed row each of about half its cube's size): global EGM96
#: 15' grid at 0.1 m with the cell centres, 2026-12-03, 156 million for 296,315 unknowns
#: (528 each; 465 at 238,311), benchmarks/README.md, issue 21's memory.
FACTOR_ENTRIES_PER_UNKNOWN = 530

#: The rest of a fit's peak per unknown of its largest step (bytes): the upper triangle of
#: the whole problem (about 85 non-zeros a row), the slices of the normal equations being
#: assembled, and the data nodes and cell centres (the global 15' grid at 0.5 m, the
#: matrix's grid row with the most nodes per unknown: 1.10 GB peak resident for 172,651
#: unknowns, 6,350 bytes each, of which about 1,750 the factors).
OTHER_BYTES_PER_UNKNOWN = 4_400

#: Peak memory of a fit per unknown of its largest step (bytes; about 6,500 with float32
#: factors, 8,600 with float64 ones): global 15' grid at 0.1 m 1.46 GB for 296,339
#: unknowns (4,940 each), at 0.5 m 6,350 (benchmarks/README.md). A step needing more
#: than the memory available is not built (:class:`BasisTooLarge`), and
#: :func:`geoidspline.fitting.memory.plan` plans level 0 with it.
BYTES_PER_UNKNOWN = OTHER_BYTES_PER_UNKNOWN + FACTOR_ENTRIES_PER_UNKNOWN * np.dtype(FACTOR_DTYPE).itemsize

#: Cell centres of a grid (:mod:`geoidspline.fitting.cell_centres`) as sites: their weight
#: relative to a node's.
CELL_CENTRE_WEIGHT = 1.0

#: The leaves of a level whose spacing is below this many node spacings take every cell
#: centre in them as a site from the level's first step: there the nodes alone leave the
#: B-splines free between them (about as many B-splines as nodes) and the spline swings
#: (Andes 0.1 m: 0.167 m off the interval at level 4, h = 1.43 node spacings). Coarser
#: levels are decided by the nodes; where their spline still leaves a centre's interval
#: by more than the tolerance, the centre marks its B-splines for refinement as a node
#: does, and the finer leaves take their centres. Measured in benchmarks/README.md
#: ("Between the nodes").
CELL_CENTRE_SPACINGS = 2.0

#: A centre's weight is :data:`CELL_CENTRE_WEIGHT` times ``(T / (T + w))²``, ``w`` half
#: its interval's width: its residual counted in the room it has (a node's is T, a
#: centre's T beyond its interval's ends), so that a wide interval (a steep feature,
#: where the two interpolants disagree) does not pull the spline from the nodes to its
#: middle. Rounded down to a power of 4, at most this many classes (each class is one
#: more assembly of the normal equations).
CELL_CENTRE_WEIGHT_CLASSES = 4

#: Whether a grid fit (:func:`geoidspline.fitting.driver.fit_source`) takes its cell
#: centres by default: on, every row of issue 21's matrix measured with them in
#: benchmarks/README.md ("Between the nodes"). ``fit_nodes(..., cell_centres=...)`` chooses.
CELL_CENTRES_BY_DEFAULT = True

#: Ridge relative to the mean diagonal of AᵀA: keeps B-splines no site sees decided.
RIDGE = 1e-10

_EMPTY = np.empty(0, dtype=np.int64)


class BasisTooLarge(FitError):
    """A refinement step's whole problem would need more memory than the system has left
    (:func:`geoidspline.fitting.driver.fit_nodes` then fits by overlays instead)."""


def leaf_sites(nodes: DataNodes, basis: HierarchicalBasis, params: FitParameters, levels=None):
    """One ``(points, node index)`` pair per level: rays through the nodes thinned at
    that level's spacing, at its radii, inside its leaves and outside every finer
    active support (there a finer B-spline would reach into the leaf). ``levels``: a
    bool per level, False leaving that level without sites (default: every level)."""
    out = []
    for lv in range(basis.levels):
        h = basis.spacing(lv)
        if basis.leaves[lv].size == 0 or (levels is not None and not levels[lv]):
            out.append((np.empty((0, 3)), np.empty(0, np.int64)))
            continue
        ray_mask = nodes.thinned(h, params.rays_per_cell)
        points, node_of_site = sites_for_level(nodes, ray_mask, h, basis.order, None, params.radial_offsets,
                                                basis.leaves[lv])
        keep = np.ones(points.shape[0], bool)
        for finer in range(lv + 1, basis.levels):
            if basis.active[finer].size:
                cells = pack_keys(np.floor(points / basis.spacing(finer)).astype(np.int64))
                keep &= ~isin_sorted(cells, covered_cell_keys(basis.active[finer], basis.order))
        out.append((points[keep], node_of_site[keep]))
    return out


def centre_reach_deg(params: FitParameters, nodes: DataNodes) -> float:
    """How far beyond the region (degrees) a cell centre can lie in a leaf that takes
    centres (:data:`CELL_CENTRE_SPACINGS`): twice the support of the coarsest such level,
    refined from points in the region (Algorithm 2 may add a level's support more)."""
    return math.degrees(2.0 * params.order * CELL_CENTRE_SPACINGS * nodes.spacing_rad)


def centre_weight_groups(centres, tolerance_m: float):
    """``[(weight, centres)]``: the cell centres in classes of weight (powers of 4, at
    most :data:`CELL_CENTRE_WEIGHT_CLASSES` below :data:`CELL_CENTRE_WEIGHT`), the empty
    ones left out."""
    half_width = 0.5 * (centres.high - centres.low)
    share = (tolerance_m / (tolerance_m + half_width)) ** 2
    steps = -np.clip(np.floor(-np.log(share) / np.log(4.0)), 0, CELL_CENTRE_WEIGHT_CLASSES - 1)
    steps = steps.astype(int)
    return [(CELL_CENTRE_WEIGHT * 4.0 ** float(k), centres.subset(steps == k)) for k in np.unique(steps)]


def _penalty(basis: HierarchicalBasis, diagonal, weight):
    """Second differences of each level's coefficients, scaled by the level's mean
    diagonal of AᵀA (so each level is regularised alike, whatever its site density)."""
    at = basis.offsets()
    blocks = []
    for lv, keys in enumerate(basis.active):
        if keys.size == 0:
            continue
        d = diagonal[at[lv]:at[lv + 1]]
        scale = float(d[d > 0].mean()) if np.any(d > 0) else 1.0
        blocks.append(_second_difference_penalty(keys) * (weight * scale))
    return sp.block_diag(blocks, format="csc") if blocks else sp.csc_matrix((0, 0))


class SymmetricMatrix:
    """A symmetric matrix held as its upper triangle (CSR, diagonal included): half the
    memory of the whole; ``@`` multiplies by the whole (two products with the half, the
    work of one with the whole)."""

    def __init__(self, upper):
        self.upper = upper.tocsr()
        self.diagonal = self.upper.diagonal()
        self.shape = self.upper.shape

    def __matmul__(self, x):
        return self.upper @ x + self.upper.T @ x - self.diagonal * x

    def principal_lower(self, index):
        """The lower triangle of the principal block on ``index`` (sorted), dense."""
        return self.upper[index][:, index].T.toarray()


def _system(basis: HierarchicalBasis, points, values, regularization, extra=None):
    """The whole problem's matrix (AᵀA + penalty + ridge, a :class:`SymmetricMatrix`) and Aᵀv.
    ``extra``: groups ``(points, values, weight)`` of sites weighted ``weight`` (per level,
    as ``points`` and ``values``); the penalty scales with the diagonal of all sites."""
    matrix, rhs = normal_matrix(basis, [(p, v) for p, v in zip(points, values)], extra or ())
    diagonal = matrix.diagonal()
    matrix = matrix + sp.triu(_penalty(basis, diagonal, regularization), format="csc")
    scale = float(diagonal[diagonal > 0].mean()) if np.any(diagonal > 0) else 1.0
    matrix = matrix + sp.identity(basis.coefficient_count, format="csc") * (RIDGE * scale)
    return SymmetricMatrix(matrix), rhs


def _solve(basis: HierarchicalBasis, points, values, regularization, extra=None):
    """The whole problem by one sparse LDLᵀ factorisation."""
    system, rhs = _system(basis, points, values, regularization, extra)
    return qdldl.Solver(system.upper.tocsc()).solve(rhs)


def _binned(positions, size):
    """Block keys of positions (M, 3) in cubes of ``size``, and the order sorting them."""
    bins = pack_keys(np.floor(positions / size).astype(np.int64))
    order = np.argsort(bins, kind="stable")
    return bins[order], order


def _gather(sorted_bins, order, wanted):
    starts = np.searchsorted(sorted_bins, wanted, side="left")
    stops = np.searchsorted(sorted_bins, wanted, side="right")
    parts = [order[a:b] for a, b in zip(starts, stops) if b > a]
    return np.sort(np.concatenate(parts)) if parts else np.empty(0, np.int64)


def solve_basis(basis: HierarchicalBasis, points, values, params: FitParameters, force_tiles=False,
                progress=None, name="hierarchical fit", start=None, memory_budget=None, extra=None):
    """Coefficients (all levels, in :meth:`HierarchicalBasis.offsets` order) of the
    least-squares fit of ``values`` at ``points`` (one array each per level) over the
    whole basis, and the number of local problems factorised.

    Up to :data:`WHOLE_MAX_UNKNOWNS` unknowns: one sparse factorisation. Above (or with
    ``force_tiles``): the same whole problem by conjugate gradients preconditioned by
    overlapping local solves (:class:`SchwarzPreconditioner`, §5.3.3's local problems
    used as a preconditioner rather than as the answer), from ``start`` (the previous
    refinement step's spline, :func:`carry_over`) until the fitted values at the sites
    are within :data:`SOLVE_FRACTION` of the tolerance (RMS) of the whole problem's:
    one spline with no seams between local problems. ``progress`` is told of each
    local factorisation as the stage ``name``.
    """
    progress = as_progress(progress)
    if basis.coefficient_count <= WHOLE_MAX_UNKNOWNS and not force_tiles:
        with progress.stage(name, 1, "block") as advance:
            coefs = _solve(basis, points, values, params.regularization, extra)
            advance(1)
        return coefs, 1
    need = basis.coefficient_count * BYTES_PER_UNKNOWN
    limits = [b for b in (memory_budget, available_bytes()) if b is not None]
    available = min(limits) if limits else None
    if available is not None and need > available:
        raise BasisTooLarge(f"{name}: the hierarchical basis has grown to {basis.coefficient_count:,} unknowns, "
                            f"which need about {need / 1e9:.3g} GB at once; {available / 1e9:.3g} GB are available; "
                            "overlays are fitted level by level in local blocks")
    t0 = time.perf_counter()
    system, rhs = _system(basis, points, values, params.regularization, extra)
    t1 = time.perf_counter()
    index_sets = schwarz_blocks(basis, SCHWARZ_BLOCK, SCHWARZ_OVERLAP, SCHWARZ_MAX_UNKNOWNS)
    with progress.stage(name, len(index_sets), "block") as advance:
        precondition = SchwarzPreconditioner(system, index_sets, advance)
    t2 = time.perf_counter()
    sites = int(sum(p.shape[0] for p in points))
    x0 = np.zeros(basis.coefficient_count) if start is None else start
    target = SOLVE_FRACTION * params.tolerance_m * math.sqrt(max(sites, 1))
    coefs, iterations, reached = conjugate_gradients(system, rhs, precondition, x0, target, MAX_ITERATIONS)
    if reached > target:
        raise FitError(f"{name}: conjugate gradients did not converge in {iterations} iterations "
                       f"(RMS change at the sites {reached / math.sqrt(max(sites, 1)):.3g} m)")
    log.info("%s: assembled in %.1f s; %d local problems (%d unknowns in all, at most %d in one) factorised in "
             "%.1f s; %d iterations of conjugate gradients in %.1f s", name, t1 - t0, len(index_sets),
             sum(i.size for i in index_sets), max(i.size for i in index_sets), t2 - t1, iterations,
             time.perf_counter() - t2)
    return coefs, len(index_sets)


def finest_admissible_level(params: FitParameters, nodes: DataNodes) -> int:
    """Finest level allowed: ``max_level``, and not finer than the data resolve."""
    level = 0
    while level < params.max_level and params.spacing(level + 1) >= MIN_H_PER_DATA_SPACING * nodes.spacing_rad:
        level += 1
    return level


def fit_hierarchical(nodes: DataNodes, coverage, region: Region, params: FitParameters, progress=None,
                     force_tiles=False, start=None, on_step=None, interpolant=None,
                     memory_budget=None, centres=None) -> FitResult:
    """Fit ``nodes`` (:class:`~geoidspline.fitting.sites.DataNodes`) over ``region`` with
    the hierarchical basis; :func:`geoidspline.fitting.driver.fit_nodes` calls it for
    ``params.refinement == "hierarchical"``. ``coverage`` goes into the result as it is.

    ``on_step(basis, points, values, coefficients)``, when given, is called after each
    refinement step's fit (points and values per leaf level), e.g. to measure the
    normal matrices (benchmarks/hierarchical_vs_overlays.py). ``interpolant`` (an exact
    source's :class:`~geoidspline.fitting.hierarchical_interpolation.HierarchicalQuasiInterpolant`)
    gives each step's coefficients, on its basis (``shell``), instead of least squares.
    ``memory_budget`` (bytes): a step whose whole problem would need more is not built
    (:class:`BasisTooLarge`). ``centres``: a grid's cell centres
    (:class:`~geoidspline.fitting.cell_centres.CellCentres`): the leaves of levels finer
    than :data:`CELL_CENTRE_SPACINGS` node spacings take every centre in them as a site
    (weight :data:`CELL_CENTRE_WEIGHT`, valued at the middle of its interval), and a
    centre of the region where the spline lies more than the nodes' target outside its
    interval marks its B-splines for refinement as a node above the target does; the fit
    stops when neither is left or nothing more can be refined (what is left, where nodes
    and centres pull apart at the finest level, is for the local passes of
    :func:`geoidspline.fitting.driver.complete_at_finest_level`, which take the centres
    too: multiplying the weight of the centres outside and fitting the whole basis again,
    tried first, cost whole steps and pushed nodes out; benchmarks/README.md, "Between
    the nodes").
    """
    start = time.perf_counter() if start is None else start
    progress = as_progress(progress)
    region_dirs = nodes.directions[nodes.in_region]
    region_values = nodes.values[nodes.in_region]
    finest = finest_admissible_level(params, nodes)
    strategy = HierarchicalRefinement(params.order, params.h0, MARK_RADIUS,
                                      SHELL if interpolant is None else interpolant.shell)
    basis = strategy.initial(region)
    if basis.coefficient_count == 0:
        raise FitError(f"no cells of spacing {params.h0} meet the sphere over the region {region.as_tuple()}")
    reports = []
    previous = None  # (basis, coefficients) of the last step: conjugate gradients start there
    converged = data_limited = False
    if centres is not None:
        centre_dirs = centres.directions[centres.in_region]
        centre_groups = centre_weight_groups(centres, params.tolerance_m)
    kept = None  # the last spline keeping every node, while the centres are still being fitted
    centre_max = None
    while True:
        t0 = time.perf_counter()
        step = len(reports)
        if interpolant is None:
            sites = leaf_sites(nodes, basis, params)
            points, values = [p for p, _ in sites], [nodes.values[i] for _, i in sites]
            x0 = carry_over(*previous, basis) if previous is not None else None
            extra = None
            fine = [basis.spacing(lv) < CELL_CENTRE_SPACINGS * nodes.spacing_rad for lv in range(basis.levels)]
            if centres is not None and any(fine):
                extra = []
                for weight, group in centre_groups:
                    chosen = leaf_sites(group, basis, params, fine)
                    extra.append(([p for p, _ in chosen], [group.values[i] for _, i in chosen], weight))
            coefs, solved = solve_basis(basis, points, values, params, force_tiles, progress,
                                        f"hierarchical step {step} ({basis.coefficient_count:,} unknowns)", x0,
                                        memory_budget, extra)
            previous = (basis, coefs)
        else:  # §5.3.1: the hierarchical quasi-interpolant, no solve
            (coefs, points, values), solved = interpolant.coefficients(basis, progress), 0
        if on_step is not None:
            on_step(basis, points, values, coefs)
        spline = AmbientSpline(basis.level_splines(coefs))
        errors = region_values - spline.evaluate_points(region_dirs)
        above = np.abs(errors) > params.node_target_m
        marks = region_dirs[above]
        if centres is not None:
            outside = centres.outside(spline.evaluate_points(centre_dirs), centres.in_region)
            centre_above = outside > params.node_target_m
            centre_max = float(outside.max(initial=0.0))
            marks = np.concatenate([marks, centre_dirs[centre_above]])
            if not above.any():
                kept = (spline, errors, basis, len(reports) + 1)
        top = basis.levels - 1
        reports.append(LevelReport(
            level=top, h=basis.spacing(top), coefficients=basis.coefficient_count,
            marked_cells=int(basis.leaves[top].size), sites=int(sum(p.shape[0] for p in points)),
            blocks_solved=solved, max_error_m=float(np.abs(errors).max()),
            rms_error_m=float(np.sqrt(np.mean(errors ** 2))), nodes_above_tolerance=int(above.sum()),
            seconds=time.perf_counter() - t0,
        ))
        log.info("hierarchical step %d: levels 0-%d, %d coefficients (%s), max |error| %.4f m, %d nodes above "
                 "%.4g m%s (%.1f s)", step, top, basis.coefficient_count,
                 "/".join(str(a.size) for a in basis.active), reports[-1].max_error_m, int(above.sum()),
                 params.node_target_m, "" if centres is None else
                 f"; cell centres at most {centre_max:.4f} m outside the interval, {int(centre_above.sum())} above",
                 reports[-1].seconds)
        if not marks.shape[0]:
            converged = True
            break
        refined = strategy.refine(basis, marks, max_level=finest)
        if refined is basis:
            data_limited = finest < params.max_level
            converged = not above.any()
            break
        basis = refined
    if centres is not None and above.any() and kept is not None:
        # the centres cost the nodes their tolerance and no refinement gives it back: the
        # nodes' promise comes first, so the last spline that kept it is the fit
        log.info("hierarchical fit: %d nodes above %.4g m after the cell centres' steps; the fit of step %d "
                 "(every node kept) is the result", int(above.sum()), params.node_target_m, kept[3] - 1)
        spline, errors, basis, steps = kept
        reports = reports[:steps]
        converged = True
    return FitResult(
        spline=spline, parameters=params, region=region, levels=reports,
        node_count=int(errors.size), node_max_error_m=float(np.abs(errors).max()),
        node_rms_error_m=float(np.sqrt(np.mean(errors ** 2))), converged=converged,
        seconds=time.perf_counter() - start, node_directions=region_dirs, node_errors=errors,
        data_limited=data_limited, coverage=coverage, basis=basis,
    )


# ---------------------------------------------------------------------------------
# The whole problem by conjugate gradients, preconditioned by overlapping local solves


def schwarz_blocks(basis: HierarchicalBasis, size: float, overlap: float, max_unknowns: int | None = None):
    """Index sets (into the vector of all levels) of overlapping subdomains: per cube of
    side ``size`` holding a support centre, every active B-spline whose support meets the
    cube grown by ``overlap`` (unit-sphere units). A cube whose set would hold more than
    ``max_unknowns`` is split in eight (again while that is so, down to the finest
    support's width), each part holding a support centre a subdomain of its own: the
    dense factor of a subdomain costs the cube of its size."""
    n = basis.order
    lo = np.concatenate([unpack_keys(k) * basis.spacing(lv) for lv, k in enumerate(basis.active)])
    width = np.concatenate([np.full(k.size, n * basis.spacing(lv)) for lv, k in enumerate(basis.active)])
    hi = lo + width[:, None]
    centre = lo + width[:, None] / 2.0
    sorted_bins, order = _binned(centre, size)
    blocks = np.unique(sorted_bins)
    reach = int(math.ceil((n * basis.spacing(0) / 2.0 + overlap) / size))
    near = cube_offsets(-reach, reach)
    smallest = n * basis.spacing(basis.levels - 1)
    octants = cube_offsets(0, 1)
    out = []

    def add(box_lo, side, candidates):
        box_hi = box_lo + side
        members = candidates[np.all((lo[candidates] < box_hi + overlap) & (hi[candidates] > box_lo - overlap), axis=1)]
        if max_unknowns is None or members.size <= max_unknowns or side / 2.0 < smallest:
            out.append(members)
            return
        inside = members[np.all((centre[members] >= box_lo) & (centre[members] < box_hi), axis=1)]
        part = np.floor((centre[inside] - box_lo) / (side / 2.0)).clip(0, 1).astype(np.int64)
        for octant in octants:
            if np.any(np.all(part == octant, axis=1)):
                add(box_lo + octant * (side / 2.0), side / 2.0, members)

    for key in blocks:
        block = unpack_keys(np.array([key]))[0]
        add(block * size, size, _gather(sorted_bins, order, pack_keys(block[None] + near)))
    return out


class SchwarzPreconditioner:
    """Additive Schwarz: ``z = Σ_b R_bᵀ S_bb⁻¹ R_b r`` over overlapping subdomains, each
    principal block of the whole matrix factorised once by dense Cholesky (in float64), its
    factor packed (the lower triangle by rows, one array for all blocks) and held in
    :data:`FACTOR_DTYPE`, and all blocks applied by one compiled call
    (:func:`geoidspline._kernels.fitting.schwarz_apply`, accumulating in float64). The
    blocks are nearly full, so the packed triangle is the least they can be held in.
    Rounding the factors changes the preconditioner, not the problem solved: ``L̃ L̃ᵀ``
    stays positive definite, and conjugate gradients stop on the same rule, at an iterate
    that differs within it (benchmarks/README.md, issue 21's memory: iterations and
    stores of float32 factors against float64 ones)."""

    def __init__(self, system: SymmetricMatrix, index_sets, advance=None):
        sizes = np.array([idx.size for idx in index_sets], dtype=np.int64)
        self.block_at = np.r_[0, np.cumsum(sizes)]
        self.index = np.concatenate(index_sets).astype(np.int64) if index_sets else _EMPTY
        packed_sizes = sizes * (sizes + 1) // 2
        self.factor_at = np.r_[0, np.cumsum(packed_sizes)]
        self.factors = np.empty(int(self.factor_at[-1]), dtype=FACTOR_DTYPE)
        # each block is factorised in float64 here, then rounded into its place
        scratch = np.empty(int(packed_sizes.max()) if sizes.size else 0)
        for b, idx in enumerate(index_sets):
            packed = scratch[:packed_sizes[b]]
            _cholesky(system.principal_lower(idx), packed)
            self.factors[self.factor_at[b]:self.factor_at[b + 1]] = packed
            if advance is not None:
                advance(1)

    def __call__(self, r):
        return schwarz_apply(self.block_at, self.index, self.factor_at, self.factors, r)


def _cholesky(lower, out):
    """The packed Cholesky factor of a principal block into ``out``. The whole matrix is
    positive definite, so are its blocks; should rounding make one not quite so, a
    relative shift of its diagonal is taken (the preconditioner need not be exact)."""
    scale = float(np.abs(np.diag(lower)).max()) if lower.size else 1.0
    shift = 0.0
    while cholesky_packed(lower, shift * scale, out) != 0:
        if shift >= 1e-3:
            raise FitError(f"the local problem of {lower.shape[0]} unknowns could not be factorised")
        shift = 1e-12 if shift == 0.0 else shift * 100.0


def conjugate_gradients(system, rhs, precondition, x0, tolerance, max_iterations=MAX_ITERATIONS):
    """Preconditioned CG on ``system`` (CSR) from ``x0`` until ``sqrt(rᵀ M⁻¹ r) <= tolerance``
    (≈ the energy norm of the error, i.e. the size of the error of the fitted values at
    the sites: scipy's ``cg`` stops on the plain residual norm instead, which says
    nothing in metres). Returns (x, iterations, final sqrt(rᵀ M⁻¹ r))."""
    x = x0.copy()
    r = rhs - system @ x
    z = precondition(r)
    p = z.copy()
    rz = float(r @ z)
    it = 0
    while math.sqrt(max(rz, 0.0)) > tolerance and it < max_iterations:
        q = system @ p
        alpha = rz / float(p @ q)
        x += alpha * p
        r -= alpha * q
        z = precondition(r)
        rz_new = float(r @ z)
        p = z + (rz_new / rz) * p
        rz = rz_new
        it += 1
    return x, it, math.sqrt(max(rz, 0.0))


def carry_over(old: HierarchicalBasis, old_coefficients, new: HierarchicalBasis) -> np.ndarray:
    """A start for the new basis's coefficients: the old spline's coefficients where the
    same B-spline is still active, and a refined B-spline's coefficient passed to those of
    its children that are active (the refinement relation); zero elsewhere."""
    at_old, at_new = old.offsets(), new.offsets()
    x = np.zeros(new.coefficient_count)
    for lv in range(old.levels):
        keys = old.active[lv]
        coefs = np.asarray(old_coefficients[at_old[lv]:at_old[lv + 1]])
        if lv < new.levels and new.active[lv].size:
            kept = isin_sorted(keys, new.active[lv])
            pos = np.searchsorted(new.active[lv], keys[kept])
            x[at_new[lv] + pos] += coefs[kept]
            keys, coefs = keys[~kept], coefs[~kept]
        if keys.size and lv + 1 < new.levels and new.active[lv + 1].size:
            child, parent, weight = children(keys, old.order)
            hit = isin_sorted(child, new.active[lv + 1])
            pos = np.searchsorted(new.active[lv + 1], child[hit])
            np.add.at(x, at_new[lv + 1] + pos, coefs[parent[hit]] * weight[hit])
    return x
