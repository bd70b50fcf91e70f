"""Ambient B-spline objects: one sparse level, and the sum of hierarchical overlays.

The reference manifold is the unit sphere. A geodetic position (latitude φ, longitude λ,
degrees) maps to the direction ``u = (cos φ cos λ, cos φ sin λ, sin φ)``; the geoid
undulation N(φ, λ) is approximated by ``S(u)``, ``S`` a trivariate spline on R³ that was
fitted to the radially constant extension of N (Lehmann 2013, ch. 3, 5.2).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import _kernels
from .errors import CoordinateError

__all__ = ["LevelSpline", "AmbientSpline", "BrickIndex", "directions", "check_coordinates", "tile_of_indices"]


def check_coordinates(latitude, longitude):
    """Broadcast latitude/longitude (degrees) to float arrays and check their range.

    NaN is allowed (it yields NaN); a finite latitude outside [-90, 90] or an infinite
    value is a :class:`CoordinateError`. Longitudes are any finite value (wrapped).
    """
    latitude, longitude = np.broadcast_arrays(
        np.asarray(latitude, dtype=float), np.asarray(longitude, dtype=float)
    )
    with np.errstate(invalid="ignore"):
        bad_lat = np.abs(latitude) > 90.0
    if np.any(bad_lat):
        first = latitude[bad_lat].ravel()[0]
        raise CoordinateError(
            f"latitude must be within [-90, 90] degrees; got {first!r} "
            f"({int(np.count_nonzero(bad_lat))} value(s) out of range)"
        )
    if np.any(np.isinf(longitude)):
        raise CoordinateError("longitude must be finite (degrees)")
    return latitude, longitude


def directions(latitude, longitude):
    """Unit vectors (..., 3) for latitude/longitude in degrees (no range check)."""
    phi = np.radians(latitude)
    lam = np.radians(longitude)
    cos_phi = np.cos(phi)
    return np.stack([cos_phi * np.cos(lam), cos_phi * np.sin(lam), np.sin(phi)], axis=-1)


def tile_of_indices(indices, h, order, tile_size):
    """Tile (integer triple) of each coefficient: the cube holding its support centre."""
    centre = (np.asarray(indices, dtype=float) + order / 2.0) * h
    return np.floor(centre / tile_size).astype(np.int64)


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
        keys = _kernels.pack_keys(indices)
        order_idx = np.argsort(keys, kind="stable")
        return cls(level, h, order, keys[order_idx], np.asarray(coefficients, float)[order_idx])

    @property
    def indices(self) -> np.ndarray:
        return _kernels.unpack_keys(self.keys)

    def __len__(self):
        return int(self.keys.size)


class BrickIndex:
    """The query structure of a spline: every level's coefficients regrouped by bricks.

    A brick is a cube of ``2**BRICK_BITS`` cells of its level; for each (i, j) column of
    B-splines touching its cells it stores the run of k present, contiguous in one value
    array. A point then costs one hash probe per level and direct reads of its
    ``order³`` coefficients. Coefficients near brick faces are stored in up to 8 bricks;
    the memory cost is about 25 bytes per coefficient (values, duplicates and tables),
    measured by :attr:`nbytes`. Immutable once built; evaluation is thread-safe.
    """

    def __init__(self, levels, order):
        bits = _kernels.BRICK_BITS
        side = (1 << bits) + order - 1
        slot_keys, slot_vals, slot_start, slot_mask = [], [], [], []
        offsets, kmins, lengths, values, presence = [], [], [], [], []
        inv_hs = []
        brick_base = 0
        value_base = 0
        slot_base = 0
        for lv in levels:
            if len(lv) == 0:
                continue
            idx = lv.indices
            low = idx >> bits
            high = (idx + order - 1) >> bits
            pair_coef, pair_brick = [], []
            for combo in range(8):
                use_high = np.array([(combo >> d) & 1 for d in range(3)], dtype=bool)
                valid = np.all(~use_high | (high != low), axis=1)
                brick = np.where(use_high, high, low)[valid]
                pair_coef.append(np.flatnonzero(valid))
                pair_brick.append(brick)
            coef = np.concatenate(pair_coef)
            brick = np.concatenate(pair_brick)
            brick_keys, brick_id = np.unique(_kernels.pack_keys(brick), return_inverse=True)
            local = idx[coef, :2] - (brick[:, :2] << bits) + (order - 1)
            kz = idx[coef, 2]
            order_idx = np.lexsort((kz, local[:, 1], local[:, 0], brick_id))
            coef, brick_id, local, kz = coef[order_idx], brick_id[order_idx], local[order_idx], kz[order_idx]
            column = (brick_id * side + local[:, 0]) * side + local[:, 1]
            starts = np.flatnonzero(np.r_[True, column[1:] != column[:-1]])
            stops = np.r_[starts[1:], column.size]
            kmin = kz[starts]
            length = kz[stops - 1] - kmin + 1
            col_start = np.r_[0, np.cumsum(length)[:-1]] + value_base
            nb = brick_keys.size
            col_offset = np.zeros((nb, side, side), dtype=np.int64)
            col_kmin = np.zeros((nb, side, side), dtype=np.int64)
            col_len = np.zeros((nb, side, side), dtype=np.int64)
            cid = column[starts]
            if np.abs(kmin).max() >= 32000 or length.max() >= 0xFFFF:
                raise ValueError(f"level {lv.level}: indices beyond the query tables' 16-bit range")
            col_offset.reshape(-1)[cid] = col_start
            col_kmin.reshape(-1)[cid] = kmin
            col_len.reshape(-1)[cid] = length
            presence.append(self._presence(brick_keys, lv.h))
            vals = np.zeros(int(length.sum()))
            run = np.repeat(np.arange(starts.size), stops - starts)
            vals[col_start[run] - value_base + (kz - kmin[run])] = lv.coefficients[coef]
            keys_table, vals_table = _kernels.build_hash(brick_keys)
            slot_keys.append(keys_table)
            slot_vals.append(np.where(vals_table >= 0, vals_table + brick_base, -1))
            slot_start.append(slot_base)
            slot_mask.append(keys_table.size - 1)
            offsets.append(col_offset)
            kmins.append(col_kmin)
            lengths.append(col_len)
            values.append(vals)
            inv_hs.append(1.0 / lv.h)
            brick_base += nb
            value_base += vals.size
            slot_base += keys_table.size
        self.order = order
        self.inv_hs = np.array(inv_hs, dtype=np.float64)
        cat = lambda parts, dtype, shape: np.concatenate(parts) if parts else np.zeros(shape, dtype)  # noqa: E731
        self.slot_keys = cat(slot_keys, np.int64, 1)
        self.slot_vals = cat(slot_vals, np.int64, 1)
        self.slot_start = np.array(slot_start, dtype=np.int64)
        self.slot_mask = np.array(slot_mask, dtype=np.int64)
        # one int64 per column (offset, first k, length) so a column costs one read
        offset = cat(offsets, np.int64, (0, side, side))
        kmin = cat(kmins, np.int64, (0, side, side))
        length = cat(lengths, np.int64, (0, side, side))
        self.columns = (offset << 32) | ((kmin + 32768) << 16) | length
        self.values = cat(values, np.float64, 0)
        n = _kernels.PRESENCE_SIDE
        self.presence = np.stack(presence) if presence else np.zeros((0, n, n, n), np.uint8)

    @staticmethod
    def _presence(brick_keys, h):
        """Coarse cells (side PRESENCE_CELL) that some brick of the level overlaps."""
        n = _kernels.PRESENCE_SIDE
        cell = _kernels.PRESENCE_CELL
        span = (1 << _kernels.BRICK_BITS) * h
        lo = _kernels.unpack_keys(brick_keys) * span
        first = np.floor(lo / cell).astype(np.int64) + n // 2
        last = np.floor((lo + span) / cell).astype(np.int64) + n // 2
        grid = np.zeros((n, n, n), np.uint8)
        for a, b in zip(np.clip(first, 0, n - 1), np.clip(last, 0, n - 1)):
            grid[a[0]:b[0] + 1, a[1]:b[1] + 1, a[2]:b[2] + 1] = 1
        return grid

    @property
    def nbytes(self) -> int:
        return sum(a.nbytes for a in (self.slot_keys, self.slot_vals, self.columns, self.values, self.presence))

    def add_to(self, points, out, nderiv=0):
        if self.inv_hs.size:
            _kernels.evaluate_bricks(points, self.inv_hs, self.order, nderiv, self.presence, self.slot_keys,
                                     self.slot_vals, self.slot_start, self.slot_mask, self.columns,
                                     self.values, out)


_SORT_THRESHOLD = 100_000


def _spread_bits(v):
    """Insert two zero bits between each of the low 10 bits of v (int64 array)."""
    v = v & 0x3FF
    v = (v | (v << 16)) & 0x30000FF
    v = (v | (v << 8)) & 0x300F00F
    v = (v | (v << 4)) & 0x30C30C3
    v = (v | (v << 2)) & 0x9249249
    return v


def _morton_keys(points):
    """Z-order keys of points in [-1.25, 1.25)³ on a 1024³ lattice (NaN points last)."""
    cells = np.floor((np.nan_to_num(points, nan=1.25) + 1.25) * (1024 / 2.5)).astype(np.int64)
    cells = np.clip(cells, 0, 1023)
    return _spread_bits(cells[:, 0]) | (_spread_bits(cells[:, 1]) << 1) | (_spread_bits(cells[:, 2]) << 2)


class AmbientSpline:
    """The sum of hierarchical overlay levels: S = Σ_ℓ S_ℓ (thesis §5.2).

    Evaluation is thread-safe: the object is immutable after construction and the
    kernels only read it.
    """

    def __init__(self, levels):
        levels = list(levels)
        orders = {lv.order for lv in levels}
        if len(orders) > 1:
            raise ValueError(f"all levels must share one spline order, got {sorted(orders)}")
        self.levels = tuple(levels)
        self.order = orders.pop() if orders else 4
        self.index = BrickIndex(self.levels, self.order)

    @property
    def coefficient_count(self) -> int:
        return sum(len(lv) for lv in self.levels)

    def evaluate_points(self, points, nderiv=0):
        """Values (M,) or value+derivatives (M, 4|10) at ambient points (M, 3)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        width = {0: 1, 1: 4, 2: 10}[nderiv]
        out = np.zeros((points.shape[0], width))
        if points.shape[0] >= _SORT_THRESHOLD:
            # visit the points in Morton order: neighbours share bricks and cache lines
            order = np.argsort(_morton_keys(points), kind="stable")
            sorted_out = np.zeros_like(out)
            self.index.add_to(np.ascontiguousarray(points[order]), sorted_out, nderiv)
            out[order] = sorted_out
        else:
            self.index.add_to(points, out, nderiv)
        bad = ~np.all(np.isfinite(points), axis=1)
        out[bad] = np.nan
        return out[:, 0] if nderiv == 0 else out

    def undulation(self, latitude, longitude):
        """The restriction to the sphere at latitude/longitude in degrees (metres)."""
        latitude, longitude = check_coordinates(latitude, longitude)
        shape = latitude.shape
        values = self.evaluate_points(directions(latitude.ravel(), longitude.ravel()))
        values = values.reshape(shape)
        return values[()] if shape == () else values
