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
# small helpers of the query loop, inlined into it at numba's IR level
_ijit = numba.njit(cache=True, nogil=True, fastmath=False, inline="always")


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
    nearest point is inside or on it and the farthest outside or on it. "On" has a
    relative slack of 1e-9: where the sphere touches a cell face (the poles and the four
    equator points on the axes, whenever 1/h is an integer) rounding of ``k h`` must not
    drop the outer cell (at h = 0.005, -201 h + h rounds below -1): level 0 then misses
    the B-splines outside the south pole, and an overlay fitting the residual at the
    outer sites there made a 70 mm error at the pole.
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
        out[s] = near <= r2 * (1.0 + 1e-9) and r2 * (1.0 - 1e-9) <= far
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
# Every level's coefficients are regrouped by bricks of 2**BRICK_BITS cells a side. A
# brick lists, for each (i, j) column of B-splines touching its cells, one contiguous
# run of k values (zeros fill gaps), so evaluating a point on a level costs one hash
# probe for its brick and then direct array reads: no search over coefficients.
#
# A brick has two tables (see :class:`geoidspline.spline.BrickIndex`): the level's own
# coefficients, and the *folded* coefficients: the sum of this level and all coarser
# ones rewritten on this level's grid by B-spline subdivision, stored only near the
# unit sphere (the level's band). A point inside the band of the finest level that
# has a brick at it is therefore evaluated on that one level only.

BRICK_BITS = 4
_HASH_MULT = np.uint64(0x9E3779B97F4A7C15)
# a column entry (int32): run offset from the brick's base << COL_SHIFT | first local
# k << COL_KBITS | run length; local k and lengths are < 2**COL_KBITS
COL_KBITS = 5
COL_SHIFT = 2 * COL_KBITS
_COL_KMASK = (1 << COL_KBITS) - 1


@_ijit
def _hash_slot(key, mask):
    h = np.uint64(key) * _HASH_MULT
    return np.int64((h >> np.uint64(32)) & np.uint64(mask))


@_jit
def build_hash(keys):
    """Open-addressing hash table (linear probing) from key to its position in keys.

    Returns (capacity, 2) int64 slots: (key, position), key -1 for an empty slot; a
    probe reads one 16-byte slot, so one cache line.
    """
    capacity = 1
    while capacity < 2 * keys.shape[0] + 2:
        capacity *= 2
    mask = capacity - 1
    slots = np.full((capacity, 2), -1, dtype=np.int64)
    for pos in range(keys.shape[0]):
        s = _hash_slot(keys[pos], mask)
        while slots[s, 0] != -1:
            s = (s + 1) & mask
        slots[s, 0] = keys[pos]
        slots[s, 1] = pos
    return slots


@_ijit
def _hash_find(slots, start, mask, key):
    s = _hash_slot(key, mask)
    while True:
        k = slots[start + s, 0]
        if k == key:
            return slots[start + s, 1]
        if k == -1:
            return -1
        s = (s + 1) & mask


PRESENCE_CELL = 0.125  # side of the coarse cells of the per-level presence map
PRESENCE_SIDE = 20  # covers [-1.25, 1.25) on each axis


