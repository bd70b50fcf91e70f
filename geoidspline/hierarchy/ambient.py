"""The ambient spline: the sum of a hierarchy of levels, S = Σ_ℓ S_ℓ (thesis §5.2).

The reference manifold is the unit sphere. A geodetic position (latitude φ, longitude λ,
degrees) maps to the direction ``u = (cos φ cos λ, cos φ sin λ, sin φ)``; the geoid
undulation N(φ, λ) is approximated by ``S(u)``, ``S`` a trivariate spline on R³ that was
fitted to the radially constant extension of N (Lehmann 2013, ch. 3, 5.2).
"""

from __future__ import annotations

import numpy as np

from ..bspline.evaluate import evaluate_levels
from ..sphere.coordinates import COMPILED_FROM_POINTS, check_coordinates, directions
from ..sphere.region import MAX_ABS_POINT_LONGITUDE_DEG

#: Batches from this size on use the compiled, folded index (:class:`~geoidspline.bspline.index.BrickIndex`).
FOLDED_FROM_POINTS = COMPILED_FROM_POINTS


class AmbientSpline:
    """The sum of hierarchical overlay levels: S = Σ_ℓ S_ℓ (thesis §5.2).

    Two evaluators, chosen by the batch size alone (so a result never depends on what
    was evaluated before):

    - fewer than :data:`FOLDED_FROM_POINTS` points: pure numpy, level by level
      (:func:`geoidspline.bspline.evaluate.evaluate_levels`); nothing to build, the compiled
      kernels are not loaded, so a one-point query in a fresh process stays fast;
    - from :data:`FOLDED_FROM_POINTS` points on: the compiled folded index
      (:class:`BrickIndex`, one level per point near the sphere), built on first use.

    The two agree to rounding (1e-12 m on values; tested to 1e-9 m for values,
    gradients and Hessians). Evaluation is thread-safe: the levels are immutable and
    the kernels only read them; two threads may both build the index the first time,
    and build identical ones.
    """

    def __init__(self, levels, value_step=None, quantise=False):
        levels = list(levels)
        orders = {lv.order for lv in levels}
        if len(orders) > 1:
            raise ValueError(f"all levels must share one spline order, got {sorted(orders)}")
        self.levels = tuple(levels)
        self.order = orders.pop() if orders else 4
        #: metres: the coefficients are multiples of it (a store's, as read), so the index
        #: may hold them as integers (:class:`BrickIndex`); None if not known
        self.value_step = value_step
        #: the index holds the integers of ``value_step`` whatever its size (a part of a
        #: store whose whole index would: the same bits, the whole's bytes a coefficient)
        self.quantise = quantise
        self._folded = None

    @property
    def index(self):
        """The folded query index (built on first use)."""
        if self._folded is None:
            from ..bspline.index import BrickIndex  # loads the compiled kernels: large batches only

            self._folded = BrickIndex(self.levels, self.order, value_step=self.value_step,
                                      quantise=self.quantise)
        return self._folded

    @property
    def coefficient_count(self) -> int:
        return sum(len(lv) for lv in self.levels)

    def evaluate_points(self, points, nderiv=0, any_batch=False, ordered=False):
        """Values (M,) or value+derivatives (M, 4|10) at ambient points (M, 3).

        Small batches are summed level by level, large ones by the folded index: the two
        agree to rounding. ``any_batch``: the folded index whatever the batch's size, so
        that a point's value has the same bits in any batch (a fit made band by band
        evaluates fewer sites at once than the whole globe's). ``ordered``: the points
        are in :func:`~geoidspline._kernels.query.query_order`'s order already (with
        ``any_batch``: the same values, bit for bit, without sorting them again)."""
        points = np.ascontiguousarray(points, dtype=np.float64).reshape(-1, 3)
        if points.shape[0] < FOLDED_FROM_POINTS and not any_batch:
            out = evaluate_levels(self.levels, points, nderiv)
        else:
            width = {0: 1, 1: 4, 2: 10}[nderiv]
            out = np.zeros((points.shape[0], width))
            self.index.add_to(points, out, nderiv, ordered=ordered)  # orders many points itself
            bad = ~np.all(np.isfinite(points), axis=1)
            out[bad] = np.nan
        return out[:, 0] if nderiv == 0 else out

    def undulation(self, latitude, longitude):
        """The restriction to the sphere at latitude/longitude in degrees (metres).

        Arrays broadcast, NaN gives NaN, a latitude beyond ±90° raises
        :class:`CoordinateError`. Large batches take one compiled call
        (:meth:`BrickIndex.undulation_latlon`), bitwise equal to evaluating
        :func:`directions` with :meth:`evaluate_points`.
        """
        lat, lon = np.broadcast_arrays(np.asarray(latitude, dtype=np.float64),
                                       np.asarray(longitude, dtype=np.float64))
        shape = lat.shape
        if lat.size >= FOLDED_FROM_POINTS:
            # the kernel counts what check_coordinates refuses (in its pass over the
            # coordinates: no serial numpy pass here)
            values, invalid = self.index.undulation_latlon(np.ascontiguousarray(lat).ravel(),
                                                           np.ascontiguousarray(lon).ravel(),
                                                           MAX_ABS_POINT_LONGITUDE_DEG)
            if invalid:
                check_coordinates(lat, lon)  # raises, naming the first bad value
            return values.reshape(shape)
        lat, lon = check_coordinates(lat, lon)
        values = self.evaluate_points(directions(lat.ravel(), lon.ravel()))
        values = values.reshape(shape)
        return values[()] if shape == () else values
