"""A regional update of a store: the fit's update strategy inside the store's update transaction.

:func:`update_store` checks the source against the store, fits Δ with the store's own
parameters (:func:`geoidspline.fitting.update.fit_update`) and writes it
(:func:`geoidspline.store.update.update_transaction`).
"""

from __future__ import annotations

import dataclasses
import math
from typing import TYPE_CHECKING

from ..errors import CoordinateError, FitError, StoreCorruptError, StoreError
from ..fitting.executors import Executor
from ..fitting.parameters import RADIAL_OFFSETS, FitParameters
from ..fitting.update import fit_update
from ..geodesy.ellipsoids import KM_PER_DEGREE
from ..options import check_number
from ..sources.plausibility import MAX_CHANGE_M, MAX_SLOPE, check_update
from ..sources.reference import Target, conform
from ..sphere.region import Region
from ..store.format import MANIFEST
from ..store.update import update_transaction

if TYPE_CHECKING:  # annotations only
    from ..store.reader import TileStore

__all__ = ["update_store"]


def _shrunk(extent: Region, margin_deg: float) -> Region | None:
    """The largest region whose ``margin_deg`` zone (:meth:`Region.expanded`) fits in ``extent``."""
    south, north = extent.south + margin_deg, extent.north - margin_deg
    if extent.south <= -90.0:
        south = -90.0
    if extent.north >= 90.0:
        north = 90.0
    if south >= north:
        return None
    if extent.longitude_span >= 360.0:
        return Region(south, extent.west, north, extent.east)
    widest = max(abs(extent.south), abs(extent.north))  # where Region.expanded measures its margin
    if widest >= 89.0:
        return None  # the zone would take every longitude
    lon_margin = margin_deg / math.cos(math.radians(widest))
    if extent.longitude_span <= 2 * lon_margin:
        return None
    # rounded inwards to 4 decimals, so that the region offered is accepted as printed
    s, w = math.ceil(south * 1e4) / 1e4, math.ceil((extent.west + lon_margin) * 1e4) / 1e4
    n, e = math.floor(north * 1e4) / 1e4, math.floor((extent.east - lon_margin) * 1e4) / 1e4
    return Region(s, w, n, e) if s < n and w < e else None


def _check_compatible(store: TileStore, source, region: Region, blend_width_km: float):
    blend_deg = blend_width_km / KM_PER_DEGREE
    new = source.provenance
    extent = source.extent
    if not region.within(extent):
        raise CoordinateError(
            f"update region {region.bounds_text()} is not inside the extent of {new.source} ({extent.bounds_text()})"
        )
    zone = region.expanded(blend_deg) if blend_deg > 0 else region
    if not zone.within(extent):
        inner = _shrunk(extent, blend_deg)
        hint = (f"give a region at least {blend_width_km:g} km inside it (the largest is "
                f"{inner.bounds_text()}) or a smaller --blend-width"
                if inner is not None else "give a smaller --blend-width")
        raise CoordinateError(
            f"update region {region.bounds_text()} with its {blend_width_km:g} km blend zone reaches beyond the "
            f"extent of {new.source} ({extent.bounds_text()}): there is no new data there to blend from; {hint}"
        )
    store_region = Region(*store.manifest["region"])
    if not store_region.is_global:
        centre_lat = 0.5 * (region.south + region.north)
        centre_lon = region.west + 0.5 * region.longitude_span
        if not store_region.contains(centre_lat, centre_lon):
            raise CoordinateError(f"update region {region.as_tuple()} lies outside the store's region "
                                  f"{store_region.as_tuple()}")


def _older(version: str, than: str) -> bool:
    """Whether a release number (``major.minor.patch``) precedes ``than``."""
    def key(text):
        return tuple(int(part) if part.isdigit() else 0 for part in text.split(".")[:3])
    return key(version) < key(than)


