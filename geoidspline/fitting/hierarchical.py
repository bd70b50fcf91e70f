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
free, solved whole (qdldl) or in local blocks (:func:`block_problems`, §5.3.3).

The result is a normal :class:`geoidspline.fitting.result.FitResult`: each active B-spline of
level ℓ is a coefficient of level ℓ, and the sum of the levels is the spline, so stores
of either method are written, queried, updated and exported the same way.
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
import math
import time
from dataclasses import dataclass

import numpy as np
import qdldl
import scipy.sparse as sp

from ..bspline.keys import covered_cell_keys, cube_offsets, isin_sorted, pack_keys, unpack_keys
from ..errors import FitError
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.hierarchical import Domain, HierarchicalBasis, HierarchicalRefinement, normal_matrix
from ..sphere.region import Region
from .executors import Executor
from .least_squares import _second_difference_penalty
from .parameters import MIN_H_PER_DATA_SPACING, FitParameters
from .progress import as_progress
from .result import FitResult, LevelReport
from .sites import DataNodes, sites_for_level


__all__ = ["fit_hierarchical", "leaf_sites", "solve_basis", "block_problems", "HierarchicalProblem"]

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

#: Site radii ``1 + ρ h`` of the rays, used when ``FitParameters.radial_offsets`` is
#: left at its default: on the sphere only. The thin basis (:data:`SHELL`) holds two or
#: three B-splines across the sphere and cannot stay constant along rays as long as the
#: overlays' (±1.5 h); its fine levels carry the whole undulation, not a small residual,
#: so that misfit along the rays shows on the sphere (Andes: 67,973 coefficients and
#: the tolerance not reached with ±1.5 h, 28,021 with ±0.15 h, 21,472 with 0). The
#: combinations that vanish on the sphere are left to the penalty: no query sees them.
#: Measured in benchmarks/README.md.
RADIAL_OFFSETS = (0.0,)

#: Up to this many coefficients the whole basis is one problem (one sparse LDLᵀ
#: factorisation); above, local problems per block (:func:`block_problems`). The
#: factorisation grows about as n^1.7 (global EGM96 at 0.1 m: 15,082 unknowns 14 s,
#: 60,298 unknowns 151 s), the blocks about linearly (238,165 unknowns: 131 blocks of
#: 983,795 unknowns in all, 388 s of solves, 197 s on two workers), so blocks would be
#: faster from about 40,000 on; but blocks leave seams between the nodes (global 0.1 m:
#: 1.37 m at cell centres on the plane x = 0.4 between two blocks, nodes within 0.114 m),
#: so the whole problem is kept as long as it is affordable.
WHOLE_MAX_UNKNOWNS = 100_000

#: The margin of a local problem is one support of the level this many above the
#: coarsest level its block owns a B-spline of. On a leaf of level ℓ the B-splines of
#: level ℓ - 1 are non-zero too, and theirs couple to level ℓ - 2: with one level up,
#: blocks needed a ridge of 1e-4 to agree and then refined more than the whole problem
#: (55..72N 30..5W at 0.1 m: 5,594 coefficients and 0.144 m at cell centres against
#: 3,729 and 0.078 m); with two levels up and a ridge of 1e-8 they give the whole
#: problem's fit (3,729 and 0.078 m; the Andes part at 0.5 m: 5,323 and 0.319 m both).
MARGIN_LEVELS_UP = 2

#: Ridge relative to the mean diagonal of AᵀA: keeps B-splines no site sees decided.
RIDGE = 1e-10

#: The ridge of a local problem. With sites on the sphere only, the thin basis has
#: combinations that vanish on the sphere (a null space the penalty decides); a block
#: whose margin is too narrow decides them its own way, and the coefficients kept from
#: different blocks then no longer cancel on the sphere (Andes, level 0 alone, margin
#: one level-0 support: 99 m at the nodes against 15 m). With the margin of
#: :data:`MARGIN_LEVELS_UP` a tiny ridge suffices (1e-4 biased the fit: see above).
BLOCK_RIDGE = 1e-8

_EMPTY = np.empty(0, dtype=np.int64)


def leaf_sites(nodes: DataNodes, basis: HierarchicalBasis, params: FitParameters):
    """One ``(points, node index)`` pair per level: rays through the nodes thinned at
    that level's spacing, at its radii, inside its leaves and outside every finer
    active support (there a finer B-spline would reach into the leaf)."""
    out = []
    for lv in range(basis.levels):
        h = basis.spacing(lv)
        if basis.leaves[lv].size == 0:
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


