"""Linearly independent hierarchical B-splines (thesis §5.3; Kraft 1998), on packed keys.

Levels ℓ = 0, 1, ... have spacing ``h_ℓ = h0 / 2^ℓ``; the B-spline ``k`` of level ℓ and
order n lives on the cells ``k .. k + n - 1`` of its level (its half-open support box
σ^ℓ_k). A basis is one set of *active* B-splines per level, ``B^ℓ``, and a domain of
*leaf cells* per level, ``ω^ℓ``; the spline is ``S = Σ_ℓ Σ_{k ∈ B^ℓ} b^ℓ_k B^ℓ_k``.

The operators and algorithms of the thesis (METHOD.md §3):

- ``up(K)``: the (n+1)³ children ``2k + m`` that span each B-spline of ``K``
  (refinement relation, :func:`geoidspline.bspline.basis.children`); ``down(K)``: the
  B-splines one level coarser all of whose children are in ``K``.
- Algorithm 1 (one refinement step): the marked B-splines ``K^ℓ`` are replaced by their
  children, ``B^{ℓ+1} ← B^{ℓ+1} ∪ up(K^ℓ)``; then, from the top down, every B-spline whose
  support overlaps the support of an active B-spline two or more levels finer is refined
  too (requirement 5.3, the sets ``J^ℓ``), and B-splines spanned by the level above are
  removed (``B^ℓ ← B^ℓ \\ down(B^{ℓ+1})``).
- Algorithm 2 (domain): ``ω^L`` = cells of the finest level meeting the manifold and an
  active support; ``ω^ℓ`` (ℓ < L) the same, without the cells overlapping a finer leaf
  (5.4). An active B-spline whose support meets no leaf cell of its level (``I^ℓ``) is
  replaced by its children; finally every B-spline whose support meets no leaf cell of
  its level is dropped.

Generalisations, each needed because the thesis states the algorithms for the case it
draws (refinement at the finest level only, in R^d):

- marked B-splines may be at any level (a joint least-squares refit can leave a node
  above the tolerance in a coarse leaf, which then is refined there);
- requirement 5.3 is enforced against every level two or more above (the thesis writes
  ℓ + 2; "more than one level apart" in its text, and Theorem 5.6's bound C1 = 2 needs
  all of them) and repeated until it holds everywhere, since refining a level-ℓ
  B-spline for it can make its children violate it against level ℓ + 3;
- the manifold restricts the domain: a cell belongs to it when it meets the unit sphere
  and its level-0 ancestor is one of the level-0 domain cells (the region's active
  cells); B-splines whose support holds no domain cell are never active, so they take
  no part in requirement 5.3 either;
- Algorithm 2 is repeated until no ``I^ℓ`` remains, so that the children it adds are
  judged against leaves that include them (one pass leaves holes where a coarse cell
  is only partly covered by finer leaves).

Numpy only, but for the per-level normal equations
(:func:`geoidspline._kernels.fitting.normal_equations`, the overlays' kernel).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from .._kernels.fitting import normal_equations
from ..bspline.basis import bspline_weights, children
from ..bspline.domain import active_cells
from ..bspline.keys import (
    covered_cell_keys, cube_offsets, isin_sorted, keys_centred_near, pack_keys, touching_cell_keys, unpack_keys,
)
from ..bspline.level import LevelSpline
from ..sphere.region import Region

__all__ = [
    "up", "down", "boxes_meet_sphere", "coarsen_cells", "Domain", "HierarchicalBasis", "algorithm1", "algorithm2",
    "initial_basis", "refine", "violations_53", "marked_functions", "HierarchicalRefinement", "design_matrix",
    "level_expansion", "level_normal_matrix", "normal_matrix",
]

_EMPTY = np.empty(0, dtype=np.int64)


# ---------------------------------------------------------------------------------
# operators on sorted, unique packed keys


def _intersect(a, b):
    return a[isin_sorted(a, b)] if a.size and b.size else _EMPTY


def _difference(a, b):
    return a[~isin_sorted(a, b)] if a.size and b.size else a


def up(keys, order: int) -> np.ndarray:
    """Sorted keys of the children ``2k + m`` (m in {0..n}³) of the B-splines ``keys``."""
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size == 0:
        return _EMPTY
    return np.unique(children(keys, order)[0])


def down(keys, order: int) -> np.ndarray:
    """Sorted keys of the B-splines one level coarser all of whose children are in ``keys``.

    Child ``c`` of parent ``j`` has ``c = 2j + m`` with one ``m`` per axis, so a parent
    is counted once per child present; the parents counted (n+1)³ times are ``down``.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if keys.size == 0:
        return _EMPTY
    idx = unpack_keys(keys)
    parents = []
    for m in cube_offsets(0, order):
        diff = idx - m
        even = np.all((diff & 1) == 0, axis=1)
        parents.append(pack_keys(diff[even] >> 1))
    parents, count = np.unique(np.concatenate(parents), return_counts=True)
    return parents[count == (order + 1) ** 3]


