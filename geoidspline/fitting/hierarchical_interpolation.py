"""The hierarchical quasi-interpolant of thesis §5.3.1 (Definition 5.4), for exact sources.

Over the linearly independent hierarchical basis (:mod:`geoidspline.hierarchy.hierarchical`)

    Q^L G = Σ_ℓ Σ_{k ∈ B^ℓ} λ^ℓ_k (G − Q^{ℓ−1} G) B^ℓ_k,        Q^{−1} G = 0,

level by level, coarse to fine: the coefficients of the active B-splines of level ℓ
are local linear functionals of the residual of the levels before, reading only leaves
of level ℓ (Definition 5.4); no linear solve beyond a patch. Two functionals:

- ``"cell"``, the thesis's: λ^ℓ_k interpolates on one leaf cell ``c ∈ ω^ℓ ∩ σ^ℓ_k``
  (on a cell the n³ B-splines non-zero there are a basis of the polynomials of
  coordinate order n): n³ samples of the cell, the inverse of the n x n collocation
  matrix per axis (:func:`dual_functional`), the leaf nearest the centre of σ^ℓ_k
  (:func:`functional_cells`). Exact, but its norm is 36.7 per axis for cubics at the
  central offsets and 146 at the ends (:func:`functional_norms`): the part of G a cubic
  misses on a cell comes back multiplied by up to 49,000-3,000,000, thousands of metres
  on EGM96 at level 0.
- ``"patch"`` (default, :data:`FUNCTIONAL`): least squares on the leaves of level ℓ in a
  patch of cells (:func:`_patch_coefficients`): every coefficient a patch owns is a
  fixed linear functional of the residual on leaves of its level in the patch, dual to
  the B-splines there; with ``ridge=0`` it satisfies Lemma 5.5 exactly, the fit adds a
  small ridge (:data:`PATCH_RIDGE`) against the near-dependence of the B-splines that
  only reach into a corner of the shell of leaves.

What Lemma 5.5 needs of the cell, and the basis: on a leaf of level ℓ the B-splines
of levels finer than ℓ vanish and those of ℓ − 2 and coarser too (requirement 5.3),
so ``G − Q^{ℓ−1} G`` there is a combination of level-ℓ B-splines alone whenever G is in
the space (projector) or a polynomial (reproduction); and every level-ℓ B-spline that
is non-zero on the cell must be active or have a zero coefficient. The thesis's Ω
basis (``Domain.shell = None``: every B-spline touching a leaf) has that; the thin
basis of the least-squares fit (``SHELL = 1``: two or three B-splines across the
sphere) drops B-splines that are non-zero on the sphere (a cubic B-spline centred 1-2
cells from the sphere is up to 1/6 there) and so loses even the constants: measured in
benchmarks/README.md, which is why :data:`INTERPOLANT_SHELL` is ``None``.

The source is the radially constant extension ``G(x) = N(x / |x|)`` of an exact model,
read from a latitude/longitude lattice of its synthesis by the 6 x 6-point Lagrange
lookups of :mod:`geoidspline.fitting.interpolation` (its :class:`LatticeLookup`); the fit
measures its error at that lattice's nodes and refines where it is above the
tolerance, as the least-squares driver (:func:`geoidspline.fitting.hierarchical.fit_hierarchical`) does.
"""

from __future__ import annotations

import hashlib
import logging
import math
import time

import numpy as np

from ..bspline.basis import bspline_weights
from ..bspline.keys import cube_offsets, isin_sorted, pack_keys, unpack_keys
from ..errors import FitError
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.hierarchical import HierarchicalBasis
from ..sphere.coordinates import latlon_of
from .interpolation import lattice_spacing, sample_band
from .progress import as_progress

__all__ = ["dual_functional", "functional_cells", "functional_norms", "quasi_interpolate",
           "HierarchicalQuasiInterpolant", "INTERPOLANT_SHELL", "hierarchical_interpolant"]

log = logging.getLogger(__name__)

#: The basis the quasi-interpolant is built on (:class:`~geoidspline.hierarchy.hierarchical.Domain`
#: ``shell``): ``None``, the thesis's Ω, every B-spline touching a leaf. The thin basis of
#: the least-squares fit does not reproduce polynomials on the sphere (see the module's
#: docstring; measured in benchmarks/README.md).
INTERPOLANT_SHELL = None

#: Sample points a fit evaluates at once (the lattice lookups and the coarser levels).
_CHUNK = 2_000_000


