"""The query index: every level's coefficients regrouped by bricks, with folded levels.

See :class:`BrickIndex`. Compiled kernels are in :mod:`geoidspline._kernels.query` (C).
"""

from __future__ import annotations

import math

import numpy as np

from .._kernels import query as _qk
from .._kernels._clib import threads
from .basis import refinement_weights
from .keys import KEY_BITS, KEY_OFFSET, pack_keys, unpack_keys
from .level import LevelSpline

FOLD_BAND_CELLS = 2.0
"""Half-width of a level's folded band, in cells of that level: the folded table of a
brick holds every B-spline touching a cell of the brick that meets the shell
``1 - w <= |x| <= 1 + w``, ``w = FOLD_BAND_CELLS * h`` (plus 1e-9 for rounding)."""


_ORDER_THRESHOLD = 20_000  # from this many points, BrickIndex.add_to orders them itself


IN_ORDER_MAX_BYTES = 1 << 18
"""Latitude/longitude batches of an index whose tables that a point on the sphere reads
(:meth:`BrickIndex.hot_bytes`) fit in this many bytes (a core's L2 cache on the machines
measured) are evaluated in the order given: the sort by cell that keeps big tables' reads
in the caches buys nothing there and costs a third of the batch (benchmarks/README.md,
branch q23q). Bigger ones are sorted. Either gives the same bits."""


PREFETCH_BRICKS_FROM_BYTES = 32 << 20
"""Float64 tables (values) of this many bytes or more, beyond a last-level cache, have the
bricks ahead of a latitude/longitude batch's points prefetched (``fold_size``, see
``src/query.c``'s ``prefetch_bricks``): a global batch of 1,000,000 points enters a new brick
every few hundred points, and its table comes from memory (benchmarks/README.md). Tables
that fit the caches gain nothing from it. Either gives the same bits."""


_FOLD_CHUNK_BRICKS = 512  # bricks folded at once (a dense (side³) block each, transient)


_SAME_H_RTOL = 1e-12


_STEP_HALVINGS = 8  # a store's tiles are quantised with its step or down to 1/256 of it


QUANTISE_FROM_COEFFICIENTS = 50_000_000
"""From this many coefficients on (about 0.9 GB of float64 tables, beyond the caches), the
tables of a spline with a known value step hold its integers (:class:`BrickIndex`):
dequantising costs time per point where the tables are cached (EGM96 2 mm store, 6.5 M
coefficients: 1.4 times slower), little where memory dominates, and saves 2.5 times the
memory (benchmarks/README.md, "Query index")."""


def _merge_levels(levels):
    """Non-empty levels sorted coarse to fine; levels of one spacing summed into one."""
    groups = []
    for lv in sorted((lv for lv in levels if len(lv)), key=lambda lv: -lv.h):
        if groups and abs(groups[-1][0].h - lv.h) <= _SAME_H_RTOL * lv.h:
            groups[-1].append(lv)
        else:
            groups.append([lv])
    merged = []
    for group in groups:
        if len(group) == 1:
            merged.append(group[0])
            continue
        keys, inverse = np.unique(np.concatenate([lv.keys for lv in group]), return_inverse=True)
        coefs = np.bincount(inverse, weights=np.concatenate([lv.coefficients for lv in group]),
                            minlength=keys.size)
        merged.append(LevelSpline(group[0].level, group[0].h, group[0].order, keys, coefs))
    return merged


def _fold_depths(levels):
    """Dyadic depth of each level below the coarsest (h = h_coarsest / 2**depth).

    ``None`` from the first level whose grid is not nested in all coarser ones: such a
    level (and every finer one) is not folded and is always evaluated on its own.
    """
    depths = []
    for lv in levels:
        ratio = levels[0].h / lv.h
        depth = round(math.log2(ratio))
        if (depths and depths[-1] is None) or abs(ratio - 2.0**depth) > _SAME_H_RTOL * ratio:
            depths.append(None)
        else:
            depths.append(depth)
    return depths


