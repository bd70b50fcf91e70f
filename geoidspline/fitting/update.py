"""The regional update, a strategy of the fit: new data inside a region, a spline's own values outside it.

An update fits one more set of overlays, Δ, to the residual

    r(u) = w(u) · (N_new(u) − S_old(u)),

w = 1 inside the region, falling to 0 with a cosine taper over ``blend_width_km``
outside it. Where the new source has no data but the store has (a national grid's
sea), N_new − S_old is that of the nearest node with new data, faded out with the same
taper over the blend width (:func:`fade_into_no_data`): the coast is no step, and
beyond the blend width the store keeps its values. Δ only takes B-splines whose whole
support lies inside the blend zone (the region grown by the blend width), so outside
the zone Δ is exactly 0 and the store keeps its old values there (to the rounding of
summing its levels); the result S_old + Δ is one spline on R³ (C² everywhere, no step
at the region's edge) and only the tiles owning Δ's B-splines are rewritten: every
other tile file stays byte-identical. The blend zone must lie inside the source's
extent: beyond it there is no new data to fade from, and a B-spline reaching there
would be unconstrained. This module fits Δ (:func:`fit_update`); writing it is the store's
(:mod:`geoidspline.store.update`), and :func:`geoidspline.api.update` composes the two.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from ..bspline.domain import supports_inside
from ..bspline.level import add_levels
from ..errors import FitError
from ..geodesy.ellipsoids import KM_PER_DEGREE
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.overlays import OverlayRefinement
from ..sphere.coverage import Coverage
from ..sphere.region import Region
from ..sphere.sample import NodeSample
from .driver import clip_to_extent, finer_data_hint, fit_nodes
from .parameters import FitParameters, finest_level
from .result import FitResult

__all__ = ["fit_update", "RegionalUpdate", "blend_weight", "fade_into_no_data"]

#: Node spacings of the new source a blend zone should span: Δ falls from the new
#: values to 0 within it on B-splines the data determine.
BLEND_NODE_SPACINGS = 4


def _step(axis) -> float:
    """Largest spacing (degrees) of a sample axis (0 for a single node)."""
    return float(np.max(np.diff(axis))) if len(axis) > 1 else 0.0


def blend_weight(region: Region, blend_deg: float, latitude, longitude):
    """1 inside ``region``, a cosine taper to 0 over ``blend_deg`` degrees of arc outside."""
    latitude = np.asarray(latitude, float)
    longitude = np.asarray(longitude, float)
    dlat = np.maximum.reduce([region.south - latitude, latitude - region.north, np.zeros_like(latitude)])
    if region.longitude_span >= 360.0:
        dlon = np.zeros_like(longitude)
    else:
        offset = (longitude - region.west) % 360.0
        beyond = offset - region.longitude_span
        dlon = np.where(beyond <= 0.0, 0.0, np.minimum(beyond, 360.0 - offset))
    distance = np.hypot(dlat, dlon * np.cos(np.radians(latitude)))
    if blend_deg <= 0.0:
        return (distance <= 0.0).astype(float)
    return _cosine_taper(distance / blend_deg)


def _cosine_taper(ratio):
    """1 at ratio 0 falling to 0 at ratio 1 (and beyond) as ½(1 + cos πr): flat at both
    ends, so a blend adds no kink."""
    ratio = np.minimum(np.asarray(ratio, dtype=float), 1.0)
    return np.where(ratio >= 1.0, 0.0, 0.5 * (1.0 + np.cos(np.pi * ratio)))


class _ResidualRefinement(OverlayRefinement):
    """Overlays from level 0 on, restricted to B-splines whose support lies inside the
    blend zone: Δ is then 0 outside the zone whatever the data there (a B-spline reaching
    past the zone would be constrained only on one side of it, and free to change the
    store hundreds of km away)."""

    def __init__(self, refine_radius, zone: Region):
        super().__init__(refine_radius)
        self.zone = zone

    def level_keys(self, level, h, order, region, violating_directions):
        keys, marked, _ = super().level_keys(max(level, 1), h, order, region, violating_directions)
        if keys.size:
            keys = keys[supports_inside(keys, h, order, self.zone)]
        return keys, marked, None


def fade_into_no_data(difference, latitude, longitude, blend_width_km: float):
    """At each node of a latitude/longitude lattice without data (NaN in ``difference``),
    the difference at the nearest node with data times a cosine taper from 1 there to 0
    at ``blend_width_km`` (0 beyond, and everywhere for a width of 0 or no data at all).

    Distances are measured on the lattice with the spacing of its middle latitude (a
    taper, so a few per cent of distance do not matter); nodes with data get 0.
    """
    from scipy.ndimage import distance_transform_edt

    difference = np.asarray(difference, dtype=float)
    has_data = np.isfinite(difference)
    faded = np.zeros(difference.shape)
    if blend_width_km <= 0.0 or has_data.all() or not has_data.any() or difference.ndim != 2:
        return faded
    dlat, dlon = _step(latitude) or 1.0, _step(longitude) or 1.0
    mid = math.radians(0.5 * (float(latitude[0]) + float(latitude[-1])))
    sampling = (dlat * KM_PER_DEGREE, dlon * KM_PER_DEGREE * max(math.cos(mid), 1e-3))
    distance, (rows, cols) = distance_transform_edt(~has_data, sampling=sampling, return_indices=True)
    faded[~has_data] = (_cosine_taper(distance / blend_width_km) * difference[rows, cols])[~has_data]
    return faded


@dataclass
class RegionalUpdate:
    """A fitted regional update: Δ, the spline it gives and the data it was fitted to.

    ``node_*``: the source's nodes inside the region that have data (degrees, metres),
    where the result is measured; ``coverage``: the old coverage joined with the
    source's; ``node_spacing_km``: the source's largest node spacing."""

    delta: FitResult
    merged: AmbientSpline
    parameters: FitParameters
    coverage: Coverage
    node_latitude: np.ndarray
    node_longitude: np.ndarray
    node_undulation: np.ndarray
    node_spacing_km: float
    blend_width_km: float
    #: what the update's check measured before fitting (the caller's ``check``), and what
    #: was converted or taken in the source (said in the update's record)
    plausibility: dict | None = None
    source_notes: tuple = ()

    def hint(self, source_name: str) -> str | None:
        """Why the tolerance may not have been reached: a blend zone too narrow for the
        source's nodes (None when it is wide enough)."""
        if self.blend_width_km < BLEND_NODE_SPACINGS * self.node_spacing_km:
            return (f"the blend width ({self.blend_width_km:g} km) spans fewer than {BLEND_NODE_SPACINGS} node "
                    f"spacings of {source_name} ({self.node_spacing_km:.3g} km): the update cannot fall "
                    f"to the store's values within it; widen the blend or use a finer source")
        return None


