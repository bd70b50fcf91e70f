"""Kernels of queries: the brick index, its evaluation and batches of latitude/longitude.

The grid, B-spline and key conventions are those of :mod:`geoidspline._kernels`. C:
``src/query.c``; a spline's tables travel to it as one record (:class:`Spline`).

The validated API is :mod:`geoidspline.bspline.index`.
"""

from __future__ import annotations

import ctypes
import math

import numpy as np

from ._clib import F64, I64, PTR, c_in, c_out, function, ptr, threads
from .layout import KEY_BITS, KEY_OFFSET

BRICK_BITS = 4


# a column entry (int32): run offset from the brick's base << COL_SHIFT | first local
# k << COL_KBITS | run length; local k and lengths are < 2**COL_KBITS
COL_KBITS = 5


COL_SHIFT = 2 * COL_KBITS


PRESENCE_CELL = 0.125  # side of the coarse cells of the per-level presence map


PRESENCE_SIDE = 20  # covers [-1.25, 1.25) on each axis


class Spline(ctypes.Structure):
    """The query tables of one spline, as ``src/query.c``'s ``gs_spline`` (field for field).

    Built once per index by :meth:`of`, which keeps the arrays referenced for as long as
    the record lives; the kernels take a pointer to it."""

    _fields_ = [("order", I64), ("nlev", I64), ("side", I64),
                ("inv_hs", PTR), ("band_lo2", PTR), ("band_hi2", PTR), ("presence", PTR),
                ("slots", PTR), ("slot_start", PTR), ("slot_mask", PTR),
                ("fold_base", PTR), ("own_base", PTR), ("fold_cols", PTR), ("own_cols", PTR),
                ("values", PTR), ("fold_offs", PTR), ("own_offs", PTR), ("fold_full", PTR), ("own_full", PTR),
                ("qvalues", PTR), ("qbase", PTR), ("value_step", F64), ("qwidth", I64), ("fold_size", PTR)]

    @classmethod
    def of(cls, order, inv_hs, band_lo2, band_hi2, presence, slots, slot_start, slot_mask, fold_base, fold_cols,
           own_base, own_cols, values, fold_offs, fold_full, own_offs, own_full, qvalues=None, qbase=None,
           value_step=0.0, fold_size=None) -> "Spline":
        """``presence`` (levels, PRESENCE_SIDE³) uint8; ``slots`` (capacity, 2) int64;
        ``fold_cols``/``own_cols`` and ``fold_offs``/``own_offs`` (bricks, side, side) int32
        (the offsets int16 with quantised values),
        ``fold_full``/``own_full`` (bricks, 2**BRICK_BITS, 2**BRICK_BITS) uint16 (see
        :func:`full_columns`); the rest per level or per brick (int64) and ``values``
        float64. Quantised tables (:func:`quantise_table`): ``qvalues`` int16 or int32 and
        ``qbase`` int32 per brick with ``value_step`` (metres), ``values`` then unused;
        ``None`` (the default): the float64 ``values``. ``fold_size`` (int64 per brick, the
        values of its folded table) asks the kernels to prefetch the bricks ahead of a batch's
        points (float64 tables beyond the caches); ``None``: they do not. Every array must be
        C-contiguous already."""
        arrays = dict(inv_hs=(inv_hs, np.float64), band_lo2=(band_lo2, np.float64),
                      band_hi2=(band_hi2, np.float64), presence=(presence, np.uint8), slots=(slots, np.int64),
                      slot_start=(slot_start, np.int64), slot_mask=(slot_mask, np.int64),
                      fold_base=(fold_base, np.int64), own_base=(own_base, np.int64),
                      fold_cols=(fold_cols, np.int32), own_cols=(own_cols, np.int32), values=(values, np.float64),
                      # int16 offsets with quantised values (src/query.c's column_offset)
                      fold_offs=(fold_offs, np.int32 if qvalues is None else np.int16),
                      own_offs=(own_offs, np.int32 if qvalues is None else np.int16),
                      fold_full=(fold_full, np.uint16), own_full=(own_full, np.uint16))
        if fold_size is not None:
            arrays.update(fold_size=(fold_size, np.int64))
        if qvalues is not None:
            arrays.update(qvalues=(qvalues, np.int32 if qvalues.dtype == np.int32 else np.int16),
                          qbase=(qbase, np.int32))
        for name, (array, dtype) in arrays.items():
            if array.dtype != np.dtype(dtype) or not array.flags.c_contiguous:
                raise TypeError(f"{name} must be a C-contiguous {np.dtype(dtype)} array (got {array.dtype})")
        record = cls(order=int(order), nlev=int(inv_hs.shape[0]), side=(1 << BRICK_BITS) + int(order) - 1,
                     value_step=float(value_step) if qvalues is not None else 0.0,
                     qwidth=qvalues.dtype.itemsize if qvalues is not None else 0,
                     **{name: ptr(array) for name, (array, _) in arrays.items()})
        record._arrays = arrays  # the tables live as long as the record
        return record


