"""The domain Ω of a level (thesis §3.2): the grid cells that meet the unit sphere.

Stability without special bases comes from working on whole cells only: a level's
B-splines are those touching an active cell, and its sites lie in active cells.
"""

from __future__ import annotations

import math

import numpy as np

from .._kernels.fitting import cells_meet_sphere
from ..sphere.coordinates import directions, latlon_of
from ..sphere.region import Region
from .keys import dilate_keys, pack_keys, unpack_keys


def _sphere_samples(region: Region, spacing_rad: float):
    """Directions covering ``region`` with neighbours closer than ``spacing_rad``."""
    dlat = math.degrees(spacing_rad)
    lats = np.arange(region.south, region.north + dlat, dlat)
    lats = np.clip(lats, -90.0, 90.0)
    out = []
    for lat in lats:
        dlon = dlat / max(math.cos(math.radians(lat)), 1e-3)
        n = max(2, int(math.ceil(region.longitude_span / dlon)) + 1)
        lons = np.linspace(region.west, region.east, n)
        out.append(directions(np.full(n, lat), lons))
    return np.concatenate(out)


def active_cells(h: float, region: Region):
    """Integer indices (M, 3) of the cells of spacing h that meet the sphere over region.

    Exact for the sphere test; for the region a conservative superset (a cell counts
    when its centre direction is within the cell's angular radius of the region).
    """
    samples = _sphere_samples(region, 0.5 * h)
    keys = np.unique(pack_keys(np.floor(samples / h).astype(np.int64)))
    # every cell meeting the sphere is next to a cell holding a sample closer than h
    cells = unpack_keys(dilate_keys(keys, -1, 1))
    cells = cells[cells_meet_sphere(cells, h, 1.0)]
    if not region.is_global:
        lat, lon = latlon_of((cells + 0.5) * h)
        margin = math.degrees(math.sqrt(3.0) * h / max(1.0 - math.sqrt(3.0) * h, 0.1))
        cells = cells[region.expanded(margin).contains(lat, lon)]
    return cells


def supports_inside(keys, h: float, order: int, region: Region):
    """Boolean mask of the B-splines (packed ``keys`` of spacing ``h``) whose support on
    the unit sphere lies inside ``region``: outside it they are exactly 0.

    Conservative: the support of key k is the cube [k h, (k + order) h]³; its points on
    the sphere lie within latitudes asin(z) over the cube's z range and within the
    longitudes the cube's (x, y) rectangle subtends from the axis (all of them when the
    rectangle touches the axis). A B-spline counts as inside when that latitude and
    longitude box lies inside the region.
    """
    lo = unpack_keys(np.asarray(keys, dtype=np.int64)).astype(float) * h
    hi = lo + order * h
    inside = (np.degrees(np.arcsin(np.clip(lo[:, 2], -1.0, 1.0))) >= region.south) & (
        np.degrees(np.arcsin(np.clip(hi[:, 2], -1.0, 1.0))) <= region.north)
    if region.longitude_span >= 360.0:
        return inside
    x = np.stack([lo[:, 0], lo[:, 0], hi[:, 0], hi[:, 0]], axis=1)
    y = np.stack([lo[:, 1], hi[:, 1], lo[:, 1], hi[:, 1]], axis=1)
    # the rectangle subtends less than 180° unless it touches the axis; measure its
    # corners' longitudes from its centre's so that the span never wraps
    centre = np.arctan2(0.5 * (lo[:, 1] + hi[:, 1]), 0.5 * (lo[:, 0] + hi[:, 0]))
    offset = (np.arctan2(y, x) - centre[:, None] + np.pi) % (2 * np.pi) - np.pi
    west = np.degrees(centre + offset.min(axis=1))
    width = np.degrees(offset.max(axis=1) - offset.min(axis=1))
    touches_axis = (lo[:, 0] <= 0.0) & (hi[:, 0] >= 0.0) & (lo[:, 1] <= 0.0) & (hi[:, 1] >= 0.0)
    start = (west - region.west) % 360.0
    return inside & ~touches_axis & (start + width <= region.longitude_span)
