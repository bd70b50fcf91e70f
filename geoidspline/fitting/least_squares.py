"""Least squares of one level, block by block (thesis §4.3, §5.3.3).

Each level is split into blocks of ``block_cells`` cells a side (a coefficient belongs
to the block holding the centre of its support). A block's local problem carries the
coefficients and sites within ``margin_cells`` cells around it and keeps only its own
coefficients, so blocks solve independently (in worker processes) and still form one
spline. Levels with few unknowns are solved whole.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import qdldl
import scipy.sparse as sp

from .._kernels.fitting import normal_equations
from ..bspline.keys import AXIS_STEPS, cube_offsets, isin_sorted, pack_keys, unpack_keys
from ..bspline.level import cube_of_support_centres
from .parameters import FitParameters


@dataclass
class LocalProblem:
    """One block's least-squares problem at one level: everything a worker needs."""

    block: tuple  # the block's cube index, or ("whole",) for a level solved at once
    h: float
    order: int
    regularization: float
    ridge: float
    keys: np.ndarray  # sorted unknowns of the local problem
    own: np.ndarray  # bool mask over keys: the coefficients this tile keeps
    points: np.ndarray  # (M, 3) site positions
    values: np.ndarray  # (M,) residual values in metres

    def solve(self):
        """:func:`solve_local_problem` of this problem."""
        return solve_local_problem(self)


def _second_difference_penalty(keys):
    """D^T D for second differences along each axis among triples present in keys."""
    rows, cols, vals = [], [], []
    row0 = 0
    for step in AXIS_STEPS:
        lower = isin_sorted(keys - step, keys)
        upper = isin_sorted(keys + step, keys)
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
    indptr, indices, data, rhs = normal_equations(
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


def local_problems(level, h, params: FitParameters, keys, points, values, force_tiles=False, overlay=None):
    order = params.order
    # Overlays fit residuals, which are near zero wherever the data do not pin them
    # down: a ridge keeps their coefficients there small (level 0 must not be biased).
    overlay = level > 0 if overlay is None else overlay
    ridge = params.overlay_ridge if overlay else 1e-10
    if keys.size <= params.untiled_max_unknowns and not force_tiles:
        yield LocalProblem(
            block=("whole",), h=h, order=order, regularization=params.regularization, ridge=ridge,
            keys=keys, own=np.ones(keys.size, bool), points=points, values=values,
        )
        return
    idx = unpack_keys(keys)
    # solve blocks hold block_cells cells of this level a side, so every level's local
    # problems have about the same size; storage tiles are independent of them
    size = params.block_cells * h
    tiles = cube_of_support_centres(idx, h, order, size)
    tile_keys = pack_keys(tiles)
    unique_tiles, tile_inverse = np.unique(tile_keys, return_inverse=True)
    margin = params.margin_cells * h
    reach = int(math.ceil(margin / size))
    site_bins = pack_keys(np.floor(points / size).astype(np.int64))
    bin_order = np.argsort(site_bins, kind="stable")
    sorted_bins = site_bins[bin_order]
    neighbour = cube_offsets(-reach, reach)
    # coefficients grouped by block, to gather a block's neighbourhood without a scan
    coef_order = np.argsort(tile_inverse, kind="stable")
    coef_start = np.searchsorted(tile_inverse[coef_order], np.arange(unique_tiles.size + 1))
    coef_reach = int(math.ceil((margin + order * h) / size))
    coef_neighbour = cube_offsets(-coef_reach, coef_reach)
    for t, tkey in enumerate(unique_tiles):
        tile = unpack_keys(np.array([tkey]))[0]
        lo = tile * size - margin
        hi = (tile + 1) * size + margin
        wanted = pack_keys(tile[None, :] + neighbour)
        starts = np.searchsorted(sorted_bins, wanted, side="left")
        stops = np.searchsorted(sorted_bins, wanted, side="right")
        chosen = np.concatenate([bin_order[a:b] for a, b in zip(starts, stops)])
        if chosen.size:
            p = points[chosen]
            chosen = chosen[np.all((p >= lo) & (p < hi), axis=1)]
        # unknowns: every coefficient non-zero somewhere in the local box
        cell_lo = np.floor(lo / h).astype(np.int64) - (order - 1)
        cell_hi = np.floor(hi / h).astype(np.int64)
        wanted_blocks = pack_keys(tile[None, :] + coef_neighbour)
        near = np.minimum(np.searchsorted(unique_tiles, wanted_blocks), unique_tiles.size - 1)
        near = near[unique_tiles[near] == wanted_blocks]
        candidates = np.concatenate([coef_order[coef_start[n]:coef_start[n + 1]] for n in near])
        candidates = candidates[np.all((idx[candidates] >= cell_lo) & (idx[candidates] <= cell_hi), axis=1)]
        local = np.sort(candidates)
        own = tile_inverse[local] == t
        yield LocalProblem(
            block=tuple(int(v) for v in tile), h=h, order=order,
            regularization=params.regularization, ridge=ridge, keys=keys[local], own=own,
            points=points[chosen], values=values[chosen],
        )
