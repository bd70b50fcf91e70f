"""Writing a regional update: the writer lock, the rewritten tiles, the next manifest.

The update itself (Δ fitted to the blended residual) is a strategy of the fit
(:mod:`geoidspline.fitting.update`); :func:`geoidspline.api.update` composes the two
inside :func:`update_transaction`. The new tiles and manifest are committed the same
atomic way as a fresh store (:mod:`geoidspline.store.writer`); the previous version's
tile files are kept for readers that opened it, until the next write. Only the tiles
owning Δ's B-splines are rewritten: every other tile file stays byte-identical.
"""

from __future__ import annotations

import contextlib
import logging
import os
from pathlib import Path

import numpy as np

from ..bspline.keys import unpack_keys
from ..bspline.level import tiles_of_directions
from ..errors import StoreError
from ..sphere.coordinates import directions
from .codec import node_safe_step
from .coverage import coverage_record
from .format import TILE_DIR, error_stats, load_manifest, utc_now
from .manifest import build_manifest
from .reader import TileStore
from .signing import key_fingerprint, load_private_key, signature_name
from .writer import (
    StoreLock,
    _Attempt,
    _manifest_state,
    commit,
    crash_point,
    quantisation_meta,
    tile_encoding,
    tile_groups,
    tile_stats,
    write_tile_entry,
)

__all__ = ["update_transaction", "UpdateTransaction"]

log = logging.getLogger("geoidspline.store")


def _check_writable(root: Path):
    if not (os.access(root, os.W_OK) and os.access(root / TILE_DIR, os.W_OK)):
        try:
            read_only_fs = bool(os.statvfs(root).f_flag & os.ST_RDONLY)
        except OSError:
            read_only_fs = False
        cause = "read-only file system" if read_only_fs else "no permission to write it"
        raise StoreError(f"{root}: store is read-only ({cause}); nothing was changed")


class UpdateTransaction:
    """One update of a store under its writer lock: :attr:`store` as it is now that the
    lock is held; :meth:`write` writes the update's tiles and makes its manifest, which
    :func:`update_transaction` commits when its block ends without an error."""

    def __init__(self, root: Path, store: TileStore, attempt: _Attempt):
        self.root = root
        self.store = store
        self.attempt = attempt
        self.manifest: dict | None = None
        self.record: dict | None = None

    def write(self, update, source, region, blend_width_km: float) -> dict:
        """Write the tiles Δ (a :class:`geoidspline.fitting.update.RegionalUpdate`)
        changes; return the update's history record (the manifest waits for the commit)."""
        self.record, self.manifest = _write_update(self.root, self.store, update, source, region, blend_width_km,
                                                   self.attempt)
        return self.record


@contextlib.contextmanager
def update_transaction(path, blend_width_km: float = 100.0, wait_seconds: float = 0.0, sign=None):
    """Lock the store at ``path`` for an update and commit what :meth:`UpdateTransaction.write`
    wrote when the block ends; an error in the block leaves the store as it was.

    Refused before anything is written when the store is read-only or locked by another
    writer (after ``wait_seconds``). The manifest is read once the writer lock is held,
    so concurrent updates apply one after the other (a second one started meanwhile
    waits up to ``wait_seconds`` for the first, then is refused; it is never lost).

    ``sign``: an Ed25519 private key (object or PEM file) that signs the new manifest
    (:mod:`geoidspline.store.signing`). The signer vouches for the whole store, so a
    store whose current version is signed must be signed by the same key (checked
    before the update); an unsigned update of a signed store leaves it unsigned, with a
    warning.
    """
    root = Path(path)
    signing_key = load_private_key(sign) if sign is not None else None  # a bad key before any work
    if not blend_width_km >= 0.0:
        raise StoreError(f"blend width must be a non-negative number of km, got {blend_width_km}")
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
        manifest = store.manifest
        with _Attempt(root, manifest["store_version"]) as attempt:
            transaction = UpdateTransaction(root, store, attempt)
            yield transaction
            if transaction.manifest is None:
                raise StoreError(f"{root}: the update wrote nothing; nothing was changed")
            if transaction.record is not None:
                transaction.record["signed_by"] = key_fingerprint(signing_key) if signing_key is not None else None
            commit(root, transaction.manifest, keep_files=[e["file"] for e in manifest["tiles"]],
                   expect_state=state, attempt=attempt, signing_key=signing_key)


def _write_update(root, store, update, source, region, blend_width_km, attempt):
    """Write the update's tile files; (history record, new manifest)."""
    manifest = store.manifest
    params = update.parameters
    delta, merged = update.delta, update.merged
    format_version, encoding = tile_encoding(manifest)  # the store's own tile format and step
    node_directions = directions(update.node_latitude, update.node_longitude)
    store_step = encoding.get("value_step_m")
    value_bound = None
    if store_step:
        # the errors of what the store will hold: a format-2 store rounds coefficients
        # to its step; the rewritten tiles take the store's step halved as often as the
        # update's tolerance needs at its nodes (the untouched tiles' coefficients are
        # multiples of every such step, so they keep their values)
        step, errors = node_safe_step(merged, node_directions,
                                      update.node_undulation - merged.evaluate_points(node_directions),
                                      params.tolerance_m, start_step=store_step)
        encoding = dict(encoding, value_step_m=step)
        old_levels = {lv.level for lv in store.spline.levels}
        # each level's rounding: at most half its coarsest step anywhere (partition of unity)
        value_bound = sum((store_step if lv.level in old_levels else step) / 2.0 for lv in merged.levels)
    else:
        errors = update.node_undulation - merged.undulation(update.node_latitude, update.node_longitude)
    converged = bool(delta.converged) and (errors.size == 0 or float(np.abs(errors).max()) <= params.tolerance_m)

    version = manifest["store_version"] + 1
    spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size, **encoding}
    if manifest.get("store_id"):
        spline_meta["store_id"] = manifest["store_id"]
    changed = set(tile_groups(delta.spline, params.tile_size))
    groups = tile_groups(merged, params.tile_size)
    node_tile = tiles_of_directions(node_directions, params.tile_size)
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
    hint = None if converged else update.hint(source.provenance.source)
    if hint:
        record["hint"] = hint
    if update.plausibility is not None:
        record["plausibility"] = update.plausibility
    if update.source_notes:
        record["source_notes"] = list(update.source_notes)
    levels = [{"level": lv.level, "h": lv.h, "coefficients": len(lv)} for lv in merged.levels]
    spline = dict(manifest["spline"], levels=levels, coefficients=merged.coefficient_count,
                  **(quantisation_meta(store_step, len(merged.levels), value_bound) if store_step else {}))
    return record, build_manifest(record, [entries[k] for k in sorted(entries)], manifest,
                                  coverage=coverage_record(update.coverage), spline=spline)
