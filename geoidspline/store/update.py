"""Regional updates: new data inside a region, the store's own values outside it.

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
would be unconstrained. The new tiles and manifest are committed the same atomic way as a fresh store (:mod:`geoidspline.store.writer`); the previous
version's tile files are kept for readers that opened it, until the next write.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import os
from pathlib import Path

import numpy as np

from ..bspline.domain import supports_inside
from ..bspline.keys import unpack_keys
from ..bspline.level import add_levels
from ..errors import CoordinateError, FitError, StoreCorruptError, StoreError
from ..fitting.driver import clip_to_extent, finer_data_hint, fit_nodes
from ..fitting.executors import Executor
from ..fitting.parameters import FitParameters, finest_level
from ..geodesy.ellipsoids import KM_PER_DEGREE
from ..options import check_number
from ..hierarchy.ambient import AmbientSpline
from ..hierarchy.overlays import OverlayRefinement
from ..sources.base import NodeSample
from ..sphere.coordinates import directions
from ..sphere.coverage import Coverage
from ..sphere.region import Region
from .codec import node_safe_step
from .coverage import coverage_record
from .format import FORMAT_VERSION, MANIFEST, TILE_DIR, error_stats, load_manifest, utc_now
from .reader import TileStore
from .signing import key_fingerprint, load_private_key, signature_name
from .writer import (
    StoreLock,
    _Attempt,
    _manifest_state,
    commit,
    crash_point,
    group_by_tile,
    quantisation_meta,
    tile_encoding,
    tile_groups,
    tile_stats,
    write_tile_entry,
)

__all__ = ["update_store", "blend_weight", "fade_into_no_data"]

log = logging.getLogger("geoidspline.store")


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
    old = store.manifest["provenance"]
    new = source.provenance
    if new.ellipsoid and old.get("ellipsoid") and new.ellipsoid != old["ellipsoid"]:
        raise StoreError(
            f"{store.path}: the store is on {old['ellipsoid']}, the source {new.source} on {new.ellipsoid}; "
            "refit the source on the store's ellipsoid first"
        )
    if new.tide_system and old.get("tide_system") and new.tide_system != old["tide_system"]:
        raise StoreError(
            f"{store.path}: the store is {old['tide_system']}, the source {new.source} is {new.tide_system}; "
            "convert the source to the store's tide system first"
        )
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


def _stored_parameters(store: TileStore) -> FitParameters:
    """The store's own fit parameters (an update refits with them)."""
    known = {f.name for f in dataclasses.fields(FitParameters)}
    stored = {k: v for k, v in store.manifest["fit"]["parameters"].items() if k in known}
    try:
        if "radial_offsets" in stored:
            stored["radial_offsets"] = tuple(stored["radial_offsets"])
        return FitParameters(**stored)
    except (TypeError, ValueError, FitError) as exc:
        raise StoreCorruptError(f"{store.path / MANIFEST}: manifest key 'fit.parameters' does not hold the "
                                f"store's fit parameters ({exc})") from None


def _check_writable(root: Path):
    if not (os.access(root, os.W_OK) and os.access(root / TILE_DIR, os.W_OK)):
        try:
            read_only_fs = bool(os.statvfs(root).f_flag & os.ST_RDONLY)
        except OSError:
            read_only_fs = False
        cause = "read-only file system" if read_only_fs else "no permission to write it"
        raise StoreError(f"{root}: store is read-only ({cause}); nothing was changed")