_SPLINE = ctypes.POINTER(Spline)
_evaluate_bricks = function("gs_evaluate_bricks", _SPLINE, PTR, I64, I64, PTR, I64)
_undulation_latlon = function("gs_undulation_latlon", _SPLINE, PTR, PTR, I64, I64, PTR, I64, F64, I64,
                             restype=I64)
_unit_vectors = function("gs_unit_vectors", PTR, PTR, I64, PTR, I64)
_query_order = function("gs_query_order", PTR, I64, PTR, PTR)
_build_hash = function("gs_build_hash", PTR, I64, PTR, I64)
_brick_row_entries = function("gs_brick_row_entries", PTR, I64, I64, I64, I64, I64, PTR, PTR, PTR, PTR, PTR, PTR,
                              restype=I64)
_own_table_row = function("gs_own_table_row", PTR, I64, PTR, PTR, PTR, I64, PTR, PTR, PTR, restype=I64)
_own_table_keys = function("gs_own_table_keys", PTR, I64, PTR, I64, I64, I64, I64, PTR, PTR, PTR, PTR, PTR,
                           restype=I64)
_finest_step = function("gs_finest_step", PTR, I64, F64, I64, restype=I64)
_quantise_table = function("gs_quantise_table", PTR, I64, PTR, I64, F64, I64, PTR, PTR, restype=I64)
_quantise_mixed = function("gs_quantise_mixed", PTR, I64, PTR, I64, F64, PTR, PTR, PTR, restype=I64)
_full_columns = function("gs_full_columns", PTR, I64, I64, PTR, I64, PTR)
_quantised_sums_level = function("gs_quantised_sums_level", I64, restype=I64)
_subdivide_bricks = function("gs_subdivide_bricks", PTR, I64, PTR, PTR, PTR, I64, PTR, I64, I64)


def brick_row_entries(keys, order, bits, row):
    """Every (brick, coefficient) pair of one row of a level's bricks (brick index ``row``
    on the first axis): a B-spline is listed in each brick of ``2**bits`` cells a side
    whose tables hold it (1 to 8, see :class:`geoidspline.bspline.index._Slab`).

    ``keys``: sorted packed keys (those outside the row are skipped). Returns
    ``(brick_keys (B,), brick_start (B + 1,), brick_of_entry (E,), local (E, 3) int16,
    coefficient index (E,) int32)``, entries sorted by (brick key, local position) (a
    counting sort by brick over the keys in order); ``local = k - brick 2**bits + order - 1``
    per axis.
    """
    keys = c_in(keys, np.int64)
    # the row's keys are one run of the sorted keys (first index a0 from row 2**bits -
    # order + 1 to row 2**bits + 2**bits - 1, the major part of the key): scanning only
    # it makes a level's rows cost one pass over its keys, not one pass a row
    a0_first = (row << bits) - order + 1
    a0_end = (row + 1) << bits
    first, last = np.searchsorted(keys, [(a0_first + KEY_OFFSET) << (2 * KEY_BITS),
                                         (a0_end + KEY_OFFSET) << (2 * KEY_BITS)])
    run = keys[first:last]
    bound = 4 * run.size  # a key is in at most 2 x 2 bricks of one row
    brick_keys = np.empty(bound, np.int64)
    brick_start = np.empty(bound + 1, np.int64)
    brick_of_entry = np.empty(bound, np.int32)
    local = np.empty((bound, 3), np.int16)  # 0 .. 2**bits + order - 2: small (memory)
    coef = np.empty(bound, np.int32)
    sizes = np.zeros(2, np.int64)
    if _brick_row_entries(ptr(run), run.size, int(first), int(order), int(bits), int(row), ptr(brick_keys),
                          ptr(brick_start), ptr(brick_of_entry), ptr(local), ptr(coef), ptr(sizes)) != 0:
        raise MemoryError("brick_row_entries: out of memory")
    nb, total = int(sizes[0]), int(sizes[1])
    # views: the bound's unused tail was never written, so its pages were never touched;
    # a row's entries are transient (copies cost 12 % of building the 2 mm store's index)
    return brick_keys[:nb], brick_start[:nb + 1], brick_of_entry[:total], local[:total], coef[:total]


