"""Numeric kernels of the ambient B-spline method, free of validation.

Conventions shared by every kernel:

- A level is a uniform grid of spacing ``h`` in R³ (unit sphere units). Cell ``a``
  (an integer triple) is ``[a h, (a+1) h)``; B-spline ``k`` of order ``n`` is the
  tensor product ``Π_d B_n(x_d / h - k_d)`` of the cardinal B-spline on ``[0, n)``,
  so it is non-zero on cells ``k .. k + n - 1`` and a point in cell ``a`` is touched
  by ``k = a - n + 1 .. a`` on each axis.
- Coefficient indices are packed into one int64 key, 21 bits an axis, so that sorting
  keys sorts by (i, j, k) and the ``n`` B-splines of one (i, j) column that touch a
  cell are consecutive keys. That makes a sorted key array a compact sparse 3-D index.

The public, validated API is in :mod:`geoidspline.spline` and :mod:`geoidspline.fit`.
"""

from __future__ import annotations

import numpy as np
import numba

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
_KEY_MASK = (1 << KEY_BITS) - 1
MAX_INDEX = KEY_OFFSET - 16  # room for the n-1 neighbours of the outermost cell

# cache=True keeps compiled code in __pycache__ so a cold process does not recompile.
_jit = numba.njit(cache=True, nogil=True, fastmath=False)
_pjit = numba.njit(cache=True, nogil=True, parallel=True, fastmath=False)


def pack_keys(index):
    """Pack integer triples (..., 3) into int64 keys (no range check)."""
    index = np.asarray(index, dtype=np.int64) + KEY_OFFSET
    return (index[..., 0] << (2 * KEY_BITS)) | (index[..., 1] << KEY_BITS) | index[..., 2]


def unpack_keys(keys):
    """Inverse of :func:`pack_keys`: int64 keys to integer triples (..., 3)."""
    keys = np.asarray(keys, dtype=np.int64)
    out = np.empty(keys.shape + (3,), dtype=np.int64)
    out[..., 0] = (keys >> (2 * KEY_BITS)) & _KEY_MASK
    out[..., 1] = (keys >> KEY_BITS) & _KEY_MASK
    out[..., 2] = keys & _KEY_MASK
    return out - KEY_OFFSET


@_jit
def _pack(i, j, k):
    return ((i + KEY_OFFSET) << (2 * KEY_BITS)) | ((j + KEY_OFFSET) << KEY_BITS) | (k + KEY_OFFSET)