def dual_functional(order: int):
    """Sample positions ``t`` (n,) in a cell (units of the cell, in (0, 1)) and the matrix
    ``D`` (n, n) with ``D @ f(t)`` = the coefficients of the n B-splines non-zero on the
    cell (offset j: B-spline ``a - n + 1 + j`` of cell ``a``, the convention of
    :func:`geoidspline.bspline.basis.bspline_weights`) of the polynomial of order n
    through the samples: the inverse of the collocation matrix ``B_j(t_i)``.

    The samples are the cell's n midpoints ``(i + 1/2) / n``; the 3-D functional is the
    tensor product ``D ⊗ D ⊗ D`` on the n³ points ``t ⊗ t ⊗ t``.
    """
    t = (np.arange(order) + 0.5) / order
    return t, np.linalg.inv(bspline_weights(t, order, 0)[0])


def _offsets_by_distance(order: int) -> np.ndarray:
    """The n³ cell offsets ``o`` (cell ``k + o`` of B-spline ``k``), central first."""
    offsets = cube_offsets(0, order - 1)
    distance = np.abs(offsets - (order - 1) / 2.0).max(axis=1) * 1e3 + np.abs(offsets - (order - 1) / 2.0).sum(axis=1)
    return offsets[np.argsort(distance, kind="stable")]


def functional_cells(basis: HierarchicalBasis, level: int):
    """For each active B-spline of ``level`` (sorted keys): the leaf cell of its level its
    functional reads, the one closest to the centre of its support, and the B-spline's
    offset in that cell (0..n-1 per axis, as :func:`dual_functional` numbers them).

    Returns ``(cells (K,) packed keys, offsets (K, 3))``. Algorithm 2 keeps only
    B-splines whose support holds a leaf of their level, so every one has a cell.
    """
    n = basis.order
    keys = basis.active[level]
    idx = unpack_keys(keys)
    leaves = basis.leaves[level]
    cells = np.full(keys.size, -1, dtype=np.int64)
    found = np.zeros(keys.size, bool)
    for o in _offsets_by_distance(n):
        if found.all():
            break
        open_ = np.flatnonzero(~found)
        cand = pack_keys(idx[open_] + o)
        hit = isin_sorted(cand, leaves)
        cells[open_[hit]] = cand[hit]
        found[open_[hit]] = True
    if not found.all():
        raise FitError(f"level {level}: {int((~found).sum())} active B-splines hold no leaf of their level")
    # offset of B-spline k in cell a: k = a - n + 1 + j
    offsets = idx - unpack_keys(cells) + n - 1
    return cells, offsets


def functional_norms(order: int) -> np.ndarray:
    """‖λ‖∞ per offset j (n,) of the 1-D functional (row sums of |D|); the 3-D norm of
    offset ``(j0, j1, j2)`` is the product. Central offsets have the smallest."""
    return np.abs(dual_functional(order)[1]).sum(axis=1)


#: The local functionals :func:`quasi_interpolate` offers (see :data:`FUNCTIONAL`).
FUNCTIONALS = ("cell", "patch")

#: The functional a fit uses: ``"patch"``, local least squares on the leaves of the level
#: in a patch of cells (:func:`_patch_coefficients`). ``"cell"``, interpolation on one
#: leaf cell (the thesis's choice of an evaluation point in one active cell), has
#: norms of 36.7 per axis for cubics even at the central offsets (49,000 in 3-D,
#: :func:`functional_norms`): on EGM96 over the Andes level 0 alone misses by
#: 14,138 m against the patch's 16.6 m (benchmarks/README.md).
FUNCTIONAL = "patch"

#: Width (cells of the level, per axis) of the patches of the ``"patch"`` functional, in
#: units of the order: a patch owns the B-splines whose support centre it holds.
PATCH_ORDERS = 1

#: How far (cells of the level, in units of the order) a patch's problem reaches beyond
#: the patch: at least half an order, so that every owned support lies inside.
PATCH_MARGIN_ORDERS = 0.5


def _cell_samples(order):
    """Sample positions (n³, 3) in a cell (units of the cell) and the collocation matrix
    (n³ samples x n³ B-splines non-zero on the cell), both in :func:`cube_offsets` order."""
    t, _ = dual_functional(order)
    m1 = bspline_weights(t, order, 0)[0]
    m3 = np.einsum("ia,jb,kc->ijkabc", m1, m1, m1).reshape(order ** 3, order ** 3)
    return t[cube_offsets(0, order - 1)], m3