def update_store(path, source, region: Region, blend_width_km: float = 100.0, executor: Executor | None = None,
                 tolerance_m: float | None = None, progress=None, wait_seconds: float = 0.0, sign=None) -> dict:
    """Replace the store's geoid inside ``region`` by ``source``; return the update report.

    Refused before anything is written when the store is read-only or locked by another
    writer, when the source's ellipsoid or tide system differs from the store's, or when
    the region lies outside the source's extent or the store's region. The manifest is
    read once the writer lock is held, so concurrent updates apply one after the other
    (a second one started meanwhile waits up to ``wait_seconds`` for the first, then is
    refused; it is never lost).

    Coverage: the store answers where it did before and, inside ``region``, wherever
    ``source`` has data; where the source has no data (a national grid's sea, say) the
    store keeps its own values (the residual fitted there is 0) and its coverage.
    ``tolerance_m`` (metres), when given, is this update's tolerance instead of the
    store's. The update may add levels finer than the store's, as far as the new
    source's node spacing determines them.

    ``sign``: an Ed25519 private key (object or PEM file) that signs the new manifest
    (:mod:`geoidspline.store.signing`). The signer vouches for the whole store, so a
    store whose current version is signed must be signed by the same key (checked
    before the update); an unsigned update of a signed store leaves it unsigned, with a
    warning.
    """
    root = Path(path)
    signing_key = load_private_key(sign) if sign is not None else None  # a bad key before any work
    blend_width_km = check_number("blend_width_km", blend_width_km)
    tolerance_m = check_number("tolerance_m", tolerance_m, rule="update_tolerance_m")
    wait_seconds = check_number("wait_seconds", wait_seconds)
    load_manifest(root)  # a store, before a lock file is created in it
    _check_writable(root)
    with StoreLock(root, wait_seconds):
        crash_point("after-lock")
        version = load_manifest(root)["store_version"]
        signed = (root / signature_name(version)).exists()
        # the manifest as it is now that the lock is held (and, to be signed again, as signed)
        store = TileStore.open(root, key=signing_key.public_key() if signing_key and signed else None)
        state = _manifest_state(root)
        if signed and signing_key is None:
            log.warning("%s: store version %d is signed (%s); this update is not, so the store will not be: "
                        "sign it with the key (sign=KEY, geoid-update --sign KEY)", root, version,
                        signature_name(version))
        _check_compatible(store, source, region, blend_width_km)
        manifest = store.manifest
        with _Attempt(root, manifest["store_version"]) as attempt:
            record, new_manifest = _update(root, store, source, region, blend_width_km, executor, progress, attempt,
                                          tolerance_m)
            commit(root, new_manifest, keep_files=[e["file"] for e in manifest["tiles"]], expect_state=state,
                   attempt=attempt, signing_key=signing_key)
    record["signed_by"] = key_fingerprint(signing_key) if signing_key is not None else None
    return record