def coarsen_cells(cells, levels_up: int) -> np.ndarray:
    """Sorted keys of the cells ``levels_up`` levels coarser that hold ``cells``."""
    cells = np.asarray(cells, dtype=np.int64)
    if levels_up == 0 or cells.size == 0:
        return cells
    return np.unique(pack_keys(unpack_keys(cells) >> levels_up))


# ---------------------------------------------------------------------------------
# the domain


def boxes_meet_sphere(lo, hi, radius=1.0):
    """Whether each box [lo, hi] (M, 3) meets the sphere |x| = radius.

    The box is convex, so it does when its nearest point is inside the sphere and its
    farthest outside; a relative slack of 1e-9 keeps boxes the sphere touches at a face
    (as :func:`geoidspline._kernels.fitting.cells_meet_sphere` does).
    """
    near = np.where(lo > 0, lo, np.where(hi < 0, hi, 0.0))
    far = np.maximum(lo * lo, hi * hi)
    r2 = radius * radius
    return ((near * near).sum(axis=1) <= r2 * (1 + 1e-9)) & (far.sum(axis=1) >= r2 * (1 - 1e-9))


@dataclass(frozen=True, eq=False)
class Domain:
    """Where the hierarchical spline lives: the level-0 ``root`` cells (sorted keys,
    spacing ``h0``) and, at every level, their descendants that meet the manifold.

    ``meets(lo, hi) -> bool (M,)`` tells which boxes ``[lo, hi]`` (M, 3) meet the
    manifold; the default is the unit sphere (:func:`boxes_meet_sphere`). A cell of
    level ℓ is a domain cell when it meets the manifold and its level-0 ancestor is a
    root cell.

    ``shell`` (cells of the B-spline's own level, or ``None``) thins the basis across
    the manifold: a B-spline takes part only when the box of half-width ``shell``
    around the centre of its support meets the manifold. ``None`` keeps every B-spline
    whose support holds a domain cell (the thesis's Ω); 1.0 keeps two or three per
    normal direction instead of four or five, the rule overlays use for their levels
    (``refine_radius``). Either selection is a subset of a linearly independent set,
    so the theorems hold for both; the thin one gives up polynomial reproduction on the
    off-manifold part of the cells, which no data site or query ever sees.
    """

    root: np.ndarray
    h0: float
    meets: object = None
    shell: float | None = None

    @classmethod
    def sphere(cls, h0: float, region: Region, shell=None) -> "Domain":
        cells = active_cells(h0, region)
        return cls(np.unique(pack_keys(cells)) if cells.size else _EMPTY, h0, shell=shell)

    def spacing(self, level: int) -> float:
        return self.h0 / 2.0 ** level

    def _meets(self, lo, hi):
        return self.meets(lo, hi) if self.meets is not None else boxes_meet_sphere(lo, hi)

    def cells(self, keys, level: int) -> np.ndarray:
        """The domain cells among the cell ``keys`` (sorted) of ``level``."""
        keys = np.asarray(keys, dtype=np.int64)
        if keys.size == 0:
            return _EMPTY
        idx = unpack_keys(keys)
        keep = isin_sorted(pack_keys(idx >> level), self.root)
        if level > 0 and keep.any():
            h = self.spacing(level)
            lo = idx[keep] * h
            keep[keep] = self._meets(lo, lo + h)
        return keys[keep]

    def admissible(self, keys, level: int, order: int) -> np.ndarray:
        """Mask over B-spline ``keys`` of ``level``: within ``shell`` of the manifold."""
        keys = np.asarray(keys, dtype=np.int64)
        if self.shell is None or keys.size == 0:
            return np.ones(keys.size, bool)
        h = self.spacing(level)
        centre = (unpack_keys(keys) + order / 2.0) * h
        return self._meets(centre - self.shell * h, centre + self.shell * h)