def _solve(basis: HierarchicalBasis, points, values, regularization, ridge=None):
    matrix, rhs = normal_matrix(basis, [(p, v) for p, v in zip(points, values)])
    diagonal = matrix.diagonal()
    system = matrix + _penalty(basis, diagonal, regularization)
    scale = float(diagonal[diagonal > 0].mean()) if np.any(diagonal > 0) else 1.0
    system = system + sp.identity(basis.coefficient_count, format="csc") * ((RIDGE if ridge is None else ridge) * scale)
    return qdldl.Solver(sp.triu(system, format="csc")).solve(rhs)


@dataclass
class HierarchicalProblem:
    """One block's local problem over the hierarchical basis: every active B-spline (of
    any level) whose support meets the block's box, the sites and leaves in the box.
    The B-splines the block keeps (``own``) have their whole support in the box."""

    block: tuple
    order: int
    h0: float
    regularization: float
    active: tuple  # per level: sorted keys of the local unknowns
    leaves: tuple  # per level: sorted keys of the leaves meeting the box
    own: tuple  # per level: bool mask over active[ℓ]
    points: tuple  # per level: (M, 3) sites in the box
    values: tuple  # per level: (M,) values at them

    def digest(self) -> bytes:
        """A hash of everything the solution depends on: equal digests, equal solutions
        (a refinement step leaves most blocks as they were)."""
        h = hashlib.blake2b(repr((self.block, self.order, self.h0, self.regularization)).encode(), digest_size=20)
        for name, part in zip("alopv", (self.active, self.leaves, self.own, self.points, self.values)):
            for level, array in enumerate(part):
                if array.size:  # a level added elsewhere (empty here) changes nothing here
                    h.update(f"|{name}{level}:".encode())
                    h.update(np.ascontiguousarray(array).tobytes())
        return h.digest()

    def solve(self):
        """(own keys per level, own coefficients per level, solve seconds)."""
        start = time.perf_counter()
        basis = HierarchicalBasis(Domain(_EMPTY, self.h0), self.order, self.active, self.leaves)
        coefs = _solve(basis, self.points, self.values, self.regularization, BLOCK_RIDGE)
        at = basis.offsets()
        keys = tuple(a[o] for a, o in zip(self.active, self.own))
        values = tuple(coefs[at[lv]:at[lv + 1]][o] for lv, o in enumerate(self.own))
        return keys, values, time.perf_counter() - start


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


def block_keys(basis: HierarchicalBasis, size: float) -> np.ndarray:
    """Sorted keys of the blocks (cubes of side ``size``) holding an active support centre."""
    n = basis.order
    return np.unique(np.concatenate([
        pack_keys(np.floor((unpack_keys(keys) + n / 2.0) * basis.spacing(lv) / size).astype(np.int64))
        for lv, keys in enumerate(basis.active)]))


