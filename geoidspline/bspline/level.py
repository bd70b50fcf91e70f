"""One level of an ambient spline: sparse B-spline coefficients on one grid spacing."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import keys as _keys


def cube_of_support_centres(indices, h, order, cube_size):
    """The cube (integer triple) of side ``cube_size`` holding each B-spline's support
    centre ``(k + order/2) h``: how storage tiles and least-squares blocks group
    coefficients (a storage *tile* and a solve *block* are both such cubes, of
    different sizes)."""
    centre = (np.asarray(indices, dtype=float) + order / 2.0) * h
    return np.floor(centre / cube_size).astype(np.int64)


def tiles_of_directions(dirs, tile_size):
    """The storage tile of each point ``dirs`` (M, 3), as packed keys of the cube of
    side ``tile_size`` holding it: the tile whose statistics a data node or check point
    counts in (coefficients go by :func:`cube_of_support_centres`)."""
    return _keys.pack_keys(np.floor(np.asarray(dirs) / tile_size).astype(np.int64))


@dataclass(frozen=True, eq=False)
class LevelSpline:
    """One level of an ambient spline: sparse B-spline coefficients on spacing ``h``.

    ``keys`` are packed coefficient indices (see :mod:`geoidspline._kernels`), strictly
    increasing; ``coefficients`` are in metres. The invariants are checked once here.
    """

    level: int
    h: float
    order: int
    keys: np.ndarray
    coefficients: np.ndarray

    def __post_init__(self):
        keys = np.ascontiguousarray(self.keys, dtype=np.int64)
        coefs = np.ascontiguousarray(self.coefficients, dtype=np.float64)
        if keys.ndim != 1 or keys.shape != coefs.shape:
            raise ValueError("keys and coefficients must be 1-D arrays of the same length")
        if keys.size > 1 and not np.all(keys[1:] > keys[:-1]):
            raise ValueError("keys must be strictly increasing")
        if not (self.h > 0 and np.isfinite(self.h)):
            raise ValueError(f"h must be positive, got {self.h}")
        if not 2 <= self.order <= 8:
            raise ValueError(f"spline order must be within 2..8, got {self.order}")
        if not np.all(np.isfinite(coefs)):
            raise ValueError("coefficients must be finite")
        object.__setattr__(self, "keys", keys)
        object.__setattr__(self, "coefficients", coefs)

    @classmethod
    def from_indices(cls, level, h, order, indices, coefficients):
        """Build from integer index triples (M, 3), in any order."""
        keys = _keys.pack_keys(indices)
        order_idx = np.argsort(keys, kind="stable")
        return cls(level, h, order, keys[order_idx], np.asarray(coefficients, float)[order_idx])

    @property
    def indices(self) -> np.ndarray:
        return _keys.unpack_keys(self.keys)

    def __len__(self):
        return int(self.keys.size)


def add_levels(first: LevelSpline, second: LevelSpline) -> LevelSpline:
    """The sum of two splines of the same level (spacing and order) as one: the union of
    their keys, coefficients added."""
    if (first.level, first.h, first.order) != (second.level, second.h, second.order):
        raise ValueError(f"cannot add level {second.level} (h={second.h}, order {second.order}) to level "
                         f"{first.level} (h={first.h}, order {first.order})")
    keys = np.union1d(first.keys, second.keys)
    values = np.zeros(keys.size)
    values[np.searchsorted(keys, first.keys)] += first.coefficients
    values[np.searchsorted(keys, second.keys)] += second.coefficients
    return LevelSpline(first.level, first.h, first.order, keys, values)