# ---------------------------------------------------------------------------------
# the basis


@dataclass(frozen=True, eq=False)
class HierarchicalBasis:
    """Active B-splines ``active[ℓ]`` and leaf cells ``leaves[ℓ]`` (sorted packed keys)
    of levels 0..L, on ``domain``; order ``order``."""

    domain: Domain
    order: int
    active: tuple
    leaves: tuple

    @property
    def levels(self) -> int:
        return len(self.active)

    @property
    def coefficient_count(self) -> int:
        return int(sum(a.size for a in self.active))

    def spacing(self, level: int) -> float:
        return self.domain.spacing(level)

    def offsets(self) -> np.ndarray:
        """Position of each level's first coefficient in the one vector of all levels."""
        return np.r_[0, np.cumsum([a.size for a in self.active])].astype(np.int64)

    def level_splines(self, coefficients) -> list:
        """The spline of ``coefficients`` (ordered level by level, keys sorted) as one
        :class:`LevelSpline` per level: their sum is the hierarchical spline."""
        coefficients = np.asarray(coefficients, dtype=float)
        at = self.offsets()
        return [LevelSpline(lv, self.spacing(lv), self.order, keys, coefficients[at[lv]:at[lv + 1]])
                for lv, keys in enumerate(self.active) if keys.size]

    def leaf_level(self, points) -> np.ndarray:
        """Level of the leaf cell holding each point (M, 3); -1 where none does."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        out = np.full(points.shape[0], -1, dtype=np.int64)
        for lv in range(self.levels - 1, -1, -1):
            open_ = out < 0
            if not open_.any() or self.leaves[lv].size == 0:
                continue
            cells = pack_keys(np.floor(points[open_] / self.spacing(lv)).astype(np.int64))
            hit = isin_sorted(cells, self.leaves[lv])
            idx = np.flatnonzero(open_)[hit]
            out[idx] = lv
        return out


def _overlapping(keys, level, others, other_level, order):
    """Mask over ``keys`` (level) of supports overlapping a support of ``others``.

    Cells are aligned across levels, so two half-open boxes overlap exactly when the
    coarser box holds the coarser-level cell of one cell of the finer box.
    """
    keys = np.asarray(keys, dtype=np.int64)
    if other_level >= level:
        cells = coarsen_cells(covered_cell_keys(others, order), other_level - level)
        return isin_sorted(keys, touching_cell_keys(cells, order))
    cells = covered_cell_keys(keys, order)
    hit = isin_sorted(pack_keys(unpack_keys(cells) >> (level - other_level)), covered_cell_keys(others, order))
    return isin_sorted(keys, touching_cell_keys(cells[hit], order))


def initial_basis(domain: Domain, order: int) -> HierarchicalBasis:
    """Level 0: every (admissible) B-spline touching a root cell; the root cells are the leaves."""
    keys = touching_cell_keys(domain.root, order)
    return HierarchicalBasis(domain, order, (keys[domain.admissible(keys, 0, order)],), (domain.root,))


def _relevant(keys, level, domain, order):
    """The B-splines among ``keys`` that take part: their support holds a domain cell
    of their level, and they are admissible (:meth:`Domain.admissible`)."""
    if keys.size == 0:
        return keys
    keys = keys[domain.admissible(keys, level, order)]
    cells = domain.cells(covered_cell_keys(keys, order), level)
    return _intersect(keys, touching_cell_keys(cells, order))


def _requirement_53(active, domain, order):
    """Refine, from the top down, every relevant B-spline whose support overlaps the
    support of a relevant active B-spline two or more levels finer (the sets ``J^ℓ``);
    returns whether any was refined."""
    levels = len(active)
    refined = False
    for lv in range(levels - 3, -1, -1):
        cells = []
        for other in range(lv + 2, levels):
            rel = _relevant(active[other], other, domain, order)
            if rel.size:
                cells.append(coarsen_cells(covered_cell_keys(rel, order), other - lv))
        if not cells:
            continue
        mine = _relevant(active[lv], lv, domain, order)
        violating = _intersect(mine, touching_cell_keys(np.unique(np.concatenate(cells)), order))
        if violating.size:
            active[lv + 1] = np.union1d(active[lv + 1], up(violating, order))
            active[lv] = _difference(active[lv], violating)
            refined = True
    return refined


def algorithm1(active, marked, order: int, domain: Domain) -> list:
    """Algorithm 1: refine the marked B-splines ``marked[ℓ] ⊆ active[ℓ]``, enforce
    requirement 5.3 and remove the B-splines spanned by the level above.

    Returns the new active sets (children are complete here: Algorithm 2 restricts
    them to the domain).
    """
    active = [np.asarray(a, dtype=np.int64) for a in active]
    top = max([lv + 1 for lv, k in enumerate(marked) if len(k)], default=0)
    while len(active) <= top:
        active.append(_EMPTY)
    for lv, k in enumerate(marked):
        if len(k):
            active[lv + 1] = np.union1d(active[lv + 1], up(k, order))
    while _requirement_53(active, domain, order):
        pass
    for lv in range(len(active) - 1):
        active[lv] = _difference(active[lv], down(active[lv + 1], order))
    return active


def _leaves(active, domain, order):
    """ω^ℓ from the top down: domain cells meeting an active support of their level and
    not overlapping a finer leaf (5.4, with every finer level)."""
    levels = len(active)
    leaves = [_EMPTY] * levels
    under_finer = _EMPTY  # level-ℓ cells that hold a leaf of a finer level
    for lv in range(levels - 1, -1, -1):
        keys = active[lv][domain.admissible(active[lv], lv, order)]
        leaves[lv] = _difference(domain.cells(covered_cell_keys(keys, order), lv), under_finer)
        under_finer = coarsen_cells(np.union1d(under_finer, leaves[lv]), 1) if lv else _EMPTY
    return leaves


def algorithm2(active, domain: Domain, order: int):
    """Algorithm 2: the leaves ω^ℓ and the active sets restricted to them.

    B-splines of level ℓ < L whose support meets no leaf of their level (``I^ℓ``) are
    replaced by their children; repeated until there are none, then every B-spline
    whose support meets no leaf cell of its level is dropped.
    """
    active = [np.asarray(a, dtype=np.int64) for a in active]
    while len(active) > 1 and active[-1].size == 0:
        active.pop()
    while True:
        leaves = _leaves(active, domain, order)
        changed = False
        for lv in range(len(active) - 1):
            # relevant B-splines (support meets the domain) that meet no leaf
            rel = _relevant(active[lv], lv, domain, order)
            idle = _difference(rel, touching_cell_keys(leaves[lv], order))
            if idle.size:
                active[lv + 1] = np.union1d(active[lv + 1], up(idle, order))
                active[lv] = _difference(active[lv], idle)
                changed = True
        if not changed:
            break
    active = [_intersect(a, touching_cell_keys(w, order)) for a, w in zip(active, leaves)]
    active = [a[domain.admissible(a, lv, order)] for lv, a in enumerate(active)]
    return active, leaves


def refine(basis: HierarchicalBasis, marked) -> HierarchicalBasis:
    """One refinement step: Algorithm 1 on the marked B-splines, then Algorithm 2, again
    (without marks) until the children Algorithm 2 adds satisfy requirement 5.3 too."""
    active = list(basis.active)
    while True:
        active = algorithm1(active, marked, basis.order, basis.domain)
        active, leaves = algorithm2(active, basis.domain, basis.order)
        if not violations_53(active, basis.domain, basis.order):
            return HierarchicalBasis(basis.domain, basis.order, tuple(active), tuple(leaves))
        marked = []


def violations_53(active, domain, order) -> int:
    """How many pairs of levels (ℓ, m >= ℓ + 2) have overlapping active supports."""
    count = 0
    for lv in range(len(active)):
        for other in range(lv + 2, len(active)):
            if active[lv].size and active[other].size:
                count += int(np.any(_overlapping(active[lv], lv, active[other], other, order)))
    return count


def marked_functions(basis: HierarchicalBasis, points, radius=None, max_level=None) -> list:
    """``K^ℓ``: the active B-splines of each point's leaf level whose support holds it.

    ``radius`` (cells, per axis) keeps only those whose support centre is that close to
    the point (``None``: all, as in the thesis). Points whose leaf is at ``max_level``
    or finer are not refined. Returns one sorted key array per level.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    level = basis.leaf_level(points)
    marked = []
    for lv in range(basis.levels):
        at = points[level == lv]
        if at.size == 0 or (max_level is not None and lv >= max_level):
            marked.append(_EMPTY)
            continue
        near = keys_centred_near(at / basis.spacing(lv), basis.order, radius, chunk=100_000)
        marked.append(_intersect(near, basis.active[lv]))
    return marked


