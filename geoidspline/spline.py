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

__all__ = ["LevelSpline", "AmbientSpline", "directions", "check_coordinates"]


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

    def add_to(self, points, out, nderiv=0):
        """Add this level's values (and derivatives) at ambient points (M, 3) to ``out``."""
        if self.keys.size:
            _kernels.evaluate_level(points, self.h, self.order, nderiv, self.keys, self.coefficients, out)


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

    @property
    def coefficient_count(self) -> int:
        return sum(len(lv) for lv in self.levels)

    def evaluate_points(self, points, nderiv=0, max_level=None):
        """Values (M,) or value+derivatives (M, 4|10) at ambient points (M, 3)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        width = {0: 1, 1: 4, 2: 10}[nderiv]
        out = np.zeros((points.shape[0], width))
        for lv in self.levels:
            if max_level is not None and lv.level > max_level:
                continue
            lv.add_to(points, out, nderiv)
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