def own_table_row(brick_start, local, coef_index, coefficients, side):
    """The own table of one row of bricks from its entries (:func:`brick_row_entries`):
    ``(base (B,), columns (B, side, side) int32, values)``.

    A run per (brick, column lx, ly) from its first to its last local k (gaps hold 0),
    runs in entry order; the column entry is the run's offset from its brick's base
    ``<< COL_SHIFT | first k << COL_KBITS | length``. Two passes: count, then fill.
    """
    brick_start = c_in(brick_start, np.int64)
    local = c_in(local, np.int16)
    coef_index = c_in(coef_index, np.int32)
    coefficients = c_in(coefficients, np.float64)
    nb = brick_start.size - 1
    args = (ptr(brick_start), nb, ptr(local), ptr(coef_index), ptr(coefficients), int(side))
    total = _own_table_row(*args, None, None, None)
    base = np.zeros(nb, np.int64)
    cols = np.zeros((nb, side, side), np.int32)
    values = np.zeros(total)
    _own_table_row(*args, ptr(base), ptr(cols), ptr(values))
    return base, cols, values


def own_table_fill(keys, coefficients, order, row, brick_keys, base, cols, values):
    """The own table of one row of a level's bricks straight from its keys, written into
    ``brick_keys`` (B,), ``base`` (B,), ``cols`` (B, side, side) int32 and ``values``
    (zeroed, C-contiguous) when it fits them: returns ``(bricks, values, written)``. The
    same table as :func:`brick_row_entries` then :func:`own_table_row` give.

    ``keys``: the level's sorted keys whose first index is in ``[row S - order + 1, row S
    + S - 1]`` (``S = 2**BRICK_BITS``), ``coefficients`` theirs.
    """
    keys = c_in(keys, np.int64)
    coefficients = c_in(coefficients, np.float64)
    side = (1 << BRICK_BITS) + int(order) - 1
    for name, array, dtype in (("brick_keys", brick_keys, np.int64), ("base", base, np.int64),
                               ("cols", cols, np.int32), ("values", values, np.float64)):
        if array.dtype != dtype or not array.flags.c_contiguous:
            raise TypeError(f"{name} must be a C-contiguous {np.dtype(dtype)} array")
    capacity = min(brick_keys.shape[0], base.shape[0], cols.shape[0])
    if cols.shape[1:] != (side, side):
        raise TypeError(f"cols must be (bricks, {side}, {side})")
    sizes = np.zeros(2, np.int64)
    done = _own_table_keys(ptr(keys), keys.size, ptr(coefficients), int(order), int(row), capacity, values.shape[0],
                           ptr(brick_keys), ptr(base), ptr(cols), ptr(values), ptr(sizes))
    if done < 0:
        raise MemoryError("own_table_keys: out of memory")
    return int(sizes[0]), int(sizes[1]), done == 0


def finest_step(coefficients, step, max_halvings):
    """The coarsest ``step / 2**k`` (``k <= max_halvings``) of which every coefficient is a
    multiple, bitwise as a store's decoder makes them (``(double)(int32) q * step``), or
    ``None``."""
    coefficients = c_in(coefficients, np.float64)
    k = _finest_step(ptr(coefficients), coefficients.size, float(step), int(max_halvings))
    return None if k < 0 else step / 2.0**k


def quantise_table(values, base, step, dtype):
    """A table's values (bricks from ``base``, each up to the next's) as ``(q, qbase int32
    per brick)`` with ``values == (qbase[brick] + q) * step`` bitwise: ``dtype`` int16 (a
    brick's q spanning at most 65,535 steps) or int32 (qbase 0). ``None`` when they are
    not all multiples of ``step`` (as a store's decoder makes them) or do not fit."""
    values = c_in(values, np.float64)
    base = c_in(base, np.int64)
    q = np.empty(values.size, dtype)
    qbase = np.empty(base.size, np.int32)
    if _quantise_table(ptr(values), values.size, ptr(base), base.size, float(step), q.itemsize, ptr(q),
                       ptr(qbase)) != 0:
        return None
    return q, qbase