class HierarchicalRefinement:
    """Refinement strategy producing one linearly independent basis over all levels.

    The counterpart of :class:`geoidspline.hierarchy.overlays.OverlayRefinement`: where overlays add a
    level of B-splines around the nodes above the tolerance, this marks the active
    B-splines at those nodes (``radius`` as in :func:`marked_functions`) and applies
    Algorithms 1 and 2, so coarse B-splines are replaced, not overlaid.
    """

    name = "hierarchical"

    def __init__(self, order: int, h0: float, radius=None, shell=None):
        self.order = order
        self.h0 = h0
        self.radius = radius
        self.shell = shell

    def initial(self, region: Region) -> HierarchicalBasis:
        return initial_basis(Domain.sphere(self.h0, region, self.shell), self.order)

    def refine(self, basis: HierarchicalBasis, violating_points, max_level=None) -> HierarchicalBasis:
        """The basis after one refinement step driven by the points above the tolerance
        (directions on the unit sphere); ``basis`` itself when nothing can be refined."""
        marked = marked_functions(basis, violating_points, self.radius, max_level)
        if not any(len(k) for k in marked):
            return basis
        return refine(basis, marked)


# ---------------------------------------------------------------------------------
# least-squares matrices


def design_matrix(basis: HierarchicalBasis, points):
    """The collocation matrix A (sites x active B-splines of all levels, CSR):
    ``A[s, j] = B_j(points[s])``, columns ordered as :meth:`HierarchicalBasis.offsets`.

    Direct evaluation of every level at every site: the reference the assembled normal
    equations (:func:`normal_matrix`) are tested against, and the tool of the tests of
    linear independence and stability.
    """
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    n = basis.order
    stencil = cube_offsets(0, n - 1)
    at = basis.offsets()
    rows, cols, vals = [], [], []
    for lv, keys in enumerate(basis.active):
        if keys.size == 0:
            continue
        scaled = points / basis.spacing(lv)
        cell = np.floor(scaled).astype(np.int64)
        t = scaled - cell
        w = [bspline_weights(t[:, d], n, 0)[0] for d in range(3)]  # (M, n) each
        wanted = pack_keys(cell[:, None, :] - (n - 1) + stencil[None])  # (M, n³)
        weight = w[0][:, stencil[:, 0]] * w[1][:, stencil[:, 1]] * w[2][:, stencil[:, 2]]
        pos = np.minimum(np.searchsorted(keys, wanted), keys.size - 1)
        hit = keys[pos] == wanted
        r, c = np.nonzero(hit)
        rows.append(r)
        cols.append(at[lv] + pos[r, c])
        vals.append(weight[r, c])
    if not rows:
        return sp.csr_matrix((points.shape[0], basis.coefficient_count))
    return sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                         shape=(points.shape[0], basis.coefficient_count))


