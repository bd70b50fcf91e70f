"""The cardinal B-spline basis: weights at points, the two-scale relation, centred samples.

Numpy only. B-spline ``k`` of order ``n`` on a grid of spacing ``h`` is
``Π_d B_n(x_d / h - k_d)``, ``B_n`` the cardinal B-spline on ``[0, n)`` (METHOD.md §1);
a point in cell ``a`` at ``t = x/h - a`` is touched by ``k = a - n + 1 .. a``. The
compiled kernels (:mod:`geoidspline._kernels`) specialise these same formulas.
"""

from __future__ import annotations

import math

import numpy as np

from .keys import cube_offsets, pack_keys, unpack_keys


def bspline_weights(t, order, nderiv):
    """Weights (nderiv + 1, M, order) of the B-splines touching points at t in [0, 1).

    ``w[d, :, j]`` is the d-th derivative (with respect to x / h) of
    ``B_order(t + order - 1 - j)``, the weight of B-spline ``k = a - order + 1 + j`` for
    a point in cell ``a``: the same convention as :func:`geoidspline._kernels.common.bspline_weights`.
    Uniform-knot de Boor recursion ``w_q[j] = ((t + q - 1 - j) w_{q-1}[j-1] +
    (1 + j - t) w_{q-1}[j]) / (q - 1)`` and ``B_q' = B_{q-1}(x) - B_{q-1}(x - 1)``.
    """
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros((nderiv + 1, t.size, order))
    if order == 4:
        # closed form of the cubic case, the one every store uses
        s = 1.0 - t
        t2 = t * t
        t3 = t2 * t
        out[0, :, 0] = s * s * s / 6.0
        out[0, :, 1] = (3.0 * t3 - 6.0 * t2 + 4.0) / 6.0
        out[0, :, 2] = (-3.0 * t3 + 3.0 * t2 + 3.0 * t + 1.0) / 6.0
        out[0, :, 3] = t3 / 6.0
        if nderiv >= 1:
            out[1, :, 0] = -0.5 * s * s
            out[1, :, 1] = 1.5 * t2 - 2.0 * t
            out[1, :, 2] = -1.5 * t2 + t + 0.5
            out[1, :, 3] = 0.5 * t2
        if nderiv >= 2:
            out[2, :, 0] = s
            out[2, :, 1] = 3.0 * t - 2.0
            out[2, :, 2] = 1.0 - 3.0 * t
            out[2, :, 3] = t
        return out
    # work[q][:, j] = B_q(t + q - 1 - j), j = 0 .. q - 1 (zero outside)
    work = [None, np.ones((t.size, 1))]
    for q in range(2, order + 1):
        prev = work[q - 1]
        cur = np.zeros((t.size, q))
        for j in range(q):
            if j >= 1:
                cur[:, j] += (t + q - 1 - j) * prev[:, j - 1]
            if j <= q - 2:
                cur[:, j] += (1 + j - t) * prev[:, j]
        work.append(cur / (q - 1))
    out[0] = work[order]

    def lower(q, j):
        return work[q][:, j] if 0 <= j <= q - 1 else 0.0

    if nderiv >= 1:
        for j in range(order):
            out[1, :, j] = lower(order - 1, j - 1) - lower(order - 1, j)
    if nderiv >= 2:
        for j in range(order):
            out[2, :, j] = lower(order - 2, j - 2) - 2.0 * lower(order - 2, j - 1) + lower(order - 2, j)
    return out


def refinement_weights(order):
    """``2^-(n-1) binom(n, m)``, m = 0..n: the refinement relation of the cardinal B-spline
    of order n, ``B(x) = Σ_m w_m B(2x - m)``; coarse coefficient ``j`` adds ``w_m`` times
    itself to fine coefficient ``2j + m`` (per axis; cubic: (1, 4, 6, 4, 1) / 8)."""
    return np.array([math.comb(order, m) for m in range(order + 1)], dtype=float) / 2.0 ** (order - 1)


def children(keys, order: int):
    """The refinement relation of the 3-D B-splines ``keys`` (packed, one level):
    ``B^ℓ_k = Σ_m w[m_x] w[m_y] w[m_z] B^{ℓ+1}_{2k+m}``, m in {0..n}³, w the
    :func:`refinement_weights` (thesis §5.3, Figure 5.1; METHOD.md §3).

    Returns ``(child_keys, parent, weight)``, each of length ``len(keys) * (n+1)³``:
    ``B^ℓ_{keys[parent[i]]} = Σ_i weight[i] B^{ℓ+1}_{child_keys[i]}`` (children of one
    parent consecutive; not deduplicated across parents). The hierarchical basis
    (:mod:`geoidspline.hierarchy.hierarchical`) builds its ``up`` operator and its
    cross-level normal equations from it; the query index folds coarse levels with the
    same weights.
    """
    keys = np.asarray(keys, dtype=np.int64)
    offsets = cube_offsets(0, order)
    w = refinement_weights(order)
    weight = w[offsets[:, 0]] * w[offsets[:, 1]] * w[offsets[:, 2]]
    child = pack_keys(2 * unpack_keys(keys)[:, None, :] + offsets[None, :, :]).ravel()
    parent = np.repeat(np.arange(keys.size), offsets.shape[0])
    return child, parent, np.tile(weight, keys.size)


def centred_bspline_samples(order: int) -> np.ndarray:
    """Values of the order-``order`` cardinal B-spline at integer offsets from its centre.

    Symmetric, summing to 1: ``[1, 4, 1] / 6`` for cubics, ``[1, 6, 1] / 8`` for quadratics.
    The centre is a knot for even orders (the weights at t = 0, whose last is B(0) = 0)
    and a cell centre for odd ones (t = 1/2).
    """
    weights = bspline_weights(np.array([0.0 if order % 2 == 0 else 0.5]), order, 0)[0, 0]
    return weights[:-1] if order % 2 == 0 else weights