@_ijit
def _present(presence, lev, x, y, z):
    """Whether level lev may have a brick at the point (False: it has none there).

    Outside the map's cube the answer is True: the hash probe decides.
    """
    i = int(np.floor(x / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    j = int(np.floor(y / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    k = int(np.floor(z / PRESENCE_CELL)) + PRESENCE_SIDE // 2
    if i < 0 or j < 0 or k < 0 or i >= PRESENCE_SIDE or j >= PRESENCE_SIDE or k >= PRESENCE_SIDE:
        return True
    return presence[lev, i, j, k] != 0


@_ijit
def _cubic_weights(t):
    """The four cubic B-spline weights of a point at t in [0, 1) of its cell."""
    s = 1.0 - t
    t2 = t * t
    t3 = t2 * t
    return s * s * s / 6.0, (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0, (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0, t3 / 6.0


@_ijit
def _pick4(w0, w1, w2, w3, i):
    if i == 0:
        return w0
    if i == 1:
        return w1
    if i == 2:
        return w2
    return w3


@_ijit
def _value_cubic(fx, fy, fz, ax, ay, az, base, cols, brick, values):
    """Value of one brick table of a cubic spline at a point: the hot path of queries.

    ``fx`` is x / h, ``ax`` its cell; ``cols[brick]`` are the brick's column entries,
    ``base`` its first value. Same sum as :func:`_eval_bricks_point`, with the weights
    in registers and a column's four coefficients read at once when its run holds them.
    """
    x0, x1, x2, x3 = _cubic_weights(fx - ax)
    y0, y1, y2, y3 = _cubic_weights(fy - ay)
    z0, z1, z2, z3 = _cubic_weights(fz - az)
    lx = ax & ((1 << BRICK_BITS) - 1)
    ly = ay & ((1 << BRICK_BITS) - 1)
    lz = az & ((1 << BRICK_BITS) - 1)
    acc = 0.0
    for p in range(4):
        wx = _pick4(x0, x1, x2, x3, p)
        for q in range(4):
            packed = cols[brick, lx + p, ly + q]
            length = packed & _COL_KMASK
            if length == 0:
                continue
            start = lz - ((packed >> COL_KBITS) & _COL_KMASK)
            offset = base + (packed >> COL_SHIFT) + start
            if start >= 0 and start + 4 <= length:
                col = values[offset] * z0 + values[offset + 1] * z1 + values[offset + 2] * z2 + values[offset + 3] * z3
            else:
                col = 0.0
                for r in range(4):
                    if 0 <= start + r < length:
                        col += values[offset + r] * _pick4(z0, z1, z2, z3, r)
            acc += wx * _pick4(y0, y1, y2, y3, q) * col
    return acc


@_jit
def _eval_bricks_point(fx, fy, fz, ax, ay, az, inv_h, order, nderiv, base, cols, brick, values, wx, wy, wz,
                       result):
    """Add one brick table's spline (and derivatives) at a point into result (any order).

    ``fx`` is x / h, ``ax`` its cell; ``cols[brick]`` are the brick's (side, side)
    column entries, ``base`` its first value.
    """
    bspline_weights(fx - ax, order, nderiv, wx)
    bspline_weights(fy - ay, order, nderiv, wy)
    bspline_weights(fz - az, order, nderiv, wz)
    lx = ax & ((1 << BRICK_BITS) - 1)
    ly = ay & ((1 << BRICK_BITS) - 1)
    lz = az & ((1 << BRICK_BITS) - 1)
    v = 0.0
    gx = 0.0
    gy = 0.0
    gz = 0.0
    hxx = 0.0
    hyy = 0.0
    hzz = 0.0
    hxy = 0.0
    hxz = 0.0
    hyz = 0.0
    for p in range(order):
        for q in range(order):
            packed = cols[brick, lx + p, ly + q]
            length = packed & _COL_KMASK
            if length == 0:
                continue
            start = lz - ((packed >> COL_KBITS) & _COL_KMASK)
            offset = base + (packed >> COL_SHIFT) + start
            # the column's sums against the z weights and their derivatives
            c0 = 0.0
            c1 = 0.0
            c2 = 0.0
            for r in range(order):
                if 0 <= start + r < length:
                    c = values[offset + r]
                    c0 += c * wz[0, r]
                    if nderiv >= 1:
                        c1 += c * wz[1, r]
                    if nderiv >= 2:
                        c2 += c * wz[2, r]
            v += wx[0, p] * wy[0, q] * c0
            if nderiv >= 1:
                gx += wx[1, p] * wy[0, q] * c0
                gy += wx[0, p] * wy[1, q] * c0
                gz += wx[0, p] * wy[0, q] * c1
            if nderiv >= 2:
                hxx += wx[2, p] * wy[0, q] * c0
                hyy += wx[0, p] * wy[2, q] * c0
                hzz += wx[0, p] * wy[0, q] * c2
                hxy += wx[1, p] * wy[1, q] * c0
                hxz += wx[1, p] * wy[0, q] * c1
                hyz += wx[0, p] * wy[1, q] * c1
    result[0] += v
    if nderiv >= 1:
        result[1] += gx * inv_h
        result[2] += gy * inv_h
        result[3] += gz * inv_h
    if nderiv >= 2:
        ih2 = inv_h * inv_h
        result[4] += hxx * ih2
        result[5] += hyy * ih2
        result[6] += hzz * ih2
        result[7] += hxy * ih2
        result[8] += hxz * ih2
        result[9] += hyz * ih2


@_ijit
def _find_brick(lev, x, y, z, inv_hs, presence, slots, slot_start, slot_mask):
    """The point's cell on level lev and the brick holding it (-1: none)."""
    if not _present(presence, lev, x, y, z):
        return -1, 0.0, 0.0, 0.0, 0, 0, 0
    inv_h = inv_hs[lev]
    fx = x * inv_h
    fy = y * inv_h
    fz = z * inv_h
    ax = int(np.floor(fx))
    ay = int(np.floor(fy))
    az = int(np.floor(fz))
    brick = _hash_find(slots, slot_start[lev], slot_mask[lev],
                       _pack(ax >> BRICK_BITS, ay >> BRICK_BITS, az >> BRICK_BITS))
    return brick, fx, fy, fz, ax, ay, az


@_pjit
def subdivide_bricks(parents, parent_of, half, weights, out):
    """Brick tables of a spline written on the grid of half the spacing (folding).

    ``parents`` (P, side, side, side) are brick tables on spacing 2h (table index c of
    brick b is B-spline ``b S - n + 1 + c``, S = 2**BRICK_BITS, n = order); child brick
    ``i`` lies in parent brick ``parent_of[i]``, in its half ``half[i]`` (0/1 per axis).
    ``out[i]`` (side³) receives the child's table on spacing h, by the refinement
    relation ``B(x) = Σ_m weights[m] B(2x - m)`` (weights = 2^-(n-1) binom(n, m)):
    child index c draws on parent index ``q = (c + n - 1 - m) / 2 + half S / 2``.
    The child's parents all lie in that parent brick. Axis by axis, so n + 1
    multiply-adds per output of each pass.
    """
    n = weights.shape[0] - 1
    cells = 1 << BRICK_BITS
    side = cells + n - 1
    width = cells // 2 + n - 1
    for i in numba.prange(out.shape[0]):
        p = parent_of[i]
        ox = half[i, 0] * (cells // 2)
        oy = half[i, 1] * (cells // 2)
        oz = half[i, 2] * (cells // 2)
        tx = np.zeros((side, width, width))
        for a in range(side):
            for m in range(n + 1):
                num = a + n - 1 - m
                if num < 0 or (num & 1) != 0 or (num >> 1) >= width:
                    continue
                q = ox + (num >> 1)
                wm = weights[m]
                for j in range(width):
                    for k in range(width):
                        tx[a, j, k] += wm * parents[p, q, oy + j, oz + k]
        ty = np.zeros((side, side, width))
        for a in range(side):
            for b in range(side):
                for m in range(n + 1):
                    num = b + n - 1 - m
                    if num < 0 or (num & 1) != 0 or (num >> 1) >= width:
                        continue
                    q = num >> 1
                    wm = weights[m]
                    for k in range(width):
                        ty[a, b, k] += wm * tx[a, q, k]
        for a in range(side):
            for b in range(side):
                for c in range(side):
                    acc = 0.0
                    for m in range(n + 1):
                        num = c + n - 1 - m
                        if num < 0 or (num & 1) != 0 or (num >> 1) >= width:
                            continue
                        acc += weights[m] * ty[a, b, num >> 1]
                    out[i, a, b, c] = acc


ORDER_BITS = 6  # points are visited bucket by bucket: 2**ORDER_BITS buckets an axis
_ORDER_LO = -1.25
_ORDER_SPAN = 2.5


@_ijit
def _spread3(v):
    """Insert two zero bits between each of the low 10 bits of v."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x30000FF
    v = (v | (v << 8)) & 0x300F00F
    v = (v | (v << 4)) & 0x30C30C3
    v = (v | (v << 2)) & 0x9249249
    return v


@_jit
def query_order(points):
    """A visiting order of points (M, 3) in which neighbours follow each other.

    Counting sort on the Z-order (Morton) index of a coarse cubic grid over
    [-1.25, 1.25)³ (2**ORDER_BITS cells an axis; points outside are clamped, NaN go
    last): O(M), stable, so the order depends on the points only.
    """
    m = points.shape[0]
    side = 1 << ORDER_BITS
    nbuckets = side * side * side
    scale = side / _ORDER_SPAN
    key = np.empty(m, dtype=np.int64)
    counts = np.zeros(nbuckets + 1, dtype=np.int64)
    for s in range(m):
        x = points[s, 0]
        y = points[s, 1]
        z = points[s, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            b = nbuckets
        else:
            i = min(max(int(np.floor((x - _ORDER_LO) * scale)), 0), side - 1)
            j = min(max(int(np.floor((y - _ORDER_LO) * scale)), 0), side - 1)
            k = min(max(int(np.floor((z - _ORDER_LO) * scale)), 0), side - 1)
            b = _spread3(i) | (_spread3(j) << 1) | (_spread3(k) << 2)
        key[s] = b
        counts[b] += 1
    total = 0
    for b in range(nbuckets + 1):
        c = counts[b]
        counts[b] = total
        total += c
    order = np.empty(m, dtype=np.int64)
    for s in range(m):
        b = key[s]
        order[counts[b]] = s
        counts[b] += 1
    return order


@_pjit
def evaluate_bricks(points, inv_hs, band_lo2, band_hi2, order, nderiv, presence, slots, slot_start, slot_mask,
                    fold_base, fold_cols, own_base, own_cols, values, out):
    """The spline (and derivatives) at points (M, 3), added into out.

    Levels are stacked coarse to fine (see :class:`geoidspline.spline.BrickIndex`):
    level ``l`` probes ``slots[slot_start[l]:slot_start[l] + slot_mask[l] + 1]``, only
    where its coarse presence map says it has bricks. Per point, from the finest level
    down, the first level with a brick at the point whose band holds the point
    (``band_lo2[l] <= |x|² <= band_hi2[l]``) is evaluated from its folded table (which
    includes every coarser level) and the loop stops; a level with a brick there but
    outside its band adds its own table and the loop goes on. A level without a brick
    at the point has no B-spline touching its cell there, so it adds nothing.
    ``fold_cols``/``own_cols`` (bricks, side, side) int32 pack a column's run offset
    from ``fold_base``/``own_base`` (bits COL_SHIFT-31), its first local k and length.
    ``out`` has 1 (value), 4 (+ gradient) or 10 (+ Hessian xx yy zz xy xz yz) columns.
    NaN points are skipped. Visit many points in :func:`query_order` (neighbours share
    bricks and cache lines): a reordered copy of the points is faster than visiting
    them in place through an index (measured 79 against 240 ns a point).
    """
    m = points.shape[0]
    width = out.shape[1]
    nlev = inv_hs.shape[0]
    fast = order == 4 and nderiv == 0
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
            r2 = x * x + y * y + z * z
            if fast:
                acc = 0.0
                for lev in range(nlev - 1, -1, -1):
                    brick, fx, fy, fz, ax, ay, az = _find_brick(lev, x, y, z, inv_hs, presence, slots,
                                                                slot_start, slot_mask)
                    if brick < 0:
                        continue
                    if band_lo2[lev] <= r2 <= band_hi2[lev]:
                        acc += _value_cubic(fx, fy, fz, ax, ay, az, fold_base[brick], fold_cols, brick, values)
                        break
                    acc += _value_cubic(fx, fy, fz, ax, ay, az, own_base[brick], own_cols, brick, values)
                out[s, 0] += acc
                continue
            for r in range(width):
                result[r] = 0.0
            for lev in range(nlev - 1, -1, -1):
                brick, fx, fy, fz, ax, ay, az = _find_brick(lev, x, y, z, inv_hs, presence, slots, slot_start,
                                                            slot_mask)
                if brick < 0:
                    continue
                if band_lo2[lev] <= r2 <= band_hi2[lev]:
                    _eval_bricks_point(fx, fy, fz, ax, ay, az, inv_hs[lev], order, nderiv, fold_base[brick],
                                       fold_cols, brick, values, wx, wy, wz, result)
                    break
                _eval_bricks_point(fx, fy, fz, ax, ay, az, inv_hs[lev], order, nderiv, own_base[brick], own_cols,
                                   brick, values, wx, wy, wz, result)
            for r in range(width):
                out[s, r] += result[r]


@_pjit
def unit_vectors(latitude, longitude, out):
    """Directions (cos φ cos λ, cos φ sin λ, sin φ) of latitude/longitude in degrees."""
    d2r = np.pi / 180.0
    for s in numba.prange(latitude.shape[0]):
        phi = latitude[s] * d2r
        lam = longitude[s] * d2r
        cos_phi = np.cos(phi)
        out[s, 0] = cos_phi * np.cos(lam)
        out[s, 1] = cos_phi * np.sin(lam)
        out[s, 2] = np.sin(phi)