def _stored_parameters(store: TileStore) -> FitParameters:
    """The store's own fit parameters (an update refits with them)."""
    known = {f.name for f in dataclasses.fields(FitParameters)}
    stored = {k: v for k, v in store.manifest["fit"]["parameters"].items() if k in known}
    try:
        if "radial_offsets" in stored:
            stored["radial_offsets"] = tuple(stored["radial_offsets"])
            software = str(store.manifest.get("software", "")).split()
            if (stored.get("refinement") == "hierarchical" and len(software) == 2 and _older(software[1], "0.3.0")
                    and stored["radial_offsets"] == RADIAL_OFFSETS["overlays"]):
                # before 0.3.0 a hierarchical fit recorded the overlays' offsets but
                # used its own (on the sphere): refit as it was fitted
                stored["radial_offsets"] = RADIAL_OFFSETS["hierarchical"]
        return FitParameters(**stored)
    except (TypeError, ValueError, FitError) as exc:
        raise StoreCorruptError(f"{store.path / MANIFEST}: manifest key 'fit.parameters' does not hold the "
                                f"store's fit parameters ({exc})") from None


def update_store(path, source, region: Region, blend_width_km: float = 100.0, executor: Executor | None = None,
                 tolerance_m: float | None = None, progress=None, wait_seconds: float = 0.0, sign=None, *,
                 accept_datum: bool = False, accept_quasi_geoid: bool = False,
                 max_change_m: float | None = MAX_CHANGE_M, max_slope: float | None = MAX_SLOPE) -> dict:
    """Replace the store's geoid inside ``region`` by ``source``; return the update report.

    Refused before anything is written when the store is read-only or locked by another
    writer, when the source's datum, quantity or tide system differs from the store's and
    no well-defined conversion exists (:func:`~geoidspline.sources.reference.conform`:
    tide systems and datums PROJ transforms well are converted, and the record's
    ``source_notes`` say so; ``accept_datum``/``accept_quasi_geoid`` take the values as
    they are), when the source is implausible against the store
    (:func:`~geoidspline.sources.plausibility.check_update`: a change beyond
    ``max_change_m`` or a slope beyond ``max_slope``; None skips), or when the region
    lies outside the source's extent or the store's region. The manifest is
    read once the writer lock is held, so concurrent updates apply one after the other
    (a second one started meanwhile waits up to ``wait_seconds`` for the first, then is
    refused; it is never lost).

    Coverage: the store answers where it did before and, inside ``region``, wherever
    ``source`` has data; where the source has no data (a national grid's sea, say) the
    store keeps its own values (the residual fitted there is 0) and its coverage.
    ``tolerance_m`` (metres), when given, is this update's tolerance instead of the
    store's. The update may add levels finer than the store's, as far as the new
    source's node spacing determines them. ``sign``: an Ed25519 private key that signs
    the new version (:func:`geoidspline.store.update.update_transaction`).
    """
    # the user's numbers by the rules every entry point shares (geoidspline.options)
    blend_width_km = check_number("blend_width_km", blend_width_km)
    tolerance_m = check_number("tolerance_m", tolerance_m, rule="update_tolerance_m")
    wait_seconds = check_number("wait_seconds", wait_seconds)
    with update_transaction(path, blend_width_km, wait_seconds, sign=sign) as transaction:
        store = transaction.store
        source, notes = conform(source, Target.of_store(store.manifest, store.path), accept_datum=accept_datum,
                                accept_quasi_geoid=accept_quasi_geoid)
        _check_compatible(store, source, region, blend_width_km)
        params = _stored_parameters(store)
        if tolerance_m is not None:  # this update's tolerance
            params = dataclasses.replace(params, tolerance_m=float(tolerance_m))

        def plausible(latitude, longitude, new, old):  # before anything is fitted or written
            return check_update(source.provenance.source, latitude, longitude, new, old, max_change_m=max_change_m,
                                max_slope=max_slope)

        fitted = fit_update(store.spline.full, store.coverage, source, region, blend_width_km, params,
                            executor=executor, progress=progress, check=plausible)
        fitted = dataclasses.replace(fitted, source_notes=tuple(notes))
        record = transaction.write(fitted, source, region, blend_width_km)
    return record