def block_problems(basis: HierarchicalBasis, points, values, params: FitParameters):
    """Local problems (thesis §5.3.3): blocks of ``tile_size`` (the store's tiles) own
    the B-splines whose support centre they hold; a block's problem carries every active
    B-spline whose support meets the block grown by a margin and the sites there.

    The margin is one support, ``order * h``, of the coarsest level the block owns a
    B-spline of: the support of every B-spline a block keeps lies in its problem (the
    thesis's condition; half that margin would do) with half a support to spare, which
    keeps the truncation of the least-squares coupling small (with half the margin,
    blocks differed from the whole problem by 0.1 m at nodes of the Andes at 0.5 m
    tolerance). Requirement 5.3 keeps level ℓ - 2 and coarser away from level-ℓ
    supports, so where a region is refined the margin shrinks with its levels."""
    n = basis.order
    size = params.tile_size
    levels = basis.levels
    spans, fbins, sbins, cbins = [], [], [], []
    for lv in range(levels):
        h = basis.spacing(lv)
        lo = unpack_keys(basis.active[lv]) * h
        spans.append((lo, lo + n * h))
        fbins.append(_binned(lo + n * h / 2.0, size))
        sbins.append(_binned(points[lv], size) if points[lv].shape[0] else (np.empty(0, np.int64),) * 2)
        cells = unpack_keys(basis.leaves[lv]) * h
        cbins.append((cells, _binned(cells + h / 2.0, size)))
    blocks = block_keys(basis, size)
    coarsest = np.full(blocks.size, levels - 1)
    for lv in range(levels - 1, -1, -1):
        coarsest[isin_sorted(blocks, fbins[lv][0])] = lv
    reach = int(math.ceil(1.5 * n * params.h0 / size))
    f_near = cube_offsets(-reach, reach)
    reach = int(math.ceil(n * params.h0 / size))
    s_near = cube_offsets(-reach, reach)
    for key, top in zip(blocks, coarsest):
        block = unpack_keys(np.array([key]))[0]
        margin = n * basis.spacing(max(int(top) - MARGIN_LEVELS_UP, 0))
        box_lo = block * size - margin
        box_hi = (block + 1) * size + margin
        active, leaves, own, pts, vals = [], [], [], [], []
        for lv in range(levels):
            h = basis.spacing(lv)
            sorted_bins, order = fbins[lv]
            cand = _gather(sorted_bins, order, pack_keys(block[None] + f_near))
            lo, hi = spans[lv]
            cand = cand[np.all((lo[cand] < box_hi) & (hi[cand] > box_lo), axis=1)]
            active.append(basis.active[lv][cand])
            centre = lo[cand] + n * h / 2.0
            own.append(np.all(np.floor(centre / size).astype(np.int64) == block, axis=1))
            sorted_bins, order = sbins[lv]
            chosen = _gather(sorted_bins, order, pack_keys(block[None] + s_near))
            if chosen.size:
                p = points[lv][chosen]
                chosen = chosen[np.all((p >= box_lo) & (p < box_hi), axis=1)]
            pts.append(points[lv][chosen])
            vals.append(values[lv][chosen])
            cells, (sorted_bins, order) = cbins[lv]
            near = _gather(sorted_bins, order, pack_keys(block[None] + f_near))
            near = near[np.all((cells[near] < box_hi) & (cells[near] + h > box_lo), axis=1)]
            leaves.append(basis.leaves[lv][near])
        yield HierarchicalProblem(
            block=tuple(int(v) for v in block), order=n, h0=params.h0, regularization=params.regularization,
            active=tuple(active), leaves=tuple(leaves), own=tuple(own), points=tuple(pts), values=tuple(vals),
        )


def solve_basis(basis: HierarchicalBasis, points, values, params: FitParameters, force_tiles=False,
                executor: Executor | None = None, progress=None, name="hierarchical fit", cache=None):
    """Coefficients (all levels, in :meth:`HierarchicalBasis.offsets` order) of the
    least-squares fit of ``values`` at ``points`` (one array each per level) over the
    whole basis: one problem up to :data:`WHOLE_MAX_UNKNOWNS` unknowns, else local
    problems per block (:func:`block_problems`) solved by ``executor``; and the number
    of problems solved. ``progress`` (:mod:`geoidspline.fitting.progress`) is told of
    each problem solved or reused, as the stage ``name``. ``cache`` (a dict kept across
    refinement steps) maps a block's :meth:`HierarchicalProblem.digest` to its result:
    a block whose problem has not changed is not solved again."""
    progress = as_progress(progress)
    if basis.coefficient_count <= WHOLE_MAX_UNKNOWNS and not force_tiles:
        with progress.stage(name, 1, "block") as advance:
            coefs = _solve(basis, points, values, params.regularization)
            advance(1)
        return coefs, 1
    cache = {} if cache is None else cache
    reused, digests, sizes = [], [], []

    def changed(problems, advance):
        for problem in problems:
            digest = problem.digest()
            if digest in cache:
                reused.append((digest, cache[digest]))
                advance(1)
            else:
                digests.append(digest)
                sizes.append(int(sum(a.size for a in problem.active)))
                yield problem

    with progress.stage(name, int(block_keys(basis, params.tile_size).size), "block") as advance:
        solved = (executor or Executor()).solve(changed(block_problems(basis, points, values, params), advance),
                                                advance)
    cache.clear()  # only this step's blocks can recur in the next
    cache.update(reused)
    cache.update(zip(digests, solved))
    at = basis.offsets()
    coefs = np.full(basis.coefficient_count, np.nan)
    for keys, values_, _ in solved + [r for _, r in reused]:
        for lv, (k, v) in enumerate(zip(keys, values_)):
            coefs[at[lv] + np.searchsorted(basis.active[lv], k)] = v
    if np.isnan(coefs).any():
        raise FitError(f"blocks returned {int((~np.isnan(coefs)).sum())} of {coefs.size} coefficients")
    log.info("%s: %d blocks solved (%d unknowns in all, at most %d in one; %.0f s of solves), %d unchanged since "
             "the last step", name, len(solved), sum(sizes), max(sizes, default=0), sum(r[2] for r in solved),
             len(reused))
    return coefs, len(solved)