QBASE_WIDE = -(2**31)  # qbase of a brick of int32 values in an int16 table (quantise_mixed)


def quantise_mixed(values, base, step):
    """A table's values (bricks from ``base``) as int16 slots: ``(q int16, qbase int32 per
    brick, starts int64 per brick)``. A brick whose q span at most 65,535 steps holds
    ``q - qbase`` (as :func:`quantise_table`'s int16), one slot a value; a brick spanning
    more holds its int32 q in two slots a value, ``qbase`` :data:`QBASE_WIDE`; ``starts``:
    each brick's first slot. ``None`` when the values are not all multiples of ``step``
    (as a store's decoder makes them)."""
    values = c_in(values, np.float64)
    base = c_in(base, np.int64)
    q = np.empty(2 * values.size, np.int16)
    qbase = np.empty(base.size, np.int32)
    starts = np.empty(base.size, np.int64)
    used = _quantise_mixed(ptr(values), values.size, ptr(base), base.size, float(step), ptr(q), ptr(qbase),
                           ptr(starts))
    if used < 0:
        return None
    return (q[:used].copy() if used < q.size else q), qbase, starts


def full_columns(cols, order, offs_dtype=np.int32):
    """The full-column maps of a table from its column entries ``cols`` (B, side, side)
    int32: ``(offs (B, side, side) offs_dtype, full (B, 2**BRICK_BITS, 2**BRICK_BITS) uint16)``.

    ``offs``: per column, its run's offset from the brick's base minus its first local k
    (local k of a non-empty column is at ``values[base + offs + k]``); ``full``: per cell
    column (lx, ly) of a brick, bit lz set when all ``order²`` columns ``(lx + p, ly + q)``
    hold local k = lz .. lz + order - 1, so that a point in cell (lx, ly, lz) reads them
    without decoding (the evaluation's fast path; the same products in the same order).
    ``offs_dtype``: int16 (the quantised tables' offsets: a brick's runs hold at most
    ``side**3`` < 2**15 values, so every offset fits) or int32.
    """
    cols = c_in(cols, np.int32)
    cells = 1 << BRICK_BITS
    offs_dtype = np.dtype(offs_dtype)
    if offs_dtype not in (np.dtype(np.int16), np.dtype(np.int32)):
        raise TypeError(f"offs_dtype must be int16 or int32, not {offs_dtype}")
    if offs_dtype == np.int16 and cols.shape[1] ** 3 > np.iinfo(np.int16).max:
        raise ValueError(f"int16 column offsets need side**3 < 2**15 (side {cols.shape[1]})")
    offs = np.empty(cols.shape, offs_dtype)
    full = np.empty((cols.shape[0], cells, cells), np.uint16)
    _full_columns(ptr(cols), cols.shape[0], int(order), ptr(offs), offs_dtype.itemsize, ptr(full))
    return offs, full


def quantised_sums_level(level=None) -> int:
    """Which build sums quantised tables: 0 the target clones, 1 AVX2 (one instruction to
    widen 4 int16), 2 AVX-512DQ (and one to convert them); the same values from each.
    ``level`` sets the widest allowed (as far as the CPU has it), None only asks. Returns
    the previous level. For tests and benchmarks; call it between batches."""
    return int(_quantised_sums_level(-1 if level is None else int(level)))


def build_hash(keys):
    """Open-addressing hash table (linear probing) from key to its position in keys.

    Returns (capacity, 2) int64 slots: (key, position), key -1 for an empty slot; a
    probe reads one 16-byte slot, so one cache line.
    """
    keys = c_in(keys, np.int64)
    capacity = 1
    while capacity < 2 * keys.shape[0] + 2:
        capacity *= 2
    slots = np.empty((capacity, 2), np.int64)
    _build_hash(ptr(keys), keys.size, ptr(slots), capacity)
    return slots