#: Coarser B-splines whose children :func:`level_expansion` forms at once (125 children
#: each for cubics, about 50 bytes a child in the temporaries: about 13 MB).
EXPANSION_PARENTS = 2048


def level_expansion(basis: HierarchicalBasis, level: int):
    """Keys ``X`` of the level-ℓ B-splines touching the leaves ω^ℓ that carry a part of
    the hierarchical spline, and the sparse matrix R (len(X) x all coefficients) writing
    the spline on them: on ω^ℓ, ``S = Σ_x (R b)_x B^ℓ_x``.

    On a leaf of level ℓ only the active B-splines of levels ℓ and ℓ - 1 are non-zero
    (finer supports hold no leaf of level ℓ, and requirement 5.3 keeps level ℓ - 2 and
    coarser away); a level ℓ - 1 B-spline enters through its children (refinement
    relation), keeping those in X.
    """
    n = basis.order
    at = basis.offsets()
    x = touching_cell_keys(basis.leaves[level], n)
    rows, cols, vals = [], [], []
    own = basis.active[level]
    if own.size:
        pos = np.searchsorted(x, own)
        hit = (pos < x.size) & (x[np.minimum(pos, x.size - 1)] == own)
        rows.append(pos[hit])
        cols.append(at[level] + np.flatnonzero(hit))
        vals.append(np.ones(int(hit.sum())))
    coarser = basis.active[level - 1] if level > 0 else _EMPTY
    for first in range(0, coarser.size, EXPANSION_PARENTS):
        # (n + 1)³ children a parent, most outside the leaves: a slice of parents at a time
        child, parent, weight = children(coarser[first:first + EXPANSION_PARENTS], n)
        pos = np.searchsorted(x, child)
        hit = (pos < x.size) & (x[np.minimum(pos, x.size - 1)] == child)
        rows.append(pos[hit])
        cols.append(at[level - 1] + first + parent[hit])
        vals.append(weight[hit])
    if not rows:
        return _EMPTY, sp.csr_matrix((0, basis.coefficient_count))
    r = sp.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                      shape=(x.size, basis.coefficient_count))
    # B-splines touching a leaf that carry no part of the spline (the thin basis leaves
    # about 40 % of them out): dropped, since their normal equations would be multiplied
    # by zero rows of R
    carrying = np.diff(r.indptr) > 0
    return x[carrying], r[carrying]