def _finest_level(params: FitParameters, nodes: DataNodes) -> int:
    """Finest level allowed: ``max_level``, and not finer than the data resolve."""
    level = 0
    while level < params.max_level and params.spacing(level + 1) >= MIN_H_PER_DATA_SPACING * nodes.spacing_rad:
        level += 1
    return level


def fit_hierarchical(nodes: DataNodes, coverage, region: Region, params: FitParameters, progress=None,
                     force_tiles=False, executor: Executor | None = None, start=None, on_step=None,
                     interpolant=None) -> FitResult:
    """Fit ``nodes`` (:class:`~geoidspline.fitting.sites.DataNodes`) over ``region`` with
    the hierarchical basis; :func:`geoidspline.fitting.driver.fit_nodes` calls it for
    ``params.refinement == "hierarchical"``. ``coverage`` goes into the result as it is.

    ``on_step(basis, points, values, coefficients)``, when given, is called after each
    refinement step's fit (points and values per leaf level), e.g. to measure the
    normal matrices (benchmarks/hierarchical_vs_overlays.py). ``interpolant`` (an exact
    source's :class:`~geoidspline.fitting.hierarchical_interpolation.HierarchicalQuasiInterpolant`)
    gives each step's coefficients, on its basis (``shell``), instead of least squares.
    """
    start = time.perf_counter() if start is None else start
    progress = as_progress(progress)
    if params.radial_offsets == FitParameters.radial_offsets:
        params = dataclasses.replace(params, radial_offsets=RADIAL_OFFSETS)
    region_dirs = nodes.directions[nodes.in_region]
    region_values = nodes.values[nodes.in_region]
    finest = _finest_level(params, nodes)
    strategy = HierarchicalRefinement(params.order, params.h0, MARK_RADIUS,
                                      SHELL if interpolant is None else interpolant.shell)
    basis = strategy.initial(region)
    if basis.coefficient_count == 0:
        raise FitError(f"no cells of spacing {params.h0} meet the sphere over the region {region.as_tuple()}")
    reports = []
    cache = {}  # block results by problem digest, across steps
    converged = data_limited = False
    while True:
        t0 = time.perf_counter()
        step = len(reports)
        if interpolant is None:
            sites = leaf_sites(nodes, basis, params)
            points, values = [p for p, _ in sites], [nodes.values[i] for _, i in sites]
            coefs, solved = solve_basis(basis, points, values, params, force_tiles, executor, progress,
                                        f"hierarchical step {step} ({basis.coefficient_count:,} unknowns)", cache)
        else:  # §5.3.1: the hierarchical quasi-interpolant, no solve
            (coefs, points, values), solved = interpolant.coefficients(basis, progress), 0
        if on_step is not None:
            on_step(basis, points, values, coefs)
        spline = AmbientSpline(basis.level_splines(coefs))
        errors = region_values - spline.evaluate_points(region_dirs)
        above = np.abs(errors) > params.tolerance_m
        top = basis.levels - 1
        reports.append(LevelReport(
            level=top, h=basis.spacing(top), coefficients=basis.coefficient_count,
            marked_cells=int(basis.leaves[top].size), sites=int(sum(p.shape[0] for p in points)),
            blocks_solved=solved, max_error_m=float(np.abs(errors).max()),
            rms_error_m=float(np.sqrt(np.mean(errors ** 2))), nodes_above_tolerance=int(above.sum()),
            seconds=time.perf_counter() - t0,
        ))
        log.info("hierarchical step %d: levels 0-%d, %d coefficients (%s), max |error| %.4f m, %d nodes above "
                 "%.4g m (%.1f s)", step, top, basis.coefficient_count,
                 "/".join(str(a.size) for a in basis.active), reports[-1].max_error_m, int(above.sum()),
                 params.tolerance_m, reports[-1].seconds)
        if not above.any():
            converged = True
            break
        refined = strategy.refine(basis, region_dirs[above], max_level=finest)
        if refined is basis:
            data_limited = finest < params.max_level
            break
        basis = refined
    return FitResult(
        spline=spline, parameters=params, region=region, levels=reports,
        node_count=int(errors.size), node_max_error_m=float(np.abs(errors).max()),
        node_rms_error_m=float(np.sqrt(np.mean(errors ** 2))), converged=converged,
        seconds=time.perf_counter() - start, node_directions=region_dirs, node_errors=errors,
        data_limited=data_limited, coverage=coverage, basis=basis,
    )