def _cell_coefficients(basis, lv, residual, ridge=None):
    """Level ``lv``'s coefficients by the one-cell functional (:func:`functional_cells`)."""
    n = basis.order
    _, dual = dual_functional(n)
    sample, _ = _cell_samples(n)
    cells, offsets = functional_cells(basis, lv)
    unique, inverse = np.unique(cells, return_inverse=True)
    points = ((unpack_keys(unique)[:, None, :] + sample[None]) * basis.spacing(lv)).reshape(-1, 3)
    values = residual(points)
    samples = values.reshape(unique.size, n, n, n)[inverse]
    coefs = np.einsum("ka,kb,kc,kabc->k", dual[offsets[:, 0]], dual[offsets[:, 1]], dual[offsets[:, 2]], samples,
                      optimize=True)
    return coefs, points, values


def _patch_coefficients(basis, lv, residual, ridge):
    """Level ``lv``'s coefficients by local least squares on its leaves, patch by patch.

    A patch is a cube of ``P = PATCH_ORDERS * n`` cells of the level; it owns the active
    B-splines whose support centre it holds, and its problem is the least-squares fit
    of the residual at the n³ samples of every leaf of the level in the patch grown by
    n/2 cells (so every owned support lies inside) by the active B-splines of the level
    non-zero there. Each owned coefficient is a linear functional of the residual on
    leaves of its level only: on a leaf the residual of a spline of the space (or of a
    polynomial) is a combination of those B-splines alone, which least squares
    recovers exactly (Lemma 5.5). The normal equations of a leaf are one fixed n³ x n³
    Gram matrix (every leaf has the same samples), scattered.
    """
    n = basis.order
    keys, leaves = basis.active[lv], basis.leaves[lv]
    sample, m3 = _cell_samples(n)
    gram = m3.T @ m3
    leaf_idx = unpack_keys(leaves)
    points = ((leaf_idx[:, None, :] + sample[None]) * basis.spacing(lv)).reshape(-1, 3)
    values = residual(points)
    cell_values = values.reshape(leaves.size, n ** 3)
    moments = cell_values @ m3  # Aᵀv per leaf and B-spline offset
    offsets = cube_offsets(0, n - 1)
    size, grow = PATCH_ORDERS * n, max(n // 2, int(math.ceil(PATCH_MARGIN_ORDERS * n)))
    reach = int(math.ceil(grow / size))
    owner = pack_keys(np.floor_divide(unpack_keys(keys) + n // 2, size))
    leaf_bin = pack_keys(np.floor_divide(leaf_idx, size))
    by_bin = np.argsort(leaf_bin, kind="stable")
    sorted_bins = leaf_bin[by_bin]
    near = cube_offsets(-reach, reach)
    coefs = np.full(keys.size, np.nan)
    for patch in np.unique(owner):
        corner = unpack_keys(np.array([patch]))[0]
        wanted = np.sort(pack_keys(corner + near))
        starts, stops = np.searchsorted(sorted_bins, wanted), np.searchsorted(sorted_bins, wanted, side="right")
        cand = np.concatenate([by_bin[a:b] for a, b in zip(starts, stops)])
        cell = leaf_idx[cand]
        cand = cand[np.all((cell >= corner * size - grow) & (cell < (corner + 1) * size + grow), axis=1)]
        wanted_keys = pack_keys(leaf_idx[cand][:, None, :] - (n - 1) + offsets[None])  # (m, n³)
        pos = np.minimum(np.searchsorted(keys, wanted_keys), keys.size - 1)
        present = keys[pos] == wanted_keys
        local, column = np.unique(pos[present], return_inverse=True)
        col = np.full(wanted_keys.shape, -1)
        col[present] = column
        unknowns = local.size
        pair = present[:, :, None] & present[:, None, :]
        rows = np.broadcast_to(col[:, :, None], pair.shape)[pair]
        cols = np.broadcast_to(col[:, None, :], pair.shape)[pair]
        normal = np.bincount(rows * unknowns + cols, weights=np.broadcast_to(gram, pair.shape)[pair],
                             minlength=unknowns * unknowns).reshape(unknowns, unknowns)
        rhs = np.bincount(col[present], weights=moments[cand][present], minlength=unknowns)
        solution = _solve_patch(normal, rhs, col, present, m3, cell_values[cand], ridge)
        mine = owner[local] == patch
        coefs[local[mine]] = solution[mine]
    if np.isnan(coefs).any():
        raise FitError(f"level {lv}: {int(np.isnan(coefs).sum())} active B-splines in no patch's problem")
    return coefs, points, values


#: Ridge added to a patch's normal equations scaled to a unit diagonal (0: the exact
#: functional of Lemma 5.5). On the shell of leaves the Ω basis is nearly dependent
#: (patches' reciprocal condition 1e-11..1e-7): without a ridge the coefficients of the
#: B-splines that reach only into a corner of the shell are large and, non-zero on the
#: leaves of the next level, throw it off (EGM96, 25° x 20° of the Andes at 0.5 m:
#: 1e-6 let the node max jump from 3.3 to 15.3 m in one step and ended at 1.17 m with
#: 50,904 coefficients; 1e-4: 1.01 m with 44,875; benchmarks/README.md).
PATCH_RIDGE = 1e-4

#: Reciprocal condition below which a patch's normal equations are not trusted (their
#: rounding error, eps / rcond, would show in the coefficients): its least squares is
#: solved from the design matrix instead (SVD), with the square root of their
#: condition. With the ridge of a fit none needs it; the exact functional (``ridge=0``)
#: does on the shell of leaves and on the few cells of the tests' small domains.
PATCH_RCOND = 1e-9


def _solve_patch(normal, rhs, col, present, m3, cell_values, ridge):
    """The patch's least-squares coefficients: the normal equations scaled to a unit
    diagonal (unknowns reaching only into corner cells have tiny ones) by Cholesky, or
    when they are ill-conditioned the design matrix by SVD (``col``: the unknown of each
    (cell, offset), where ``present``)."""
    import scipy.linalg

    scale = 1.0 / np.sqrt(np.diagonal(normal))
    scaled = normal * scale[:, None] * scale[None, :]
    if ridge:
        scaled[np.diag_indices_from(scaled)] += ridge
    factor, info = scipy.linalg.lapack.dpotrf(scaled, lower=False)
    rcond = 0.0
    if info == 0:  # positive definite to rounding: how well conditioned (LAPACK's estimate)
        rcond, info = scipy.linalg.lapack.dpocon(factor, np.abs(scaled).sum(axis=0).max())
        if info == 0 and rcond > PATCH_RCOND:
            return scale * scipy.linalg.cho_solve((factor, False), rhs * scale, check_finite=False)
    log.debug("patch of %d unknowns: rcond %.3g, solved by SVD", normal.shape[0], rcond)
    cells, per = present.shape
    design = np.zeros((cells, m3.shape[0], normal.shape[0]))
    c, o = np.nonzero(present)
    design[c, :, col[c, o]] = m3[:, o].T
    design = design.reshape(cells * m3.shape[0], -1) * scale[None, :]
    values = cell_values.reshape(-1)
    if ridge:
        design = np.vstack([design, math.sqrt(ridge) * np.eye(normal.shape[0])])
        values = np.r_[values, np.zeros(normal.shape[0])]
    return scale * scipy.linalg.lstsq(design, values, lapack_driver="gelsd")[0]


def quasi_interpolate(basis: HierarchicalBasis, evaluate, functional=None, progress=None, cache=None,
                      ridge=None):
    """Coefficients of ``Q^L G`` over ``basis`` (all levels, :meth:`HierarchicalBasis.offsets`
    order), ``G`` given by ``evaluate(points (M, 3)) -> (M,)``; ``functional`` one of
    :data:`FUNCTIONALS` (default :data:`FUNCTIONAL`).

    Returns ``(coefficients, points, values)``: ``points[ℓ]`` the sample points of level
    ℓ (n³ per cell read) and ``values[ℓ]`` the residual ``G − Q^{ℓ−1} G`` there.
    ``cache`` (a dict kept across calls with the same ``evaluate``) keeps each level's
    result under a digest of the active B-splines and leaves of it and every coarser
    level, on which alone it depends: a refinement step recomputes only the levels it
    changed and those above them. The cache ends holding this call's levels only.
    """
    functional = FUNCTIONAL if functional is None else functional
    ridge = PATCH_RIDGE if ridge is None else ridge
    if functional not in FUNCTIONALS:
        raise ValueError(f"functional must be one of {FUNCTIONALS}, got {functional!r}")
    level_coefficients = _patch_coefficients if functional == "patch" else _cell_coefficients
    progress = as_progress(progress)
    at = basis.offsets()
    coefs = np.zeros(basis.coefficient_count)
    points_out, values_out, used = [], [], {}
    digest = hashlib.blake2b(repr((functional, ridge, basis.order, basis.domain.h0)).encode(), digest_size=20)
    with progress.stage("hierarchical quasi-interpolation", basis.levels, "level") as advance:
        for lv in range(basis.levels):
            keys = basis.active[lv]
            digest.update(f"|{lv}:".encode())
            digest.update(keys.tobytes())
            digest.update(b"/")
            digest.update(basis.leaves[lv].tobytes())
            key = digest.copy().digest()
            if cache is not None and key in cache:
                level, points, values = cache[key]
            elif keys.size == 0:
                level, points, values = np.empty(0), np.empty((0, 3)), np.empty(0)
            else:
                coarser = AmbientSpline(basis.level_splines(np.where(np.arange(coefs.size) < at[lv], coefs, 0.0)))

                def residual(points):  # G - Q^{ℓ-1} G
                    out = _evaluate_chunked(evaluate, points)
                    return out - _evaluate_chunked(coarser.evaluate_points, points) if lv else out

                level, points, values = level_coefficients(basis, lv, residual, ridge)
            used[key] = (level, points, values)
            coefs[at[lv]:at[lv + 1]] = level
            points_out.append(points)
            values_out.append(values)
            advance(1)
    if cache is not None:
        cache.clear()
        cache.update(used)
    return coefs, points_out, values_out


def _evaluate_chunked(evaluate, points):
    out = np.empty(points.shape[0])
    for a in range(0, points.shape[0], _CHUNK):
        out[a:a + _CHUNK] = evaluate(points[a:a + _CHUNK])
    return out


class HierarchicalQuasiInterpolant:
    """The coefficients of one refinement step of
    :func:`geoidspline.fitting.hierarchical.fit_hierarchical` by :func:`quasi_interpolate`
    of ``evaluate`` (no solve), on the basis ``shell`` selects."""

    def __init__(self, evaluate, shell=INTERPOLANT_SHELL, functional=None):
        self.evaluate = evaluate
        self.shell = shell
        self.functional = functional
        self._cache = {}  # level results by digest, across refinement steps

    def coefficients(self, basis: HierarchicalBasis, progress=None):
        """``(coefficients, points per level, residual values per level)``."""
        start = time.perf_counter()
        coefs, points, values = quasi_interpolate(basis, self.evaluate, self.functional, progress, self._cache)
        log.info("hierarchical quasi-interpolation: %d coefficients from %d samples (%.1f s)",
                 coefs.size, sum(p.shape[0] for p in points), time.perf_counter() - start)
        return coefs, points, values


def cells_latitude_range(cells, h: float, pad_deg: float = 0.5):
    """Latitudes (degrees) spanned by the directions of the points of the cells (M, 3
    indices, spacing ``h``): the extremes over their corners, ``pad_deg`` wider (an
    extreme can lie on an edge), and a pole when a cell's (x, y) rectangle holds the axis."""
    cells = np.asarray(cells, dtype=np.int64).reshape(-1, 3)
    corners = (cells[:, None, :] + cube_offsets(0, 1)[None]) * h
    latitude, _ = latlon_of(corners.reshape(-1, 3))
    south, north = float(latitude.min()) - pad_deg, float(latitude.max()) + pad_deg
    axis = (cells[:, 0] <= 0) & (cells[:, 0] + 1 >= 0) & (cells[:, 1] <= 0) & (cells[:, 1] + 1 >= 0)
    if np.any(axis & (cells[:, 2] + 1 > 0)):
        north = 90.0
    if np.any(axis & (cells[:, 2] < 0)):
        south = -90.0
    return max(-90.0, south), min(90.0, north)


def hierarchical_interpolant(source, cells, params, spacing_deg=None, progress=None, shell=INTERPOLANT_SHELL,
                             functional=None):
    """The hierarchical quasi-interpolant of an exact ``source`` (a harmonic model) over the
    level-0 domain ``cells`` (M, 3 indices of spacing ``params.h0``), and the band of its
    synthesis, whose lattice (5' for degree 360,
    :func:`~geoidspline.fitting.interpolation.lattice_spacing`) the lookups read and whose
    nodes measure the fit's error: ``(band, interpolant)``, for
    :func:`geoidspline.fitting.driver.fit_nodes` (``method="interpolation"`` with
    ``refinement="hierarchical"``). ``shell``: the basis (:data:`INTERPOLANT_SHELL`),
    ``functional`` the local functional (:data:`FUNCTIONAL`).
    """
    spacing_deg = lattice_spacing(source, params.h0, spacing_deg)
    lookup, band = sample_band(source, *cells_latitude_range(cells, params.h0), spacing_deg, progress)
    return band, HierarchicalQuasiInterpolant(lookup, shell, functional)