def _row_span(lv, order, row):
    """The run of a level's sorted keys whose first index i is in ``[row S - order + 1,
    row S + S - 1]`` (the B-splines of row ``row`` of its bricks; i is the keys' leading
    field): ``(lo, hi)``."""
    cells = 1 << _qk.BRICK_BITS
    lo, hi = np.searchsorted(lv.keys, pack_keys(np.array([[row * cells - order + 1, -KEY_OFFSET, -KEY_OFFSET],
                                                           [row * cells + cells, -KEY_OFFSET, -KEY_OFFSET]])))
    return int(lo), int(hi)


def _brick_rows(lv, order):
    """The rows (first brick index) of a level's bricks."""
    if not len(lv):
        return range(0)
    first_i = int((lv.keys[0] >> (2 * KEY_BITS)) - KEY_OFFSET)
    last_i = int((lv.keys[-1] >> (2 * KEY_BITS)) - KEY_OFFSET)
    return range(first_i >> _qk.BRICK_BITS, ((last_i + order - 1) >> _qk.BRICK_BITS) + 1)


class _NotQuantisable(Exception):
    """A level's coefficients are not all multiples of the index's value step (or a brick
    spans more steps than int16 holds): the index is built with float64 values."""


MIXED_WIDTHS = True
"""Quantised tables are int16 with a base per brick, a brick spanning more than 65,535
steps holding int32 values in two int16 slots each (:func:`geoidspline._kernels.query.quantise_mixed`);
False: int16 while every brick fits, else int32 throughout (the tables of before
2026-12-06, which older kernel libraries read: benchmarks)."""


class _Quantised:
    """An index's values held as integers of its step: int16 slots, a base per brick (2
    bytes a value), int32 in two slots for a brick spanning more than 65,535 steps
    (:data:`MIXED_WIDTHS`; else :func:`geoidspline._kernels.query.quantise_table`, int16
    while every brick fits, else int32 for all, the parts so far widened then)."""

    def __init__(self, step):
        self.step = step
        self.dtype = np.int16
        self.values, self.qbases, self._bases = [], [], []

    def add(self, values, base):
        """Add one part of the table's values (bricks from ``base``, local to the part):
        returns each brick's first slot in the part and the part's slots."""
        if MIXED_WIDTHS:
            got = _qk.quantise_mixed(values, base, self.step)
            if got is None:
                raise _NotQuantisable
            self.values.append(got[0])
            self.qbases.append(got[1])
            return got[2], got[0].size
        while True:
            got = _qk.quantise_table(values, base, self.step, self.dtype)
            if got is not None:
                break
            if self.dtype == np.int32:
                raise _NotQuantisable
            self.dtype = np.int32
            for i, (q, qbase, start) in enumerate(zip(self.values, self.qbases, self._bases)):
                counts = np.diff(np.r_[start, q.size])
                self.values[i] = q.astype(np.int32) + np.repeat(qbase, counts)
                self.qbases[i] = np.zeros_like(qbase)
        self.values.append(got[0])
        self.qbases.append(got[1])
        self._bases.append(base)
        return base, values.size


class _Slab:
    """One row of a level's bricks (those with brick index ``row`` along the first axis):
    each of the level's coefficients listed once per brick of the row whose table holds it.

    A brick's table covers the B-splines touching its cells: ``k`` in
    ``[b S - n + 1, b S + S - 1]`` per axis, so a coefficient is in 1 to 8 bricks.
    Entries are sorted by (brick key, local position), local position
    ``(lx * side + ly) * side + lz`` with ``l = k - b S + n - 1`` in 0..side-1.
    """

    def __init__(self, lv, order, row):
        bits = _qk.BRICK_BITS
        lo, hi = _row_span(lv, order, row)
        (self.brick_keys, self.brick_start, self.brick_of_entry, self.local,
         coef) = _qk.brick_row_entries(lv.keys[lo:hi], order, bits, row)
        self.coef_index = coef + np.int32(lo)  # int32 positions in the level's coefficients