def _update(root, store, source, region, blend_width_km, executor, progress, attempt, tolerance_m=None):
    """Fit the update and write its tile files; (history record, new manifest)."""
    manifest = store.manifest
    params = _stored_parameters(store)
    if tolerance_m is not None:  # this update's tolerance
        params = dataclasses.replace(params, tolerance_m=float(tolerance_m))
    # Levels finer than the store's, down to what the new data determines (the driver
    # stops at MIN_H_PER_DATA_SPACING): Δ must fall to 0 inside the blend zone, and a
    # national grid is usually much finer than the global source the store was fitted to.
    params = dataclasses.replace(params, max_level=finest_level(params.h0))
    blend_deg = blend_width_km / KM_PER_DEGREE
    zone = region.expanded(blend_deg) if blend_deg > 0 else region

    # Δ's B-splines lie inside the zone (_ResidualRefinement): the zone's nodes are all the data
    sample = source.nodes(clip_to_extent(zone, source), spacing_deg=params.sample_spacing_deg)
    lat2, lon2 = np.meshgrid(sample.latitude, sample.longitude, indexing="ij")
    old = store.spline.full.undulation(lat2, lon2)  # the spline, covered or not
    weight = blend_weight(region, blend_deg, lat2, lon2)
    has_new = np.isfinite(sample.undulation)
    difference = np.where(has_new, sample.undulation - old, np.nan)
    # no new data where the store has its own (a national grid's sea): the change fades
    # out from the nearest new data over the blend width, as at the region's edge, so the
    # coast is no step; farther out the store keeps its values (residual 0)
    keep_old = ~has_new & np.asarray(store.coverage.covers(lat2, lon2))
    faded = fade_into_no_data(difference, sample.latitude, sample.longitude, blend_width_km)
    residual = weight * np.where(has_new, difference, np.where(keep_old, faded, np.nan))
    try:
        new_coverage = Coverage.from_sample(sample, region, source.provenance.source)
    except ValueError as exc:
        raise FitError(str(exc)) from None
    delta = fit_nodes(NodeSample(sample.latitude, sample.longitude, residual), zone, params,
                      refinement=_ResidualRefinement(params.refine_radius, zone), progress=progress, executor=executor,
                      base_is_overlay=True, finer_hint=finer_data_hint(source))
    merged = _merge(store.spline, delta.spline)
    format_version, encoding = tile_encoding(manifest)  # the store's own tile format and step
    inside = region.contains(lat2, lon2) & has_new
    store_step = encoding.get("value_step_m")
    if store_step:
        # the errors of what the store will hold: a format-2 store rounds coefficients
        # to its step; the rewritten tiles take the store's step halved as often as the
        # update's tolerance needs at its nodes (the untouched tiles' coefficients are
        # multiples of every such step, so they keep their values)
        node_directions = directions(lat2[inside], lon2[inside])
        step, errors = node_safe_step(merged, node_directions,
                                      sample.undulation[inside] - merged.evaluate_points(node_directions),
                                      params.tolerance_m, start_step=store_step)
        encoding = dict(encoding, value_step_m=step)
        old_levels = {lv.level for lv in store.spline.levels}
        # each level's rounding: at most half its coarsest step anywhere (partition of unity)
        value_bound = sum((store_step if lv.level in old_levels else step) / 2.0 for lv in merged.levels)
    else:
        errors = sample.undulation[inside] - merged.undulation(lat2[inside], lon2[inside])
    converged = bool(delta.converged) and (errors.size == 0 or float(np.abs(errors).max()) <= params.tolerance_m)

    version = manifest["store_version"] + 1
    spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size, **encoding}
    if manifest.get("store_id"):
        spline_meta["store_id"] = manifest["store_id"]
    changed = set(tile_groups(delta.spline, params.tile_size))
    groups = tile_groups(merged, params.tile_size)
    node_tile = group_by_tile(directions(lat2[inside], lon2[inside]), params.tile_size)
    entries = {tuple(e["tile"]): e for e in manifest["tiles"]}
    crash_point("before-tiles")
    for key in sorted(changed):
        tile = tuple(int(v) for v in unpack_keys(np.array([key]))[0])
        stats = tile_stats(errors[node_tile == key], [])
        if tile in entries and stats["nodes"] == 0:
            # outside the region: the old measurements still describe it
            kept = {k: entries[tile][k] for k in ("max_error_m", "rms_error_m", "check_points",
                                                  "node_max_error_m", "node_rms_error_m", "nodes")
                    if k in entries[tile]}
            stats = kept
        entries[tile] = write_tile_entry(root, key, groups[key], version, spline_meta, stats, attempt,
                                         format_version)
        crash_point("during-tiles")
    crash_point("after-tiles")
    region_stats = error_stats(errors)
    record = {
        "action": "update",
        "time": utc_now(),
        "store_version": version,
        "previous_version": manifest["store_version"],
        "source": source.provenance.source,
        "sha256": source.provenance.sha256,
        "model": source.provenance.model,
        "region": list(region.as_tuple()),
        "blend_width_km": blend_width_km,
        "tiles_rewritten": len(changed),
        "coefficients_added": int(merged.coefficient_count - store.spline.coefficient_count),
        "levels": [vars(r) for r in delta.levels],
        "nodes_in_region": region_stats["count"],
        "max_error_m": region_stats["max_error_m"],
        "rms_error_m": region_stats["rms_error_m"],
        "tolerance_m": params.tolerance_m,
        "converged": converged,
    }
    spacing_km = KM_PER_DEGREE * max(_step(sample.latitude), _step(sample.longitude))
    if not converged and blend_width_km < BLEND_NODE_SPACINGS * spacing_km:
        record["hint"] = (f"the blend width ({blend_width_km:g} km) spans fewer than {BLEND_NODE_SPACINGS} node "
                          f"spacings of {source.provenance.source} ({spacing_km:.3g} km): the update cannot fall "
                          f"to the store's values within it; widen the blend or use a finer source")
    new_manifest = dict(manifest)
    new_manifest.pop("integrity", None)
    new_manifest.update({
        "format_version": FORMAT_VERSION,
        "store_version": version,
        "updated": record["time"],
        "coverage": coverage_record(store.coverage.union(new_coverage)),
        "spline": dict(manifest["spline"], levels=[
            {"level": lv.level, "h": lv.h, "coefficients": len(lv)} for lv in merged.levels
        ], coefficients=merged.coefficient_count,
           **(quantisation_meta(store_step, len(merged.levels), value_bound) if store_step else {})),
        "tiles": [entries[k] for k in sorted(entries)],
        "history": manifest.get("history", []) + [record],
    })
    return record, new_manifest


def _merge(old: AmbientSpline, delta: AmbientSpline) -> AmbientSpline:
    """old + delta as one set of levels (the union of keys, coefficients added)."""
    by_level = {lv.level: lv for lv in old.levels}
    for lv in delta.levels:
        by_level[lv.level] = add_levels(by_level[lv.level], lv) if lv.level in by_level else lv
    return AmbientSpline([by_level[k] for k in sorted(by_level)])
