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
def _eval_point(x, y, z, inv_h, order, nderiv, keys, coefs, wx, wy, wz, result):
    """Value (result[0]), gradient (1..3) and Hessian (4..9: xx yy zz xy xz yz)."""
    fx = x * inv_h
    fy = y * inv_h
    fz = z * inv_h
    ax = int(np.floor(fx))
    ay = int(np.floor(fy))
    az = int(np.floor(fz))
    bspline_weights(fx - ax, order, nderiv, wx)
    bspline_weights(fy - ay, order, nderiv, wy)
    bspline_weights(fz - az, order, nderiv, wz)
    for r in range(result.shape[0]):
        result[r] = 0.0
    n = keys.shape[0]
    k0 = az - order + 1
    for p in range(order):
        i = ax - order + 1 + p
        for q in range(order):
            j = ay - order + 1 + q
            base = _pack(i, j, k0)
            pos = _lower_bound(keys, base)
            while pos < n and keys[pos] < base + order:
                r = keys[pos] - base
                c = coefs[pos]
                result[0] += c * wx[0, p] * wy[0, q] * wz[0, r]
                if nderiv >= 1:
                    result[1] += c * wx[1, p] * wy[0, q] * wz[0, r]
                    result[2] += c * wx[0, p] * wy[1, q] * wz[0, r]
                    result[3] += c * wx[0, p] * wy[0, q] * wz[1, r]
                if nderiv >= 2:
                    result[4] += c * wx[2, p] * wy[0, q] * wz[0, r]
                    result[5] += c * wx[0, p] * wy[2, q] * wz[0, r]
                    result[6] += c * wx[0, p] * wy[0, q] * wz[2, r]
                    result[7] += c * wx[1, p] * wy[1, q] * wz[0, r]
                    result[8] += c * wx[1, p] * wy[0, q] * wz[1, r]
                    result[9] += c * wx[0, p] * wy[1, q] * wz[1, r]
                pos += 1
    # chain rule: derivatives were taken with respect to x/h
    if nderiv >= 1:
        for r in range(1, 4):
            result[r] *= inv_h
    if nderiv >= 2:
        for r in range(4, 10):
            result[r] *= inv_h * inv_h


@_pjit
def evaluate_level(points, h, order, nderiv, keys, coefs, out):
    """Add one level's spline (and derivatives) at ambient ``points`` (M, 3) to ``out``.

    ``out`` has shape (M, 1), (M, 4) or (M, 10) for nderiv 0, 1, 2 (see _eval_point).
    Points with a NaN coordinate are skipped (the caller keeps NaN there).
    """
    inv_h = 1.0 / h
    m = points.shape[0]
    width = out.shape[1]
    for s in numba.prange(m):
        x = points[s, 0]
        y = points[s, 1]
        z = points[s, 2]
        if not (np.isfinite(x) and np.isfinite(y) and np.isfinite(z)):
            continue
        wx = np.empty((3, order))
        wy = np.empty((3, order))
        wz = np.empty((3, order))
        result = np.empty(width)
        _eval_point(x, y, z, inv_h, order, nderiv, keys, coefs, wx, wy, wz, result)
        for r in range(width):
            out[s, r] += result[r]


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