class _Members:
    """A level's coefficients by bricks, one row of bricks at a time (:class:`_Slab`).

    Listing every (brick, coefficient) pair of a level at once took 34 bytes an entry
    (2.3 entries a coefficient for order 6): 0.8 GB for the 5.6 M coefficients of the
    EGM96 2 mm store. A row holds a few % of them and is let go once used: the own
    tables are built row by row, and folding finer levels computes the rows of the
    parents it needs again (the last one is kept, as parents come in key order).
    """

    def __init__(self, lv, order):
        self.lv = lv
        self.order = order
        self.coefficients = lv.coefficients
        self.rows = _brick_rows(lv, order)
        self._cached = None

    def slab(self, row) -> _Slab:
        if self._cached is None or self._cached[0] != row:
            self._cached = (row, _Slab(self.lv, self.order, row))
        return self._cached[1]

    def scatter(self, keys, dense):
        """Add the coefficients into dense (len(keys), side³) blocks of bricks ``keys``
        (sorted)."""
        side = (1 << _qk.BRICK_BITS) + self.order - 1
        rows = (keys >> (2 * KEY_BITS)) - KEY_OFFSET
        bounds = np.r_[0, np.flatnonzero(rows[1:] != rows[:-1]) + 1, keys.size]
        flat_dense = dense.reshape(keys.size, -1)
        for a, b in zip(bounds[:-1], bounds[1:]):
            slab = self.slab(int(rows[a]))
            if not slab.brick_keys.size:
                continue
            at = np.minimum(np.searchsorted(slab.brick_keys, keys[a:b]), slab.brick_keys.size - 1)
            found = slab.brick_keys[at] == keys[a:b]
            starts = np.where(found, slab.brick_start[at], 0)
            counts = np.where(found, slab.brick_start[at + 1] - slab.brick_start[at], 0)
            total = int(counts.sum())
            if total == 0:
                continue
            block = np.repeat(np.arange(a, b), counts)
            entry = np.repeat(starts - (np.cumsum(counts) - counts), counts) + np.arange(total)
            local = slab.local[entry].astype(np.int32)
            flat = (local[:, 0] * side + local[:, 1]) * side + local[:, 2]
            flat_dense[block, flat] += self.coefficients[slab.coef_index[entry]]


_BRICKS_PER_COEFFICIENT = 1 / 256  # the own tables' first capacity (grown when a row needs more)
_VALUES_PER_COEFFICIENT = 3.0


def _grown(array, used, size):
    """A zeroed array of ``size`` rows holding ``array``'s first ``used`` rows."""
    out = np.zeros((size,) + array.shape[1:], array.dtype)
    out[:used] = array[:used]
    return out


def _own_tables(lv, order, quantised):
    """The own table of a level straight from its keys, one row of bricks at a time
    (:func:`geoidspline._kernels.query.own_table_fill`), into arrays of the level's size
    (no parts joined; their capacity is what single-level stores need, 2.3 values and
    1/940 bricks a coefficient at order 6, grown when a row needs more): (brick keys,
    value base per brick, int32 columns (nb, side, side) and values as lists of parts,
    the number of values).

    ``quantised`` (a :class:`_Quantised`) not None: the values go to it instead, row by
    row (no value parts returned), or :class:`_NotQuantisable` is raised."""
    side = (1 << _qk.BRICK_BITS) + order - 1
    n = len(lv)
    max_bricks = int(n * _BRICKS_PER_COEFFICIENT) + 64
    brick_keys = np.empty(max_bricks, np.int64)
    base = np.empty(max_bricks, np.int64)
    cols = np.zeros((max_bricks, side, side), np.int32)
    values = np.zeros(int(n * _VALUES_PER_COEFFICIENT) + 64)  # the level's, or one row's when quantised (zeroed again after use)
    b_at = v_at = 0
    for row in _brick_rows(lv, order):
        lo, hi = _row_span(lv, order, row)
        if lo == hi:
            continue
        while True:
            nb, total, written = _qk.own_table_fill(lv.keys[lo:hi], lv.coefficients[lo:hi], order, row,
                                                    brick_keys[b_at:], base[b_at:], cols[b_at:],
                                                    values if quantised is not None else values[v_at:])
            if written:
                break
            if b_at + nb > brick_keys.shape[0]:
                grown = max(2 * brick_keys.shape[0], b_at + nb)
                brick_keys, base, cols = (_grown(a, b_at, grown) for a in (brick_keys, base, cols))
            need = total if quantised is not None else v_at + total
            if need > values.shape[0]:
                values = _grown(values, 0 if quantised is not None else v_at, max(2 * values.shape[0], need))
        if quantised is not None:  # bases and sizes in the quantised table's slots
            starts, slots = quantised.add(values[:total].copy(), base[b_at:b_at + nb].copy())
            values[:total] = 0.0
            base[b_at:b_at + nb] = starts
            total = slots
        base[b_at:b_at + nb] += v_at
        b_at += nb
        v_at += total
    if not b_at:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), [], [], 0
    value_parts = [values[:v_at]] if quantised is None else []
    return brick_keys[:b_at], base[:b_at], [cols[:b_at]], value_parts, v_at