def subdivide_bricks(parents, parent_of, half, weights, out):
    """Brick tables of a spline written on the grid of half the spacing (folding).

    ``parents`` (P, side, side, side) are brick tables on spacing 2h (table index c of
    brick b is B-spline ``b S - n + 1 + c``, S = 2**BRICK_BITS, n = order); child brick
    ``i`` lies in parent brick ``parent_of[i]``, in its half ``half[i]`` (0/1 per axis).
    ``out[i]`` (side³) receives the child's table on spacing h, by the refinement
    relation ``B(x) = Σ_m weights[m] B(2x - m)`` (weights = 2^-(n-1) binom(n, m)).
    """
    parents = c_in(parents, np.float64)
    parent_of = c_in(parent_of, np.int64)
    half = c_in(half, np.int64)
    weights = c_in(weights, np.float64)
    c_out(out, np.float64)
    _subdivide_bricks(ptr(parents), parents.shape[0], ptr(parent_of), ptr(half), ptr(weights), weights.size,
                      ptr(out), out.shape[0], threads())


def query_order(points):
    """A visiting order of points (M, 3) in which neighbours follow each other.

    Counting sort on the Z-order (Morton) index of a coarse cubic grid over
    [-1.25, 1.25)³ (64 cells an axis; points outside are clamped, NaN go last): O(M),
    stable, so the order depends on the points only.
    """
    points = c_in(points, np.float64)
    m = points.shape[0]
    key = np.empty(m, np.int64)
    order = np.empty(m, np.int64)
    _query_order(ptr(points), m, ptr(key), ptr(order))
    return order


def evaluate_bricks(spline, points, nderiv, out):
    """The spline (and derivatives) at points (M, 3), added into out.

    ``spline``: the index's :class:`Spline`. Per point, from the finest level down, the
    first level with a brick at the point whose band holds the point is evaluated from
    its folded table (which includes every coarser level) and the loop stops; a level
    with a brick there but outside its band adds its own table and the loop goes on.
    ``out`` has 1 (value), 4 (+ gradient) or 10 (+ Hessian xx yy zz xy xz yz) columns.
    NaN points are skipped. Visit many points in :func:`query_order` (neighbours share
    bricks and cache lines).
    """
    points = c_in(points, np.float64)
    c_out(out, np.float64)
    if out.shape != (points.shape[0], (1, 4, 10)[nderiv]):
        raise ValueError(f"out must be ({points.shape[0]}, {(1, 4, 10)[nderiv]}) for nderiv {nderiv}")
    _evaluate_bricks(ctypes.byref(spline), ptr(points), points.shape[0], int(nderiv), ptr(out), threads())


def undulation_latlon(spline, latitude, longitude, nblocks, out, max_abs_longitude=math.inf, in_order=False):
    """Spline values at the directions of latitude/longitude (degrees) into out.

    Returns the number of invalid coordinates (a latitude beyond ±90° or infinite, a
    longitude infinite or beyond ±``max_abs_longitude`` degrees); when there are any,
    ``out`` is left unset. NaN gives NaN.
    The points are sorted by the Morton code of their cell (two counting-sort passes:
    buckets of the code's high bits in ``nblocks`` blocks, then within each bucket; the
    cell is that of the finest level's lattice for float64 tables, so that each brick's
    points follow each other, a 0.18° latitude/longitude cell for quantised ones),
    evaluated in that order (neighbours share bricks and cache lines) and the values
    written back to their places; each value does not depend on the order, the blocks or
    the thread count, and equals :func:`evaluate_bricks` at the directions
    :func:`unit_vectors` gives. Transient memory: 20 bytes per point.
    ``in_order``: no sort, the points evaluated as they come (tables in the caches: the
    sort's locality buys nothing there), the same values, no transient memory.
    """
    latitude = c_in(latitude, np.float64)
    longitude = c_in(longitude, np.float64)
    c_out(out, np.float64)
    invalid = _undulation_latlon(ctypes.byref(spline), ptr(latitude), ptr(longitude), latitude.size,
                                 max(1, int(nblocks)), ptr(out), threads(), float(max_abs_longitude),
                                 1 if in_order else 0)
    if invalid < 0:
        raise MemoryError(f"undulation_latlon: out of memory for {latitude.size} points")
    return invalid


def unit_vectors(latitude, longitude, out):
    """Directions (cos φ cos λ, cos φ sin λ, sin φ) of latitude/longitude in degrees into
    out (M, 3): the formula of :func:`undulation_latlon`, so they agree bit for bit
    (sin and cos of the angle in degrees, each within 1.12e-16 of the true one: a table
    of whole degrees and short polynomials, no rounding of the angle in radians)."""
    latitude = c_in(latitude, np.float64)
    longitude = c_in(longitude, np.float64)
    c_out(out, np.float64)
    _unit_vectors(ptr(latitude), ptr(longitude), latitude.size, ptr(out), threads())
