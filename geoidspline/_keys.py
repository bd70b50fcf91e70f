"""Packed coefficient keys: integer triples in one int64 (numpy only, no numba).

Coefficient indices are packed into one int64 key, 21 bits an axis, so that sorting keys
sorts by (i, j, k) and the ``n`` B-splines of one (i, j) column that touch a cell are
consecutive keys. That makes a sorted key array a compact sparse 3-D index. Kept apart
from :mod:`geoidspline._kernels` so that reading a store and small queries never import
numba (about a second in a cold process).
"""

from __future__ import annotations

import numpy as np

KEY_BITS = 21
KEY_OFFSET = 1 << (KEY_BITS - 1)
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
