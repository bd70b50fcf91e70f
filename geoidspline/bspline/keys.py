"""Packed coefficient keys: integer triples in one int64, and set operations on them.

Coefficient indices are packed into one int64 key, 21 bits an axis, so that sorting keys
sorts by (i, j, k) and the ``n`` B-splines of one (i, j) column that touch a cell are
consecutive keys. That makes a sorted key array a compact sparse 3-D index. Packing is
linear in each index, so an offset along an axis adds ``offset * AXIS_STEPS[axis]`` to a
key. numpy only: small queries never load the query kernels.
"""

from __future__ import annotations

import numpy as np

from .._kernels.layout import KEY_BITS, KEY_OFFSET  # noqa: F401 (the layout the kernels share)

KEY_MASK = (1 << KEY_BITS) - 1


MAX_INDEX = KEY_OFFSET - 16  # room for the n-1 neighbours of the outermost cell


def pack_keys(index):
    """Pack integer triples (..., 3) into int64 keys (no range check)."""
    index = np.asarray(index, dtype=np.int64) + KEY_OFFSET
    return (index[..., 0] << (2 * KEY_BITS)) | (index[..., 1] << KEY_BITS) | index[..., 2]


def unpack_keys(keys):
    """Inverse of :func:`pack_keys`: int64 keys to integer triples (..., 3)."""
    keys = np.asarray(keys, dtype=np.int64)
    out = np.empty(keys.shape + (3,), dtype=np.int64)
    out[..., 0] = (keys >> (2 * KEY_BITS)) & KEY_MASK
    out[..., 1] = (keys >> KEY_BITS) & KEY_MASK
    out[..., 2] = keys & KEY_MASK
    return out - KEY_OFFSET


#: Key increment of a unit step along each axis (i, j, k).
AXIS_STEPS = (1 << (2 * KEY_BITS), 1 << KEY_BITS, 1)


def cube_offsets(lo, hi):
    r = np.arange(lo, hi + 1)
    return np.array(np.meshgrid(r, r, r, indexing="ij")).reshape(3, -1).T


def _runs(keys):
    """(first, last) keys of the runs of consecutive integers in sorted unique ``keys``."""
    if keys.size == 0:
        return keys, keys
    breaks = np.flatnonzero(keys[1:] != keys[:-1] + 1) + 1
    return keys[np.r_[0, breaks]], keys[np.r_[breaks - 1, keys.size - 1]]


def _keys_of_runs(first, last):
    """Sorted keys of disjoint runs ``first..last`` (sorted, not touching)."""
    lengths = last - first + 1
    total = int(lengths.sum())
    # each key is its run's first key plus its position in the run
    offsets = np.repeat(first - (np.cumsum(lengths) - lengths), lengths)
    return offsets + np.arange(total, dtype=np.int64)


def dilate_axis(keys, step, lo, hi):
    """Sorted unique ``key + t * step`` for every key of ``keys`` (sorted, unique) and t
    in ``lo..hi``: the keys dilated along the axis of key increment ``step``
    (:data:`AXIS_STEPS`).

    The keys go as runs of consecutive keys (a column's stretch along the last axis), so
    the work is the runs' count times the shifts, not the keys' (about 20x fewer on a
    shell): every run is shifted, the shifted runs sorted and merged where they overlap
    or touch, and the keys written out once.
    """
    keys = np.asarray(keys, dtype=np.int64)
    first, last = _runs(keys)
    if first.size == 0:
        return keys
    if step == 1:  # runs stay in order: widen, then merge the ones that now touch
        first, last = first + lo, last + hi
    else:
        shifts = np.arange(lo, hi + 1, dtype=np.int64) * step
        first = (shifts[:, None] + first[None, :]).ravel()
        last = (shifts[:, None] + last[None, :]).ravel()
        order = np.argsort(first, kind="stable")
        first, last = first[order], last[order]
        last = np.maximum.accumulate(last)
    new = np.r_[True, first[1:] > last[:-1] + 1]
    group_last = np.r_[np.flatnonzero(new)[1:] - 1, first.size - 1]
    return _keys_of_runs(first[new], last[group_last])


def dilate_keys(keys, lo, hi):
    """Sorted unique keys of ``key + o`` for every offset o in [lo, hi]³.

    Packing is linear in each index, so offsets add to the keys; dilating one axis at
    a time keeps the intermediate arrays no larger than the result, not its cube.
    """
    keys = np.unique(keys)
    for step in AXIS_STEPS:
        keys = dilate_axis(keys, step, lo, hi)
    return keys


def touching_keys(cells, order):
    """Sorted keys of every B-spline non-zero on at least one of ``cells`` (M, 3)."""
    return touching_cell_keys(pack_keys(cells), order)


def touching_cell_keys(cell_keys, order):
    """:func:`touching_keys` of cells given as packed keys."""
    return dilate_keys(cell_keys, -(order - 1), 0)


def keys_centred_near(position, order, radius=None, chunk=200_000):
    """Sorted keys of the B-splines touching the cells of ``position`` (M, 3, in cells of
    their level) whose support centre ``k + order/2`` is within ``radius`` cells of it
    per axis (``None``: every B-spline touching the point). How overlays pick a level's
    B-splines and how the hierarchical basis marks B-splines for refinement."""
    position = np.asarray(position, dtype=float).reshape(-1, 3)
    offsets = np.arange(-(order - 1), 1)
    stencil = cube_offsets(-(order - 1), 0)
    found = [np.empty(0, np.int64)]
    for a in range(0, position.shape[0], chunk):
        pos = position[a:a + chunk]
        cell = np.floor(pos).astype(np.int64)
        if radius is None:
            found.append(np.unique(pack_keys((cell[:, None, :] + stencil[None]).reshape(-1, 3))))
            continue
        # the test is per axis: an (M, order, 3) mask, not the order³ candidates of every
        # point in floats (about 0.45 GB a chunk of 100,000 points for cubics)
        near = np.abs(cell[:, None, :] + offsets[None, :, None] + order / 2.0 - pos[:, None, :]) <= radius
        point, i, j, k = np.nonzero(near[:, :, None, None, 0] & near[:, None, :, None, 1] & near[:, None, None, :, 2])
        found.append(np.unique(pack_keys(cell[point] + np.stack([offsets[i], offsets[j], offsets[k]], axis=1))))
    return np.unique(np.concatenate(found))


def covered_cell_keys(coef_keys, order):
    """Sorted keys of the cells on which at least one B-spline of ``coef_keys`` lives."""
    return dilate_keys(coef_keys, 0, order - 1)


def isin_sorted(values, sorted_keys):
    pos = np.searchsorted(sorted_keys, values)
    pos = np.minimum(pos, sorted_keys.size - 1)
    return sorted_keys[pos] == values if sorted_keys.size else np.zeros(values.shape, bool)