def fit_update(old: AmbientSpline, old_coverage: Coverage, source, region: Region, blend_width_km: float,
               params: FitParameters, executor=None, progress=None, check=None) -> RegionalUpdate:
    """Fit Δ to w·(N_new − S_old) over the blend zone of ``region`` with ``params`` (the
    stored spline's own, its tolerance possibly this update's) and merge it into ``old``.

    ``check(latitude, longitude, new, old)``, when given, sees the source's nodes over the
    blend zone and the store's values there (NaN where it has no coverage) before
    anything is fitted, and may raise (the plausibility of the update); what it returns
    is kept as the update's ``plausibility``."""
    # Levels finer than the store's, down to what the new data determines (the driver
    # stops at MIN_H_PER_DATA_SPACING): Δ must fall to 0 inside the blend zone, and a
    # national grid is usually much finer than the global source the store was fitted to.
    params = dataclasses.replace(params, max_level=finest_level(params.h0))
    blend_deg = blend_width_km / KM_PER_DEGREE
    zone = region.expanded(blend_deg) if blend_deg > 0 else region

    # Δ's B-splines lie inside the zone (_ResidualRefinement): the zone's nodes are all the data
    sample = source.nodes(clip_to_extent(zone, source), spacing_deg=params.sample_spacing_deg)
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    old_values = old.undulation(lat2, lon2)  # the spline, covered or not
    plausibility = None
    if check is not None:
        covered = np.asarray(old_coverage.covers(lat2, lon2), dtype=bool)
        plausibility = check(sample.latitude, sample.longitude, sample.undulation,
                             np.where(covered, old_values, np.nan))
    weight = blend_weight(region, blend_deg, lat2, lon2)
    has_new = np.isfinite(sample.undulation)
    difference = np.where(has_new, sample.undulation - old_values, np.nan)
    # no new data where the store has its own (a national grid's sea): the change fades
    # out from the nearest new data over the blend width, as at the region's edge, so the
    # coast is no step; farther out the store keeps its values (residual 0)
    keep_old = ~has_new & np.asarray(old_coverage.covers(lat2, lon2))
    faded = fade_into_no_data(difference, sample.latitude, sample.longitude, blend_width_km)
    residual = weight * np.where(has_new, difference, np.where(keep_old, faded, np.nan))
    try:
        new_coverage = Coverage.from_sample(sample, region, source.provenance.source)
    except ValueError as exc:
        raise FitError(str(exc)) from None
    delta = fit_nodes(NodeSample(sample.latitude, sample.longitude, residual), zone, params,
                      refinement=_ResidualRefinement(params.refine_radius, zone), progress=progress, executor=executor,
                      base_is_overlay=True, finer_hint=finer_data_hint(source))
    inside = region.contains(lat2, lon2) & has_new
    return RegionalUpdate(
        delta=delta, merged=_merge(old, delta.spline), parameters=params, coverage=old_coverage.union(new_coverage),
        node_latitude=lat2[inside], node_longitude=lon2[inside], node_undulation=sample.undulation[inside],
        node_spacing_km=KM_PER_DEGREE * max(_step(sample.latitude), _step(sample.longitude)),
        blend_width_km=blend_width_km, plausibility=plausibility)


def _merge(old: AmbientSpline, delta: AmbientSpline) -> AmbientSpline:
    """old + delta as one set of levels (the union of keys, coefficients added)."""
    by_level = {lv.level: lv for lv in old.levels}
    for lv in delta.levels:
        by_level[lv.level] = add_levels(by_level[lv.level], lv) if lv.level in by_level else lv
    return AmbientSpline([by_level[k] for k in sorted(by_level)])
