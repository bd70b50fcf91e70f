"""Hierarchical overlays (thesis §5.2): which B-splines each level adds.

Level 0 takes every B-spline touching the domain Ω over the region; level ℓ + 1 takes
the B-splines near the data nodes where the sum of the levels so far violates the
tolerance. Each level is fitted to the residual of the levels before it
(:mod:`geoidspline.fitting`).
"""

from __future__ import annotations

import numpy as np

from ..bspline.domain import active_cells
from ..bspline.keys import keys_centred_near, pack_keys, touching_keys


class OverlayRefinement:
    """Hierarchical overlays (thesis §5.2): each level fits the residual of the ones
    before it on the B-splines touching the cells where the tolerance is violated."""

    name = "overlay"

    def __init__(self, refine_radius=None):
        self.refine_radius = refine_radius

    def level_keys(self, level, h, order, region, violating_directions):
        """Coefficient keys of a level, the number of cells marked, and the keys of the
        cells sites may lie in (``None``: wherever a level B-spline is non-zero)."""
        if level == 0:
            # The domain Ω is the active cells over the region; sites stay inside it so
            # that every site sees all of its B-splines and constants are reproduced.
            cells = active_cells(h, region)
            if cells.size == 0:
                return np.empty(0, dtype=np.int64), 0, None
            return touching_keys(cells, order), len(cells), np.unique(pack_keys(cells))
        if violating_directions.size == 0:
            return np.empty(0, dtype=np.int64), 0, None
        position = violating_directions / h
        cells = np.floor(position).astype(np.int64)
        n_cells = np.unique(pack_keys(cells)).size
        radius = order / 2.0 if self.refine_radius is None else self.refine_radius
        if radius >= order / 2.0:
            return touching_keys(cells, order), n_cells, None
        return keys_centred_near(position, order, radius), n_cells, None