def _joined(parts, dtype, shape):
    """``np.concatenate(parts)``, letting each part go once copied (``parts`` is emptied):
    the index is never held twice. One part of that dtype is returned as it is."""
    if len(parts) == 1 and parts[0].dtype == dtype:
        return parts.pop()
    total = sum(p.shape[0] for p in parts)
    out = np.empty((total,) + tuple(np.atleast_1d(shape)[1:]), dtype)
    at = 0
    while parts:
        part = parts.pop(0)
        out[at:at + part.shape[0]] = part
        at += part.shape[0]
        del part
    return out


def _column_tables(nb, side, run_brick, run_cx, run_cy, run_k0, run_len):
    """Column entries of runs sorted by brick: (base per brick, int32 columns, run starts).

    Run ``r`` occupies values ``start[r] .. start[r] + len[r] - 1`` of the table's value
    block; the column entry stores its offset from its brick's base.
    """
    run_start = np.r_[0, np.cumsum(run_len)[:-1]].astype(np.int64)
    base = np.zeros(nb, dtype=np.int64)
    first = np.r_[True, run_brick[1:] != run_brick[:-1]] if run_brick.size else np.zeros(0, bool)
    base[run_brick[first]] = run_start[first]
    rel = run_start - base[run_brick]
    cols = np.zeros((nb, side, side), dtype=np.int32)
    cols[run_brick, run_cx, run_cy] = ((rel << _qk.COL_SHIFT) | (run_k0 << _qk.COL_KBITS)
                                       | run_len).astype(np.int32)
    return base, cols, run_start


def _sliding(values, width, axis, func):
    """func (np.minimum / np.maximum) over windows ``[c - width + 1, c]`` of values along
    axis, for c = 0 .. n + width - 2 (outside the array: the other operand's identity)."""
    n = values.shape[axis]
    fill = np.iinfo(np.int64).max if func is np.minimum else -1
    pad = [(0, 0)] * values.ndim
    pad[axis] = (width - 1, width - 1)
    padded = np.pad(values, pad, constant_values=fill)
    out = None
    for s in range(width):
        part = np.take(padded, np.arange(s, s + n + width - 1), axis=axis)
        out = part if out is None else func(out, part)
    return out


