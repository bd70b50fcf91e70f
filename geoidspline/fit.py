"""Fitting: hierarchical overlays of ambient B-splines, solved tile by tile.

The algorithm (Lehmann 2013, §3-4 and §5.2; summarised in METHOD.md):

1. Level 0 takes every cell of spacing ``h0`` that meets the unit sphere over the
   region ("active cells") and every B-spline touching one of them.
2. Data sites are rays: each data direction ``u`` is sampled at radii ``1 + ρ h``
   within the shell, all carrying the value N(u) (the constant radial extension).
   Sites outside the active cells are dropped.
3. The level is fitted to the residual of the levels before it by sparse least
   squares, with a tiny second-difference penalty that only decides coefficients the
   data leave free (cells the data rays miss at the finest levels).
4. The residual on the sphere is measured at every data node of the region; level
   ``ℓ + 1`` (spacing ``h0 / 2^(ℓ+1)``) takes the B-splines touching the cells that
   hold nodes above the tolerance, and is fitted on every site where those B-splines
   are non-zero, so each level is a C^(n-2) spline on all of R³.
5. Each level is split into blocks of ``block_cells`` cells a side (a coefficient
   belongs to the block holding the centre of its support). A block's local problem
   carries the coefficients and sites within ``margin_cells`` cells around it and keeps
   only its own coefficients, so blocks solve independently (in worker processes) and
   still form one spline. Levels with few unknowns are solved whole. Storage tiles
   (cubes of side ``tile_size``, :mod:`geoidspline.store`) group the coefficients of
   all levels the same way, by support centre.

Refinement is a strategy object (:class:`OverlayRefinement`) so that the linearly
independent hierarchical basis of thesis §5.3 can be added beside it.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field, asdict

import numpy as np
import scipy.sparse as sp
import qdldl

from . import _kernels
from . import distributed as _distributed
from .errors import FitError
from .region import Region, GLOBAL
from .spline import AmbientSpline, LevelSpline, directions, tile_of_indices

__all__ = ["FitParameters", "LevelReport", "FitResult", "fit_source", "fit_nodes", "tile_of_indices"]

log = logging.getLogger("geoidspline.fit")

#: How level 0 is computed: by least squares on the data rays (any source), or by
#: quasi-interpolation of a source exact everywhere (:mod:`geoidspline.interpolation`).
FIT_METHODS = ("least-squares", "interpolation")

#: Finest level spacing allowed, in units of the data's node spacing.
MIN_H_PER_DATA_SPACING = 0.5


@dataclass(frozen=True)
class FitParameters:
    """Parameters of a fit. Lengths are on the unit sphere (1 = Earth radius).

    ``h0`` is the level-0 grid spacing; level ℓ has ``h0 / 2**ℓ``. ``tolerance_m`` is the
    largest |error| accepted at the data nodes; refinement stops there or at
    ``max_level``. ``radial_offsets`` are the site radii ``1 + ρ h`` in units of the
    level's spacing. ``rays_per_cell`` caps how many data directions a cell width holds
    at coarse levels (more are thinned out: they would cost time, not accuracy).
    ``regularization`` weighs the second-difference penalty relative to the mean
    diagonal of the normal matrix. An overlay level takes the B-splines whose support
    centre is within ``refine_radius`` cells (per axis) of a node above the tolerance;
    ``None`` means ``order / 2``: every B-spline touching that node (thesis §5.2).
    ``sample_spacing_deg`` is the lattice spacing (degrees) at which a spherical-harmonic
    source is synthesised for the fit (``None``: 90/N degrees for degree N, at most a
    quarter of h0); grids always give their own nodes.
    ``method`` says how level 0 is computed: ``"least-squares"`` (thesis §5) or
    ``"interpolation"``, the quasi-interpolant of :mod:`geoidspline.interpolation`, for
    sources exact everywhere (harmonic models): no linear solve, every coefficient from
    the source within a few cells. Overlays, when the tolerance asks for them, are
    least squares either way.
    ``workers`` and ``scheduler`` say where the blocks of a level are solved
    (:func:`geoidspline.distributed.solve_problems`): ``scheduler=None`` means local
    processes per ``workers`` (1: in this process); ``"local"`` a dask LocalCluster of
    ``workers`` single-threaded processes started for each level; any other value is
    the address of a running dask scheduler (``tcp://``, ``tls://``, ``inproc://`` or
    ``ucx://``), whose workers solve the blocks. Every choice gives the same
    coefficients.
    """

    order: int = 4
    h0: float = 0.1
    tolerance_m: float = 0.5
    max_level: int = 8
    tile_size: float = 0.4
    margin_cells: int = 10
    block_cells: int = 40
    radial_offsets: tuple = (-1.5, -0.9, -0.3, 0.0, 0.3, 0.9, 1.5)
    rays_per_cell: float = 5.0
    regularization: float = 1e-6
    overlay_ridge: float = 0.3
    refine_radius: float | None = 1.0
    untiled_max_unknowns: int = 20_000
    workers: int = 1
    sample_spacing_deg: float | None = None
    scheduler: str | None = None
    method: str = "least-squares"

    def __post_init__(self):
        if not 2 <= self.order <= 8:
            raise FitError(f"spline order must be within 2..8 (4 = cubic, C²), got {self.order}")
        if not 0.0 < self.h0 <= 0.5:
            raise FitError(f"h0 must be within (0, 0.5] on the unit sphere, got {self.h0}")
        if not self.tolerance_m > 0:
            raise FitError(f"tolerance must be positive metres, got {self.tolerance_m}")
        if not 0 <= self.max_level <= 12:
            raise FitError(f"max level must be within 0..12, got {self.max_level}")
        if self.h0 / 2 ** self.max_level * _kernels.MAX_INDEX < 1.5:
            raise FitError("h0 / 2**max_level is too small for the coefficient index range")
        if not self.tile_size >= self.h0:
            raise FitError(f"tile size ({self.tile_size}) must be at least h0 ({self.h0})")
        if self.margin_cells < self.order:
            raise FitError(f"margin_cells must be at least the spline order ({self.order})")
        if self.workers < 1:
            raise FitError(f"workers must be at least 1, got {self.workers}")
        if self.sample_spacing_deg is not None and not 0 < self.sample_spacing_deg <= 5:
            raise FitError(f"sample spacing must be within (0, 5] degrees, got {self.sample_spacing_deg}")
        if self.scheduler is not None and not (
            isinstance(self.scheduler, str)
            and (self.scheduler == "local"
                 or self.scheduler.startswith(_distributed.SCHEDULER_PREFIXES))
        ):
            raise FitError(
                f"scheduler must be 'local' or a dask scheduler address (tcp://, tls://, inproc:// "
                f"or ucx://), got {self.scheduler!r}"
            )

        if self.method not in FIT_METHODS:
            raise FitError(f"fit method must be one of {FIT_METHODS}, got {self.method!r}")

    def spacing(self, level: int) -> float:
        return self.h0 / 2.0 ** level

    def as_dict(self) -> dict:
        data = asdict(self)
        data["radial_offsets"] = list(self.radial_offsets)
        return data


@dataclass
class LevelReport:
    level: int
    h: float
    coefficients: int
    marked_cells: int
    sites: int
    tiles_solved: int
    max_error_m: float
    rms_error_m: float
    nodes_above_tolerance: int
    seconds: float


@dataclass
class FitResult:
    spline: AmbientSpline
    parameters: FitParameters
    region: Region
    levels: list = field(default_factory=list)
    node_count: int = 0
    node_max_error_m: float = float("nan")
    node_rms_error_m: float = float("nan")
    converged: bool = False
    seconds: float = 0.0
    # per-node arrays kept for tile statistics (sphere directions and errors)
    node_directions: np.ndarray | None = None
    node_errors: np.ndarray | None = None
    # refinement stopped because the next level would be finer than the data resolve
    data_limited: bool = False


# ---------------------------------------------------------------------------------
# geometry helpers


def _cube_offsets(lo, hi):
    r = np.arange(lo, hi + 1)
    return np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T


def _sphere_samples(region: Region, spacing_rad: float):
    """Directions covering ``region`` with neighbours closer than ``spacing_rad``."""
    dlat = math.degrees(spacing_rad)
    lats = np.arange(region.south, region.north + dlat, dlat)
    lats = np.clip(lats, -90.0, 90.0)
    out = []
    for lat in lats:
        dlon = dlat / max(math.cos(math.radians(lat)), 1e-3)
        n = max(2, int(math.ceil(region.longitude_span / dlon)) + 1)
        lons = np.linspace(region.west, region.east, n)
        out.append(directions(np.full(n, lat), lons))
    return np.concatenate(out)


def active_cells(h: float, region: Region):
    """Integer indices (M, 3) of the cells of spacing h that meet the sphere over region.

    Exact for the sphere test; for the region a conservative superset (a cell counts
    when its centre direction is within the cell's angular radius of the region).
    """
    samples = _sphere_samples(region, 0.5 * h)
    keys = np.unique(_kernels.pack_keys(np.floor(samples / h).astype(np.int64)))
    # every cell meeting the sphere is next to a cell holding a sample closer than h
    cells = _kernels.unpack_keys(_dilate_keys(keys, -1, 1))
    cells = cells[_kernels.cells_meet_sphere(cells, h, 1.0)]
    if not region.is_global:
        centre = (cells + 0.5) * h
        norm = np.linalg.norm(centre, axis=1)
        lat = np.degrees(np.arcsin(np.clip(centre[:, 2] / norm, -1, 1)))
        lon = np.degrees(np.arctan2(centre[:, 1], centre[:, 0]))
        margin = math.degrees(math.sqrt(3.0) * h / max(1.0 - math.sqrt(3.0) * h, 0.1))
        cells = cells[region.expanded(margin).contains(lat, lon)]
    return cells


_AXIS_STEP = (1 << (2 * _kernels.KEY_BITS), 1 << _kernels.KEY_BITS, 1)


def union_of_shifts(keys, shifts, chunk=1_000_000):
    """Sorted unique ``key + s`` for every key of ``keys`` (sorted, unique) and s in ``shifts``.

    Each shifted copy is sorted, so a stable sort (timsort) only merges runs: 25x faster
    than ``np.unique`` on millions of keys. In chunks of keys, so the transient is
    ``chunk * len(shifts)`` keys, not the whole set times the shifts.
    """
    shifts = np.asarray(shifts, dtype=np.int64)
    parts = []
    for a in range(0, max(keys.size, 1), chunk):
        merged = np.sort((shifts[:, None] + keys[None, a:a + chunk]).ravel(), kind="stable")
        parts.append(merged[np.r_[True, merged[1:] != merged[:-1]]] if merged.size else merged)
    if len(parts) == 1:
        return parts[0]
    merged = np.sort(np.concatenate(parts), kind="stable")
    return merged[np.r_[True, merged[1:] != merged[:-1]]]


def _dilate_keys(keys, lo, hi):
    """Sorted unique keys of ``key + o`` for every offset o in [lo, hi]³.

    Packing is linear in each index, so offsets add to the keys; dilating one axis at
    a time keeps the intermediate arrays (hi - lo + 1) times the result, not its cube.
    """
    keys = np.unique(keys)
    for step in _AXIS_STEP:
        keys = union_of_shifts(keys, np.arange(lo, hi + 1) * step)
    return keys


def _touching_keys(cells, order):
    """Sorted keys of every B-spline non-zero on at least one of ``cells``."""
    return _dilate_keys(_kernels.pack_keys(cells), -(order - 1), 0)


def _covered_cell_keys(coef_keys, order):
    """Sorted keys of the cells on which at least one B-spline of ``coef_keys`` lives."""
    return _dilate_keys(coef_keys, 0, order - 1)


def _isin_sorted(values, sorted_keys):
    pos = np.searchsorted(sorted_keys, values)
    pos = np.minimum(pos, sorted_keys.size - 1)
    return sorted_keys[pos] == values if sorted_keys.size else np.zeros(values.shape, bool)


# ---------------------------------------------------------------------------------
# the local least-squares problem (runs in worker processes)


@dataclass
class LocalProblem:
    """One tile's least-squares problem at one level: everything a worker needs."""

    tile: tuple
    h: float
    order: int
    regularization: float
    ridge: float
    keys: np.ndarray  # sorted unknowns of the local problem
    own: np.ndarray  # bool mask over keys: the coefficients this tile keeps
    points: np.ndarray  # (M, 3) site positions
    values: np.ndarray  # (M,) residual values in metres


def _second_difference_penalty(keys):
    """D^T D for second differences along each axis among triples present in keys."""
    rows, cols, vals = [], [], []
    row0 = 0
    for step in (1 << (2 * _kernels.KEY_BITS), 1 << _kernels.KEY_BITS, 1):
        lower = _isin_sorted(keys - step, keys)
        upper = _isin_sorted(keys + step, keys)
        centre = np.flatnonzero(lower & upper)
        if centre.size == 0:
            continue
        left = np.searchsorted(keys, keys[centre] - step)
        right = np.searchsorted(keys, keys[centre] + step)
        r = row0 + np.arange(centre.size)
        rows += [r, r, r]
        cols += [left, centre, right]
        vals += [np.ones(centre.size), -2.0 * np.ones(centre.size), np.ones(centre.size)]
        row0 += centre.size
    if row0 == 0:
        return sp.csr_matrix((keys.size, keys.size))
    d = sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(row0, keys.size)
    )
    return (d.T @ d).tocsr()


def solve_local_problem(problem: LocalProblem):
    """Solve one local problem; return (own keys, own coefficients, solve seconds)."""
    start = time.perf_counter()
    keys = problem.keys
    indptr, indices, data, rhs = _kernels.normal_equations(
        np.ascontiguousarray(problem.points), problem.values, problem.h, problem.order, keys
    )
    upper = sp.csc_matrix((data, indices, indptr), shape=(keys.size, keys.size))
    diag = upper.diagonal()
    scale = float(diag[diag > 0].mean()) if np.any(diag > 0) else 1.0
    penalty = sp.triu(_second_difference_penalty(keys), format="csc")
    system = upper + (problem.regularization * scale) * penalty
    system = system + sp.identity(keys.size, format="csc") * (problem.ridge * scale)
    # qdldl: LDL^T with AMD ordering, about 3x faster than SuperLU on these SPD systems
    solution = qdldl.Solver(system.tocsc()).solve(rhs)
    return keys[problem.own], solution[problem.own], time.perf_counter() - start


# ---------------------------------------------------------------------------------
# node bookkeeping


@dataclass
class _Nodes:
    """Data nodes of a fit: directions, values, region mask and thinning strides."""

    latitude: np.ndarray
    longitude: np.ndarray
    values: np.ndarray
    directions: np.ndarray
    in_region: np.ndarray
    row: np.ndarray
    col: np.ndarray
    dlat_rad: float
    dlon_rad: float

    @classmethod
    def from_sample(cls, sample, region: Region):
        lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
        row2, col2 = np.meshgrid(
            np.arange(sample.latitude.size), np.arange(sample.longitude.size), indexing="ij"
        )
        values = np.asarray(sample.undulation, dtype=float).ravel()
        keep = np.isfinite(values)
        # a pole row holds one point: keep a single node there
        pole = (np.abs(lat2.ravel()) >= 90.0) & (col2.ravel() > 0)
        keep &= ~pole
        lat = lat2.ravel()[keep]
        lon = lon2.ravel()[keep]
        dlat = np.radians(np.diff(sample.latitude).min()) if sample.latitude.size > 1 else np.pi
        dlon = np.radians(np.diff(sample.longitude).min()) if sample.longitude.size > 1 else 2 * np.pi
        return cls(
            latitude=lat,
            longitude=lon,
            values=values[keep],
            directions=directions(lat, lon),
            in_region=region.contains(lat, lon),
            row=row2.ravel()[keep],
            col=col2.ravel()[keep],
            dlat_rad=float(dlat),
            dlon_rad=float(dlon),
        )

    def thinned(self, h, rays_per_cell):
        """Mask of the nodes kept as rays at spacing h (about rays_per_cell per cell width)."""
        target = h / rays_per_cell
        lat_stride = max(1, int(target // self.dlat_rad))
        cos_lat = np.maximum(np.cos(np.radians(self.latitude)), 1e-6)
        lon_stride = np.maximum(1, np.floor(target / (self.dlon_rad * cos_lat))).astype(np.int64)
        return (self.row % lat_stride == 0) & (self.col % lon_stride == 0)


# ---------------------------------------------------------------------------------
# refinement strategy


class OverlayRefinement:
    """Hierarchical overlays (thesis §5.2): each level fits the residual of the ones
    before it on the B-splines touching the cells where the tolerance is violated."""

    name = "overlay"

    def __init__(self, refine_radius=None):
        self.refine_radius = refine_radius

    def level_keys(self, level, h, order, region, violating_directions):
        """Coefficient keys of a level, the number of cells marked, and the keys of the
        cells sites may lie in (``None``: wherever a level B-spline is non-zero)."""
        if level == 0:
            # The domain Ω is the active cells over the region; sites stay inside it so
            # that every site sees all of its B-splines and constants are reproduced.
            cells = active_cells(h, region)
            if cells.size == 0:
                return np.empty(0, dtype=np.int64), 0, None
            return _touching_keys(cells, order), len(cells), np.unique(_kernels.pack_keys(cells))
        if violating_directions.size == 0:
            return np.empty(0, dtype=np.int64), 0, None
        position = violating_directions / h
        cells = np.floor(position).astype(np.int64)
        n_cells = np.unique(_kernels.pack_keys(cells)).size
        radius = order / 2.0 if self.refine_radius is None else self.refine_radius
        if radius >= order / 2.0:
            return _touching_keys(cells, order), n_cells, None
        keys = []
        for chunk in range(0, len(position), 200_000):
            pos = position[chunk:chunk + 200_000]
            cand = cells[chunk:chunk + 200_000, None, :] + _cube_offsets(-(order - 1), 0)[None]
            near = np.all(np.abs(cand + order / 2.0 - pos[:, None, :]) <= radius, axis=2)
            keys.append(np.unique(_kernels.pack_keys(cand[near])))
        return np.unique(np.concatenate(keys)), n_cells, None


# ---------------------------------------------------------------------------------
# the driver


def _sites_for_level(nodes: _Nodes, ray_mask, h, order, keys, radial_offsets, site_cells=None):
    """Site positions and node indices for one level (rays through the kept nodes)."""
    covered = _covered_cell_keys(keys, order) if site_cells is None else site_cells
    node_idx = np.flatnonzero(ray_mask)
    pts_all, idx_all = [], []
    for rho in radial_offsets:
        pts = nodes.directions[node_idx] * (1.0 + rho * h)
        cells = np.floor(pts / h).astype(np.int64)
        inside = _isin_sorted(_kernels.pack_keys(cells), covered)
        if rho != 0.0:
            # sites off the sphere count only inside cells that meet the sphere (Ω)
            inside[inside] = _kernels.cells_meet_sphere(cells[inside], h, 1.0)
        pts_all.append(pts[inside])
        idx_all.append(node_idx[inside])
    return np.concatenate(pts_all), np.concatenate(idx_all)


def _local_problems(level, h, params: FitParameters, keys, points, values, force_tiles=False, overlay=None):
    order = params.order
    # Overlays fit residuals, which are near zero wherever the data do not pin them
    # down: a ridge keeps their coefficients there small (level 0 must not be biased).
    overlay = level > 0 if overlay is None else overlay
    ridge = params.overlay_ridge if overlay else 1e-10
    if keys.size <= params.untiled_max_unknowns and not force_tiles:
        yield LocalProblem(
            tile=("whole",), h=h, order=order, regularization=params.regularization, ridge=ridge,
            keys=keys, own=np.ones(keys.size, bool), points=points, values=values,
        )
        return
    idx = _kernels.unpack_keys(keys)
    # solve blocks hold block_cells cells of this level a side, so every level's local
    # problems have about the same size; storage tiles are independent of them
    size = params.block_cells * h
    tiles = tile_of_indices(idx, h, order, size)
    tile_keys = _kernels.pack_keys(tiles)
    unique_tiles, tile_inverse = np.unique(tile_keys, return_inverse=True)
    margin = params.margin_cells * h
    reach = int(math.ceil(margin / size))
    site_bins = _kernels.pack_keys(np.floor(points / size).astype(np.int64))
    bin_order = np.argsort(site_bins, kind="stable")
    sorted_bins = site_bins[bin_order]
    neighbour = _cube_offsets(-reach, reach)
    # coefficients grouped by block, to gather a block's neighbourhood without a scan
    coef_order = np.argsort(tile_inverse, kind="stable")
    coef_start = np.searchsorted(tile_inverse[coef_order], np.arange(unique_tiles.size + 1))
    coef_reach = int(math.ceil((margin + order * h) / size))
    coef_neighbour = _cube_offsets(-coef_reach, coef_reach)
    for t, tkey in enumerate(unique_tiles):
        tile = _kernels.unpack_keys(np.array([tkey]))[0]
        lo = tile * size - margin
        hi = (tile + 1) * size + margin
        wanted = _kernels.pack_keys(tile[None, :] + neighbour)
        starts = np.searchsorted(sorted_bins, wanted, side="left")
        stops = np.searchsorted(sorted_bins, wanted, side="right")
        chosen = np.concatenate([bin_order[a:b] for a, b in zip(starts, stops)])
        if chosen.size:
            p = points[chosen]
            chosen = chosen[np.all((p >= lo) & (p < hi), axis=1)]
        # unknowns: every coefficient non-zero somewhere in the local box
        cell_lo = np.floor(lo / h).astype(np.int64) - (order - 1)
        cell_hi = np.floor(hi / h).astype(np.int64)
        wanted_blocks = _kernels.pack_keys(tile[None, :] + coef_neighbour)
        near = np.minimum(np.searchsorted(unique_tiles, wanted_blocks), unique_tiles.size - 1)
        near = near[unique_tiles[near] == wanted_blocks]
        candidates = np.concatenate([coef_order[coef_start[n]:coef_start[n + 1]] for n in near])
        candidates = candidates[np.all((idx[candidates] >= cell_lo) & (idx[candidates] <= cell_hi), axis=1)]
        local = np.sort(candidates)
        own = tile_inverse[local] == t
        yield LocalProblem(
            tile=tuple(int(v) for v in tile), h=h, order=order,
            regularization=params.regularization, ridge=ridge, keys=keys[local], own=own,
            points=points[chosen], values=values[chosen],
        )


def _solve_level(problems, params: FitParameters, progress=None):
    results = _distributed.solve_problems(problems, params.workers, params.scheduler, progress)
    keys = np.concatenate([r[0] for r in results]) if results else np.empty(0, np.int64)
    coefs = np.concatenate([r[1] for r in results]) if results else np.empty(0)
    order = np.argsort(keys)
    return keys[order], coefs[order], len(results)


def fit_nodes(sample, region: Region, params: FitParameters, refinement=None, progress=None,
              force_tiles=False, base_is_overlay=False, first_level=None) -> FitResult:
    """Fit the nodes of a :class:`~geoidspline.sources.NodeSample` over ``region``.

    ``sample`` must cover the region plus the support margin of level 0 (see
    :func:`fit_source`, which asks the source for exactly that). ``progress``, when
    given, is called with the number of local problems just solved. With
    ``base_is_overlay`` the sample holds residuals of an existing spline (a regional
    update) and level 0 is refined and regularised like any overlay. ``first_level``, a
    :class:`LevelSpline` computed already (by quasi-interpolation), stands as level 0;
    ``(level, seconds, lattice points)`` of it go into its report.
    """
    refinement = refinement or OverlayRefinement(params.refine_radius)
    start = time.perf_counter() - (first_level[1] if first_level is not None else 0.0)
    nodes = _Nodes.from_sample(sample, region)
    if not np.any(nodes.in_region):
        raise FitError(f"no data nodes inside the region {region.as_tuple()}")
    region_dirs = nodes.directions[nodes.in_region]
    errors = nodes.values[nodes.in_region].copy()  # residual N - S at region nodes
    levels: list[LevelSpline] = []
    reports: list[LevelReport] = []
    converged = False
    violating = region_dirs[np.abs(errors) > params.tolerance_m] if base_is_overlay else region_dirs
    # a level much finer than the data spacing is not determined between the nodes
    data_spacing = max(nodes.dlat_rad, nodes.dlon_rad * float(np.cos(np.radians(np.abs(nodes.latitude)).mean())))
    data_limited = False
    for level in range(params.max_level + 1):
        t0 = time.perf_counter()
        h = params.spacing(level)
        if level > 0 and h < MIN_H_PER_DATA_SPACING * data_spacing:
            data_limited = True
            log.warning(
                "stopping at level %d: level %d (h=%.4g) would be finer than %.1f x the data spacing "
                "(%.4g on the unit sphere); sample a model source finer with --sample-spacing",
                level - 1, level, h, MIN_H_PER_DATA_SPACING, data_spacing,
            )
            break
        if level == 0 and first_level is not None:
            lv, seconds_before, site_count = first_level
            t0 -= seconds_before
            marked, solved = 0, 0
        else:
            keys, marked, site_cells = refinement.level_keys(level, h, params.order, region, violating)
            if keys.size == 0:
                converged = True
                break
            ray_mask = nodes.thinned(h, params.rays_per_cell)
            points, node_of_site = _sites_for_level(
                nodes, ray_mask, h, params.order, keys, params.radial_offsets, site_cells
            )
            values = nodes.values[node_of_site] - AmbientSpline(levels).evaluate_points(points) if levels \
                else nodes.values[node_of_site].copy()
            problems = list(_local_problems(level, h, params, keys, points, values, force_tiles,
                                            overlay=level > 0 or base_is_overlay))
            own_keys, own_coefs, solved = _solve_level(problems, params, progress)
            if own_keys.size != keys.size:
                raise FitError(f"level {level}: tiles returned {own_keys.size} of {keys.size} coefficients")
            lv = LevelSpline(level, h, params.order, own_keys, own_coefs)
            site_count = points.shape[0]
        levels.append(lv)
        errors -= AmbientSpline([lv]).evaluate_points(region_dirs)
        above = np.abs(errors) > params.tolerance_m
        violating = region_dirs[above]
        report = LevelReport(
            level=level, h=h, coefficients=len(lv), marked_cells=int(marked), sites=int(site_count),
            tiles_solved=solved, max_error_m=float(np.abs(errors).max()),
            rms_error_m=float(np.sqrt(np.mean(errors**2))), nodes_above_tolerance=int(above.sum()),
            seconds=time.perf_counter() - t0,
        )
        reports.append(report)
        log.info(
            "level %d: h=%.6g, %d coefficients, %d sites, max |error| %.4f m, %d nodes above %.4g m (%.1f s)",
            level, h, len(lv), site_count, report.max_error_m, report.nodes_above_tolerance,
            params.tolerance_m, report.seconds,
        )
        if not above.any():
            converged = True
            break
    spline = AmbientSpline(levels)
    return FitResult(
        spline=spline, parameters=params, region=region, levels=reports,
        node_count=int(errors.size), node_max_error_m=float(np.abs(errors).max()),
        node_rms_error_m=float(np.sqrt(np.mean(errors**2))), converged=converged,
        seconds=time.perf_counter() - start, node_directions=region_dirs, node_errors=errors,
        data_limited=data_limited,
    )


def support_margin_deg(params: FitParameters) -> float:
    """Angular reach (degrees) of the level-0 B-splines beyond the region's cells."""
    chord = params.order * params.h0 * math.sqrt(3.0)
    return math.degrees(2.0 * math.asin(min(1.0, chord / 2.0)))


def fit_source(source, region: Region | None = None, params: FitParameters | None = None,
               progress=None, force_tiles=False) -> FitResult:
    """Fit a geoid source (grid or model) over ``region`` (default: global)."""
    params = params or FitParameters()
    region = region or GLOBAL
    data_region = region.expanded(support_margin_deg(params))
    spacing = params.sample_spacing_deg
    if params.method == "interpolation":
        return _fit_by_interpolation(source, region, params, spacing, progress, force_tiles)
    if spacing is None and hasattr(source, "lattice_step"):
        # a model's own default (90/N degrees) can leave a low-degree model with a
        # handful of nodes: keep at least a few per level-0 cell
        spacing = min(source.lattice_step(None), math.degrees(params.h0) / 4.0)
    sample = source.nodes(_clip_to_extent(data_region, source), spacing_deg=spacing)
    return fit_nodes(sample, region, params, progress=progress, force_tiles=force_tiles)


def check_method(source, params: FitParameters):
    """Raise :class:`FitError` when ``params.method`` cannot fit ``source``."""
    if params.method == "interpolation" and (
        getattr(source.provenance, "kind", None) != "harmonic" or not hasattr(source, "lattice_step")
    ):
        raise FitError(
            "fit method 'interpolation' needs a source exact everywhere (a spherical-harmonic "
            f"model); {source.provenance.source} is a {source.provenance.kind}: fit it by least squares"
        )


def _fit_by_interpolation(source, region, params, spacing, progress, force_tiles):
    """Level 0 by quasi-interpolation of an exact source, then least-squares overlays."""
    from .interpolation import interpolate_level, lattice_spacing

    check_method(source, params)
    start = time.perf_counter()
    h = params.h0
    cells = active_cells(h, region)
    if cells.size == 0:
        raise FitError(f"no cells of spacing {h} meet the sphere over the region {region.as_tuple()}")
    keys = _touching_keys(cells, params.order)
    spacing = lattice_spacing(source, h, spacing)
    coefficients, band, lattice_points = interpolate_level(source, keys, h, params.order, spacing)
    level0 = LevelSpline(0, h, params.order, keys, coefficients)
    # the band's lattice holds every node of the region: it is the nodes' sample too
    return fit_nodes(band, region, params, progress=progress, force_tiles=force_tiles,
                     first_level=(level0, time.perf_counter() - start, lattice_points))


def _clip_to_extent(region: Region, source) -> Region:
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