@_jit
def bspline_weights(t, order, nderiv, out):
    """Cardinal B-spline values (and derivatives) touching a point.

    ``t`` in [0, 1) is the position inside the cell. ``out[d, j]`` receives the
    d-th derivative (d = 0..nderiv, with respect to x/h) of ``B_order(t + order-1-j)``,
    the weight of the B-spline ``k = a - order + 1 + j``. Uses the uniform-knot
    de Boor recursion ``w_q[j] = ((t+q-1-j) w_{q-1}[j-1] + (1+j-t) w_{q-1}[j]) / (q-1)``
    and ``B_q' = B_{q-1}(x) - B_{q-1}(x-1)``.
    """
    if order == 4:
        # closed form of the cubic case: the hot path of every query
        s = 1.0 - t
        t2 = t * t
        t3 = t2 * t
        out[0, 0] = s * s * s / 6.0
        out[0, 1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
        out[0, 2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
        out[0, 3] = t3 / 6.0
        if nderiv >= 1:
            out[1, 0] = -0.5 * s * s
            out[1, 1] = 1.5 * t2 - 2.0 * t
            out[1, 2] = -1.5 * t2 + t + 0.5
            out[1, 3] = 0.5 * t2
        if nderiv >= 2:
            out[2, 0] = s
            out[2, 1] = 3.0 * t - 2.0
            out[2, 2] = 1.0 - 3.0 * t
            out[2, 3] = t
        return
    work = np.zeros((order + 1, order + 1))
    work[1, 0] = 1.0
    for q in range(2, order + 1):
        for j in range(q):
            left = work[q - 1, j - 1] if j >= 1 else 0.0
            right = work[q - 1, j] if j <= q - 2 else 0.0
            work[q, j] = ((t + q - 1 - j) * left + (1 + j - t) * right) / (q - 1)
    for j in range(order):
        out[0, j] = work[order, j]
    if nderiv >= 1:
        q = order - 1
        for j in range(order):
            left = work[q, j - 1] if j >= 1 else 0.0
            right = work[q, j] if j <= q - 1 else 0.0
            out[1, j] = left - right
    if nderiv >= 2:
        q = order - 2
        for j in range(order):
            a = work[q, j - 2] if j >= 2 else 0.0
            b = work[q, j - 1] if (j >= 1 and j - 1 <= q - 1) else 0.0
            c = work[q, j] if j <= q - 1 else 0.0
            out[2, j] = a - 2.0 * b + c


@_jit
def _lower_bound(keys, value):
    lo = 0
    hi = keys.shape[0]
    while lo < hi:
        mid = (lo + hi) >> 1
        if keys[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo


@_jit
def cells_meet_sphere(cells, h, radius):
    """Whether each cell (M, 3) of spacing h meets the sphere |x| = radius.

    The box is convex and |x| continuous, so it meets the sphere exactly when the
    nearest point is inside or on it and the farthest outside or on it.
    """
    m = cells.shape[0]
    out = np.empty(m, dtype=np.bool_)
    r2 = radius * radius
    for s in range(m):
        near = 0.0
        far = 0.0
        for d in range(3):
            lo = cells[s, d] * h
            hi = lo + h
            if lo > 0.0:
                near += lo * lo
            elif hi < 0.0:
                near += hi * hi
            far += max(lo * lo, hi * hi)
        out[s] = near <= r2 <= far
    return out


@_jit
def normal_equations(points, values, h, order, keys):
    """Upper triangle of AᵀA (CSC) and Aᵀb for the B-splines ``keys`` at sites ``points``.

    Accumulates straight into a (len(keys), (2 order - 1)³) table indexed by the
    relative position of the second B-spline, so no sparse product or sort is needed;
    each site costs order⁶ multiply-adds. Returns (indptr, indices, data, rhs).
    """
    n = keys.shape[0]
    span = 2 * order - 1
    width = span * span * span
    table = np.zeros((n, width))
    rhs = np.zeros(n)
    inv_h = 1.0 / h
    block = order * order * order
    cols = np.empty(block, dtype=np.int64)
    vals = np.empty(block)
    loc = np.empty((block, 3), dtype=np.int64)
    wx = np.empty((3, order))
    wy = np.empty((3, order))
    wz = np.empty((3, order))
    for s in range(points.shape[0]):
        fx = points[s, 0] * inv_h
        fy = points[s, 1] * inv_h
        fz = points[s, 2] * inv_h
        ax = int(np.floor(fx))
        ay = int(np.floor(fy))
        az = int(np.floor(fz))
        bspline_weights(fx - ax, order, 0, wx)
        bspline_weights(fy - ay, order, 0, wy)
        bspline_weights(fz - az, order, 0, wz)
        found = 0
        k0 = az - order + 1
        for p in range(order):
            i = ax - order + 1 + p
            for q in range(order):
                j = ay - order + 1 + q
                base = _pack(i, j, k0)
                pos = _lower_bound(keys, base)
                while pos < n and keys[pos] < base + order:
                    r = keys[pos] - base
                    cols[found] = pos
                    vals[found] = wx[0, p] * wy[0, q] * wz[0, r]
                    loc[found, 0] = p
                    loc[found, 1] = q
                    loc[found, 2] = r
                    found += 1
                    pos += 1
        value = values[s]
        for e2 in range(found):
            c2 = cols[e2]
            v2 = vals[e2]
            rhs[c2] += v2 * value
            for e1 in range(found):
                if cols[e1] > c2:
                    continue
                off = ((loc[e1, 0] - loc[e2, 0] + order - 1) * span
                       + (loc[e1, 1] - loc[e2, 1] + order - 1)) * span + (loc[e1, 2] - loc[e2, 2] + order - 1)
                table[c2, off] += vals[e1] * v2
    # compress: column c2 holds rows c1 <= c2; offsets in lexicographic order are
    # increasing key deltas, hence increasing row positions
    count = 0
    for c in range(n):
        for off in range(width):
            if table[c, off] != 0.0:
                count += 1
    indptr = np.zeros(n + 1, dtype=np.int64)
    indices = np.empty(count, dtype=np.int64)
    data = np.empty(count)
    at = 0
    for c in range(n):
        for off in range(width):
            v = table[c, off]
            if v != 0.0:
                dr = off % span - (order - 1)
                dq = (off // span) % span - (order - 1)
                dp = off // (span * span) - (order - 1)
                target = keys[c] + (dp << (2 * KEY_BITS)) + (dq << KEY_BITS) + dr
                indices[at] = _lower_bound(keys, target)
                data[at] = v
                at += 1
        indptr[c + 1] = at
    return indptr, indices, data, rhs


# ---------------------------------------------------------------------------------
# brick index for fast queries
#
# A level's coefficients are regrouped by bricks of 2**BRICK_BITS cells a side. A brick
# lists, for each (i, j) column of B-splines touching its cells, the contiguous run of
# k values present (zeros fill gaps), so evaluating a point costs one hash probe for
# its brick per level and then direct array reads: no search over coefficients.

BRICK_BITS = 4
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)


@_jit
def _hash_slot(key, mask):
    h = np.uint64(key) * _HASH_MULT
    return np.int64((h >> np.uint64(32)) & np.uint64(mask))


@_jit
def build_hash(keys):
    """Open-addressing hash table (linear probing) from key to its position in keys."""
    capacity = 1
    while capacity < 2 * keys.shape[0] + 2:
        capacity *= 2
    mask = capacity - 1
    slot_keys = np.full(capacity, -1, dtype=np.int64)
    slot_vals = np.full(capacity, -1, dtype=np.int64)
    for pos in range(keys.shape[0]):
        s = _hash_slot(keys[pos], mask)
        while slot_keys[s] != -1:
            s = (s + 1) & mask
        slot_keys[s] = keys[pos]
        slot_vals[s] = pos
    return slot_keys, slot_vals


@_jit
def _hash_find(slot_keys, slot_vals, start, mask, key):
    s = _hash_slot(key, mask)
    while True:
        k = slot_keys[start + s]
        if k == key:
            return slot_vals[start + s]
        if k == -1:
            return -1
        s = (s + 1) & mask


PRESENCE_CELL = 0.125  # side of the coarse cells of the per-level presence map
PRESENCE_SIDE = 20  # covers [-1.25, 1.25) on each axis


@_jit
def _present(presence, lev, x, y, z):
    i = int(np.floor(x / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    j = int(np.floor(y / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    k = int(np.floor(z / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    if i < 0 or j < 0 or k < 0 or i >= PRESENCE_SIDE or j >= PRESENCE_SIDE or k >= PRESENCE_SIDE:
        return False
    return presence[lev, i, j, k] != 0


@_jit
def _eval_bricks_point(x, y, z, inv_h, order, nderiv, slot_keys, slot_vals, slot_start, slot_mask,
                       columns, values, wx, wy, wz, result):
    fx = x * inv_h
    fy = y * inv_h
    fz = z * inv_h
    ax = int(np.floor(fx))
    ay = int(np.floor(fy))
    az = int(np.floor(fz))
    bx = ax >> BRICK_BITS
    by = ay >> BRICK_BITS
    bz = az >> BRICK_BITS
    brick = _hash_find(slot_keys, slot_vals, slot_start, slot_mask, _pack(bx, by, bz))
    if brick < 0:
        return
    bspline_weights(fx - ax, order, nderiv, wx)
    bspline_weights(fy - ay, order, nderiv, wy)
    bspline_weights(fz - az, order, nderiv, wz)
    lx = ax - (bx << BRICK_BITS)
    ly = ay - (by << BRICK_BITS)
    k0 = az - order + 1
    ih2 = inv_h * inv_h
    for p in range(order):
        for q in range(order):
            packed = columns[brick, lx + p, ly + q]
            length = packed & 0xFFFF
            if length == 0:
                continue
            start = k0 - (((packed >> 16) & 0xFFFF) - 32768)
            offset = packed >> 32
            for r in range(order):
                t = start + r
                if t < 0 or t >= length:
                    continue
                c = values[offset + t]
                result[0] += c * wx[0, p] * wy[0, q] * wz[0, r]
                if nderiv >= 1:
                    result[1] += c * wx[1, p] * wy[0, q] * wz[0, r] * inv_h
                    result[2] += c * wx[0, p] * wy[1, q] * wz[0, r] * inv_h
                    result[3] += c * wx[0, p] * wy[0, q] * wz[1, r] * inv_h
                if nderiv >= 2:
                    result[4] += c * wx[2, p] * wy[0, q] * wz[0, r] * ih2
                    result[5] += c * wx[0, p] * wy[2, q] * wz[0, r] * ih2
                    result[6] += c * wx[0, p] * wy[0, q] * wz[2, r] * ih2
                    result[7] += c * wx[1, p] * wy[1, q] * wz[0, r] * ih2
                    result[8] += c * wx[1, p] * wy[0, q] * wz[1, r] * ih2
                    result[9] += c * wx[0, p] * wy[1, q] * wz[1, r] * ih2


@_pjit
def evaluate_bricks(points, inv_hs, order, nderiv, presence, slot_keys, slot_vals, slot_start, slot_mask,
                    columns, values, out):
    """Sum over all levels of the spline (and derivatives) at points (M, 3) into out.

    The tables of every level are stacked (see :class:`geoidspline.spline.BrickIndex`):
    level ``l`` probes ``slot_keys[slot_start[l]:slot_start[l] + slot_mask[l] + 1]``, only
    where its coarse presence map says it has bricks. ``columns`` packs a column's value
    offset (bits 32-63), first k + 32768 (16-31) and run length (0-15).
    ``out`` has 1 (value), 4 (+ gradient) or 10 (+ Hessian xx yy zz xy xz yz) columns.
    NaN points are skipped.
    """
    m = points.shape[0]
    width = out.shape[1]
    nlev = inv_hs.shape[0]
    # chunks, so the work arrays are allocated once per chunk and not per point
    chunk = 4096
    nchunks = (m + chunk - 1) // chunk
    for c in numba.prange(nchunks):
        wx = np.empty((3, order))
        wy = np.empty((3, order))
        wz = np.empty((3, order))
        result = np.empty(width)
        for s in range(c * chunk, min(m, (c + 1) * chunk)):
            x = points[s, 0]
            y = points[s, 1]
            z = points[s, 2]
            if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
                continue
            for r in range(width):
                result[r] = 0.0
            for lev in range(nlev):
                if _present(presence, lev, x, y, z):
                    _eval_bricks_point(x, y, z, inv_hs[lev], order, nderiv, slot_keys, slot_vals, slot_start[lev],
                                       slot_mask[lev], columns, values, wx, wy, wz, result)
            for r in range(width):
                out[s, r] += result[r]