#: Bytes of the dense scratch table of one level's normal equations, filled one slice of
#: the level's B-splines at a time (32 MB: about 11,700 cubic B-splines), so that the
#: table follows the slice, not the globe.
NORMAL_TABLE_BYTES = 32_000_000

#: Columns of the hierarchical basis whose part of ``Rᵀ F R`` one sparse product forms
#: (its temporaries are those columns' share of the whole product).
PRODUCT_COLUMNS = 4096


def level_normal_matrix(points, values, h, order, keys):
    """One level's AᵀA (upper triangle, CSC) and Aᵀv over the B-splines ``keys`` (sorted)
    at ``points``, built one slice of :data:`NORMAL_TABLE_BYTES` at a time from the sites
    that can reach the slice (by the first axis of their cell, in their order, so every
    entry is summed as by one table)."""
    n = keys.size
    rhs = np.zeros(n)
    per_slice = max(1, NORMAL_TABLE_BYTES // (8 * (2 * order - 1) ** 3))
    # the kernel's cell: floor(x * (1 / h))
    axis = np.floor(points[:, 0] * (1.0 / h)).astype(np.int64)
    by_axis = np.argsort(axis, kind="stable")
    axis = axis[by_axis]
    indptr = np.zeros(n + 1, np.int64)
    indices, data, at = np.empty(0, np.int32), np.empty(0), 0
    for first in range(0, n, per_slice):
        last = min(n, first + per_slice)
        lo, hi = unpack_keys(keys[[first, last - 1]])[:, 0]
        # the B-spline i spans the cells i .. i + order - 1 of the first axis
        a, b = np.searchsorted(axis, [lo, hi + order])
        chosen = np.sort(by_axis[a:b])
        ptr_, idx_, val_, _ = normal_equations(points[chosen], values[chosen], h, order, keys, first, last, rhs)
        if at + idx_.size > indices.size:
            # room for the rest at this slice's entries per column, and a little more:
            # growing by a guess, not by concatenating every slice (twice the level's matrix)
            size = at + idx_.size + int(1.05 * idx_.size / (last - first) * (n - last)) + 1024
            grown_indices, grown_data = np.empty(size, np.int32), np.empty(size)
            grown_indices[:at], grown_data[:at] = indices[:at], data[:at]
            indices, data = grown_indices, grown_data
            del grown_indices, grown_data
        indptr[first + 1:last + 1] = ptr_[1:] + at
        indices[at:at + idx_.size] = idx_
        data[at:at + idx_.size] = val_
        at += idx_.size
    indices, data = (indices[:at], data[:at]) if at >= 0.9 * data.size else (indices[:at].copy(), data[:at].copy())
    return sp.csc_matrix((data, indices, indptr), shape=(n, n)), rhs


def _upper_of_congruence(upper, r, total):
    """The upper triangle of ``Rᵀ F R`` (F symmetric, ``upper`` its upper triangle, CSC with
    sorted rows; R CSR with ``total`` columns) as one CSC piece per :data:`PRODUCT_COLUMNS`
    columns, so that the full product is never formed.

    F couples B-splines only a few key rows apart, so the columns of a slice, which reach
    the B-splines ``lo..hi`` of the level, see F only on ``lo - reach .. hi + reach``
    (``reach``: the largest distance of an entry from the diagonal): the product is formed
    on that band of F."""
    n = upper.shape[0]
    starts = upper.indptr[:-1]
    filled = np.diff(upper.indptr) > 0
    reach = int((np.arange(n)[filled] - upper.indices[starts[filled]]).max()) if filled.any() else 0
    r_columns = r.tocsc()
    pieces = []
    for j0 in range(0, total, PRODUCT_COLUMNS):
        j1 = min(total, j0 + PRODUCT_COLUMNS)
        rj = r_columns[:, j0:j1]
        if rj.nnz == 0:
            pieces.append(sp.csc_matrix((total, j1 - j0)))
            continue
        b0 = max(0, int(rj.indices.min()) - reach)
        b1 = min(n, int(rj.indices.max()) + reach + 1)
        band = upper if (b0, b1) == (0, n) else upper[:, b0:b1][b0:b1]
        rb = rj[b0:b1]
        product = band @ rb + band.T @ rb - sp.diags(band.diagonal()) @ rb  # F on the band times R's columns
        part = (r[b0:b1].T @ product).tocsc()
        del product
        rows = part.indices
        cols = np.repeat(np.arange(j1 - j0), np.diff(part.indptr))
        keep = rows <= cols + j0
        pieces.append(sp.csc_matrix((part.data[keep], (rows[keep], cols[keep])), shape=(total, j1 - j0)))
    return pieces


def normal_matrix(basis: HierarchicalBasis, sites, weighted=()):
    """The upper triangle (CSC, diagonal included) of AᵀA over all levels, and Aᵀv, for
    ``sites``: one ``(points, values)`` pair per level, the points inside that level's leaves.
    ``weighted``: more sites in groups ``(points per level, values per level, weight)``,
    their sums weighted (AᵀWA, AᵀWv) and added to their level's before it is put on the
    hierarchical basis (one congruence per level, whatever the groups).

    Each level's AᵀA on the B-splines touching its leaves comes from the single-level
    kernel (:func:`level_normal_matrix`), then ``Rᵀ (AᵀA) R`` with the level's expansion R
    (:func:`level_expansion`) puts it on the hierarchical basis, a slice of columns at a
    time. Only the upper triangle is kept: the matrix is symmetric, and the whole one
    is twice the memory (:class:`geoidspline.fitting.hierarchical.SymmetricMatrix` multiplies
    by the whole from it).
    """
    total = basis.coefficient_count
    rhs = np.zeros(total)
    pieces = []
    for lv, (points, values) in enumerate(sites):
        groups = [(points, values, 1.0)] + [(p[lv], v[lv], w) for p, v, w in weighted]
        groups = [g for g in groups if g[0].shape[0]]
        if not groups or basis.leaves[lv].size == 0:
            continue
        x, r = level_expansion(basis, lv)
        upper = b = None
        for group_points, group_values, weight in groups:
            more, more_b = level_normal_matrix(np.ascontiguousarray(group_points, dtype=float),
                                               np.ascontiguousarray(group_values, dtype=float), basis.spacing(lv),
                                               basis.order, x)
            if weight != 1.0:
                more, more_b = more * weight, more_b * weight
            upper, b = (more, more_b) if upper is None else (upper + more, b + more_b)
            del more
        rhs += r.T @ b
        level_pieces = _upper_of_congruence(upper, r, total)
        del upper
        if not pieces:
            pieces = level_pieces
            continue
        for i, piece in enumerate(level_pieces):  # one piece at a time: no second whole matrix
            pieces[i] = pieces[i] + piece
            level_pieces[i] = None
    if not pieces:
        return sp.csc_matrix((total, total)), rhs
    # the pieces side by side, each freed once copied: no second whole matrix
    count = sum(piece.nnz for piece in pieces)
    indptr = np.zeros(total + 1, np.int64)
    indices = np.empty(count, np.int32)
    data = np.empty(count)
    column = at = 0
    for i, piece in enumerate(pieces):
        piece.sort_indices()
        width = piece.shape[1]
        indptr[column + 1:column + width + 1] = piece.indptr[1:] + at
        indices[at:at + piece.nnz] = piece.indices
        data[at:at + piece.nnz] = piece.data
        column, at = column + width, at + piece.nnz
        pieces[i] = None
    return sp.csc_matrix((data, indices, indptr), shape=(total, total)), rhs