class BrickIndex:
    """The query structure of a spline: every level's coefficients regrouped by bricks.

    A brick is a cube of ``S = 2**BRICK_BITS`` cells of its level; its tables cover the
    ``side = S + order - 1`` B-splines per axis touching its cells, one contiguous run
    of k per (i, j) column. A level has a brick wherever one of its own B-splines
    touches a cell of the brick. Each brick has two tables:

    - *own*: the level's own coefficients S_ℓ;
    - *folded* (levels nested in all coarser ones, h_ℓ = h_coarsest / 2^d): the
      coefficients of S_0 + … + S_ℓ written on level ℓ's grid (subdivision of the
      coarser levels, :func:`refinement_weights`, plus the level's own), for every
      B-spline touching a cell of the brick that meets the *band*
      ``1 - w_ℓ <= |x| <= 1 + w_ℓ``, ``w_ℓ = FOLD_BAND_CELLS * h_ℓ``. For the coarsest
      level both tables are its own coefficients, complete (no band).

    A point is evaluated from the finest level down: the first level with a brick at
    the point whose band holds the point is evaluated from its folded table and ends
    the sum; a level with a brick there but outside its band adds its own table and
    the descent goes on (see :func:`geoidspline._kernels.query.evaluate_bricks`). Points on
    the sphere thus cost one level; the result is the exact sum Σ_ℓ S_ℓ (up to
    rounding) at every point of R³, on or off the sphere. Levels of equal spacing are
    summed; a level not nested in the coarser ones (and every finer one) is not
    folded and always evaluated on its own.

    The folded values are computed per brick in dense (side³) blocks, each from its
    parent brick's block by separable subdivision (recursively up to the coarsest
    level, for :data:`_FOLD_CHUNK_BRICKS` bricks at a time), then cut to the band.
    With ``fold=False`` no folded tables are built (every level is evaluated from its
    own table and the levels are summed): a fraction of the build time and memory
    (small batches are evaluated with numpy instead, see :class:`AmbientSpline`).
    Without folded tables (one level, or none nested) every value is a level's own
    coefficient; given ``value_step`` (metres: a store's, whose coefficients are
    multiples of it or of a power-of-two fraction of it, bitwise), the tables of a spline
    of :data:`QUANTISE_FROM_COEFFICIENTS` coefficients or more (or any, ``quantise=True``)
    hold those integers instead of float64: int16 with a base per brick, or int32 (in two
    int16 slots) for a brick spanning more than 65,535 steps (:data:`MIXED_WIDTHS`), the int16
    ones about the middle of their brick's range. Points whose cell's columns are all
    full (most) are summed from those integers and the brick's base added once: within
    16 units in the last place of the largest coefficient of the float64 tables' result
    (below 1e-13 m for a geoid's ±110 m); the others from the coefficients as the
    store's decoder gives them, bitwise as the float64 tables (tests in
    ``tests/test_query_index.py``). Such an index holds one copy of its column tables
    (own and folded are the same).
    Memory: :attr:`nbytes`. Immutable once built; evaluation is
    thread-safe.
    """

    def __init__(self, levels, order, fold=True, value_step=None, quantise=False):
        bits = _qk.BRICK_BITS
        cells = 1 << bits
        side = cells + order - 1
        if side > (1 << _qk.COL_KBITS) - 1:
            raise ValueError(f"spline order {order} too high for the query tables")
        self.order = order
        self.levels = tuple(_merge_levels(levels))
        self.depths = tuple(_fold_depths(self.levels)) if self.levels else ()
        self._side = side
        self._weights = refinement_weights(order)
        folded = [i > 0 and fold and d is not None for i, d in enumerate(self.depths)]
        # without folded tables every value is a level's own coefficient: a store's are
        # multiples of its step, held as int16 (2 bytes, not 8) when they all are
        self.value_step = None
        large = sum(len(lv) for lv in self.levels) >= QUANTISE_FROM_COEFFICIENTS
        if value_step is not None and not any(folded) and self.levels and (large or quantise):
            steps = [_qk.finest_step(lv.coefficients, float(value_step), _STEP_HALVINGS) for lv in self.levels]
            self.value_step = None if None in steps else min(steps)
        try:
            self._build(folded)
        except _NotQuantisable:
            self.value_step = None
            self._build(folded)

    def _build(self, folded):
        order, side = self.order, self._side
        members = [_Members(lv, order) for lv in self.levels]
        self._members_at_depth = {d: m for d, m in zip(self.depths, members) if d is not None}
        slot_tables, slot_start, slot_mask, presence = [], [], [], []
        fold_bases, fold_cols, own_bases, own_cols, values = [], [], [], [], []
        quantised = _Quantised(self.value_step) if self.value_step is not None else None
        band_lo2, band_hi2 = [], []
        value_base = 0
        slot_base = 0
        brick_base = 0
        for i, lv in enumerate(self.levels):
            brick_keys, base, col_parts, own_parts, own_size = _own_tables(lv, order, quantised)
            nb = brick_keys.size
            own_bases.append(base + value_base)
            own_cols.extend(col_parts)
            values.extend(own_parts)
            value_base += own_size
            if not folded[i]:
                fold_bases.append(base + value_base - own_size)
                fold_cols.append((brick_base, brick_base + nb))  # its own columns, copied once joined
                band_lo2.append(-np.inf if i == 0 else np.inf)
                band_hi2.append(np.inf if i == 0 else -np.inf)
            else:
                width = FOLD_BAND_CELLS * lv.h
                base, cols, folded_values = self._folded_tables(self.depths[i], lv.h, brick_keys, width)
                fold_bases.append(base + value_base)
                fold_cols.append(cols)
                values.append(folded_values)
                value_base += folded_values.size
                band_lo2.append(max(0.0, 1.0 - width) ** 2)
                band_hi2.append((1.0 + width) ** 2)
            slots = _qk.build_hash(brick_keys)
            slots[:, 1] = np.where(slots[:, 1] >= 0, slots[:, 1] + brick_base, -1)
            brick_base += nb
            slot_tables.append(slots)
            slot_start.append(slot_base)
            slot_mask.append(slots.shape[0] - 1)
            slot_base += slots.shape[0]
            presence.append(self._presence(brick_keys, lv.h))
        self._members_at_depth = None  # only needed while building
        cat = _joined
        self.inv_hs = np.array([1.0 / lv.h for lv in self.levels], dtype=np.float64)
        self.band_lo2 = np.array(band_lo2, dtype=np.float64)
        self.band_hi2 = np.array(band_hi2, dtype=np.float64)
        self.slots = cat(slot_tables, np.int64, (0, 2))
        self.slot_start = np.array(slot_start, dtype=np.int64)
        self.slot_mask = np.array(slot_mask, dtype=np.int64)
        self.own_base = cat(own_bases, np.int64, 0)
        self.own_cols = cat(own_cols, np.int32, (0, side, side))
        if quantised is not None:
            self.values = np.zeros(0)
            self.qvalues = cat(quantised.values, quantised.dtype, 0)
            self.qbase = cat(quantised.qbases, np.int32, 0)
        else:
            self.values = cat(values, np.float64, 0)
            self.qvalues = self.qbase = None
        # quantised tables' column offsets as int16 (every brick's fit: full_columns)
        offs_dtype = np.int16 if quantised is not None else np.int32
        self.own_offs, self.own_full = _qk.full_columns(self.own_cols, order, offs_dtype)
        if any(folded):
            self.fold_base = cat(fold_bases, np.int64, 0)
            fold_cols = [self.own_cols[p[0]:p[1]] if isinstance(p, tuple) else p for p in fold_cols]
            self.fold_cols = cat(fold_cols, np.int32, (0, side, side))
            self.fold_offs, self.fold_full = _qk.full_columns(self.fold_cols, order)
        else:  # every level evaluated from its own table: one copy of the tables
            self.fold_base, self.fold_cols = self.own_base, self.own_cols
            self.fold_offs, self.fold_full = self.own_offs, self.own_full
        n = _qk.PRESENCE_SIDE
        self.presence = np.stack(presence) if presence else np.zeros((0, n, n, n), np.uint8)
        self.fold_size = None
        if quantised is None and self.values.nbytes >= PREFETCH_BRICKS_FROM_BYTES:
            # a brick's folded table ends where its furthest column run does
            runs = self.fold_cols.reshape(self.fold_cols.shape[0], -1)
            ends = (runs >> _qk.COL_SHIFT) + (runs & ((1 << _qk.COL_KBITS) - 1))
            self.fold_size = np.ascontiguousarray(ends.max(axis=1, initial=0), dtype=np.int64)
        self._spline = None

    @property
    def spline(self) -> _qk.Spline:
        """The tables as the kernels take them (one record, built on first use)."""
        if self._spline is None:
            self._spline = _qk.Spline.of(self.order, self.inv_hs, self.band_lo2, self.band_hi2, self.presence,
                                         self.slots, self.slot_start, self.slot_mask, self.fold_base,
                                         self.fold_cols, self.own_base, self.own_cols, self.values,
                                         self.fold_offs, self.fold_full, self.own_offs, self.own_full,
                                         self.qvalues, self.qbase, self.value_step or 0.0, self.fold_size)
        return self._spline

    def __getstate__(self):
        state = self.__dict__.copy()
        state["_spline"] = None  # addresses of this process's arrays
        return state

    # -- folding ------------------------------------------------------------------

    def _dense_full(self, depth, keys):
        """Dense (len(keys), side, side, side) coefficients of S_0 + … + S_depth.

        ``keys``: sorted, unique packed brick keys at ``depth``; each block covers the
        brick's whole table. A block is its parent brick's block (brick >> 1, which
        holds every parent of the block's B-splines) subdivided, plus the level's own
        coefficients (a depth with no level of its own adds nothing).
        """
        side = self._side
        if depth == 0:
            dense = np.zeros((keys.size, side, side, side))
        else:
            dense = np.empty((keys.size, side, side, side))
            tri = unpack_keys(keys)
            parent_keys, parent_of = np.unique(pack_keys(tri >> 1), return_inverse=True)
            parents = self._dense_full(depth - 1, parent_keys)
            _qk.subdivide_bricks(parents, parent_of, np.ascontiguousarray(tri & 1), self._weights, dense)
            del parents
        members = self._members_at_depth.get(depth)
        if members is not None:
            members.scatter(keys, dense)
        return dense

    def _band_runs(self, keys, h, width):
        """Per column of each brick, the local k run needed for the band (lo, hi, valid)."""
        n = self.order
        cells = 1 << _qk.BRICK_BITS
        r0 = max(0.0, 1.0 - width - 1e-9)
        r1 = 1.0 + width + 1e-9
        lo = ((unpack_keys(keys) * cells)[:, :, None] + np.arange(cells)) * h  # (nb, 3, S)
        hi = lo + h
        near = np.where(lo > 0, lo, np.where(hi < 0, hi, 0.0)) ** 2
        far = np.maximum(lo * lo, hi * hi)
        near2 = near[:, 0, :, None, None] + near[:, 1, None, :, None] + near[:, 2, None, None, :]
        far2 = far[:, 0, :, None, None] + far[:, 1, None, :, None] + far[:, 2, None, None, :]
        meets = (near2 <= r1 * r1) & (far2 >= r0 * r0)  # (nb, S, S, S) cells meeting the band
        anyz = meets.any(axis=3)
        zmin = np.where(anyz, meets.argmax(axis=3), np.iinfo(np.int64).max)
        zmax = np.where(anyz, cells - 1 - meets[..., ::-1].argmax(axis=3), -1)
        # column c touches cells c - n + 1 .. c (local); its k run is [min a_z, max a_z + n - 1]
        zmin = _sliding(_sliding(zmin, n, 1, np.minimum), n, 2, np.minimum)
        zmax = _sliding(_sliding(zmax, n, 1, np.maximum), n, 2, np.maximum)
        return zmin, zmax + n - 1, zmax >= 0

    def _folded_tables(self, depth, h, brick_keys, width):
        side = self._side
        run_parts = []
        value_parts = []
        for at in range(0, brick_keys.size, _FOLD_CHUNK_BRICKS):
            keys = brick_keys[at:at + _FOLD_CHUNK_BRICKS]
            dense = self._dense_full(depth, keys)
            k_lo, k_hi, valid = self._band_runs(keys, h, width)
            b, cx, cy = np.nonzero(valid)
            k0 = k_lo[b, cx, cy]
            length = k_hi[b, cx, cy] - k0 + 1
            total = int(length.sum())
            first = ((b * side + cx) * side + cy) * side + k0
            offsets = np.r_[0, np.cumsum(length)[:-1]]
            flat = np.repeat(first - offsets, length) + np.arange(total)
            value_parts.append(dense.reshape(-1)[flat])
            run_parts.append((b + at, cx, cy, k0, length))
        run_brick, run_cx, run_cy, run_k0, run_len = (np.concatenate(p) for p in zip(*run_parts))
        base, cols, _ = _column_tables(brick_keys.size, side, run_brick, run_cx, run_cy, run_k0, run_len)
        return base, cols, np.concatenate(value_parts)

    @staticmethod
    def _presence(brick_keys, h):
        """Coarse cells (side PRESENCE_CELL) that some brick of the level overlaps."""
        n = _qk.PRESENCE_SIDE
        cell = _qk.PRESENCE_CELL
        span = (1 << _qk.BRICK_BITS) * h
        lo = unpack_keys(brick_keys) * span
        first = np.floor(lo / cell).astype(np.int64) + n // 2
        last = np.floor((lo + span) / cell).astype(np.int64) + n // 2
        grid = np.zeros((n, n, n), np.uint8)
        for a, b in zip(np.clip(first, 0, n - 1), np.clip(last, 0, n - 1)):
            grid[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = 1
        return grid

    @property
    def nbytes(self) -> int:
        arrays = (self.slots, self.fold_base, self.fold_cols, self.own_base, self.own_cols, self.values,
                  self.qvalues, self.qbase, self.presence, self.fold_offs, self.fold_full, self.own_offs,
                  self.own_full, self.fold_size)
        return sum(a.nbytes for a in {id(a): a for a in arrays if a is not None}.values())  # shared ones once

    @property
    def hot_bytes(self) -> int:
        """Bytes of the tables a point on the sphere reads: the hash slots, presence maps,
        folded column offsets and full maps, and the values (own tables' columns and the
        folded column entries only serve points off the sphere or in gaps)."""
        values = self.qvalues if self.qvalues is not None else self.values
        return int(sum(a.nbytes for a in (self.slots, self.presence, self.fold_offs, self.fold_full, values)))

    def add_to(self, points, out, nderiv=0, ordered=False):
        """Add the spline (nderiv 0) or value and derivatives (1, 2) at points (M, 3) to out.

        From :data:`_ORDER_THRESHOLD` points on, the points are evaluated in a
        locality-preserving order (:func:`geoidspline._kernels.query.query_order`, a counting
        sort on a coarse Z-order grid) so that neighbours share bricks and cache lines;
        each point's result does not depend on the order. ``ordered``: the points are in
        such an order already (a caller evaluating many splines at the same points sorts
        them once) and are evaluated as they come.
        """
        if not self.inv_hs.size:
            return
        if points.shape[0] >= _ORDER_THRESHOLD and not ordered:
            visit = _qk.query_order(points)
            ordered_out = np.zeros_like(out)
            self._evaluate(np.take(points, visit, axis=0), ordered_out, nderiv)
            out[visit] += ordered_out
        else:
            self._evaluate(points, out, nderiv)

    def undulation_latlon(self, latitude, longitude, max_abs_longitude=math.inf):
        """Values (M,) at the directions of 1-D latitude/longitude arrays (degrees), in
        one compiled call (:func:`geoidspline._kernels.query.undulation_latlon`).

        Returns ``(values, invalid)``: ``invalid`` counts the coordinates refused (a
        latitude beyond ±90° or infinite, a longitude infinite or beyond
        ±``max_abs_longitude`` degrees), and when it is not 0 the values are unset.
        """
        m = latitude.shape[0]
        out = np.empty(m)
        if not self.inv_hs.size:
            with np.errstate(invalid="ignore"):
                invalid = np.count_nonzero((np.abs(latitude) > 90.0) | np.isinf(longitude)
                                           | (np.abs(longitude) > max_abs_longitude))
            out[:] = 0.0
            out[np.isnan(latitude) | np.isnan(longitude)] = np.nan
            return out, invalid
        # blocks of at least 2**15 points, up to 4 per thread (a histogram of 32,769
        # counts each)
        nblocks = max(1, min(4 * threads(), m >> 15))
        invalid = _qk.undulation_latlon(self.spline, latitude, longitude, nblocks, out, max_abs_longitude,
                                        in_order=self.hot_bytes <= IN_ORDER_MAX_BYTES)
        return out, int(invalid)

    def _evaluate(self, points, out, nderiv):
        _qk.evaluate_bricks(self.spline, points, nderiv, out)
