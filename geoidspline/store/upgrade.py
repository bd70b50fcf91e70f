"""Converting a format-1 store to format 2 in place, atomically (``geoid-info --upgrade``).

Every tile is read (sha256 checked), written again in format 2 under the next store
version's names, and the new manifest committed in one :func:`os.replace`, as any
write (:mod:`geoidspline.store.writer`): a crash leaves the format-1 store as it was.
The coefficients are quantised with the largest step whose proven bound (``levels ·
step / 2``) fits in the room the fit left at its nodes (its tolerance minus its node
max; :func:`~geoidspline.store.codec.slack_step`): the nodes themselves are not in the
store, so a fresh fit's check at every node (:func:`~geoidspline.store.codec.node_safe_step`)
cannot be made, and the bound alone keeps the nodes within the tolerance. The
manifest's accuracy figures are the fit's and stay, the bound is stated beside them.
"""

from __future__ import annotations

import logging
import uuid
from pathlib import Path

import numpy as np

from ..bspline.keys import pack_keys, unpack_keys
from ..errors import StoreError
from .codec import slack_step
from .coverage import coverage_record
from .format import FORMAT_VERSION, load_manifest, utc_now
from .manifest import build_manifest
from .reader import TileStore
from .signing import signature_name
from .writer import (StoreLock, _Attempt, _manifest_state, commit, crash_point, quantisation_meta, tolerance_asked,
                     write_tile_entry)

__all__ = ["upgrade_store"]

_STAT_KEYS = ("max_error_m", "rms_error_m", "check_points", "node_max_error_m", "node_rms_error_m", "nodes")

log = logging.getLogger("geoidspline.store")


def upgrade_store(path) -> dict:
    """Rewrite the format-1 store at ``path`` (or a format-2 manifest whose tiles are still
    format 1: a format-1 store updated since) in format 2; return the history record.

    A store already in format 2 is refused (nothing to do), as is one locked by a writer.
    The manifest is read again once the writer lock is held; an I/O fault removes the
    files written and leaves the store as it was (as every write).
    """
    root = Path(path)
    manifest = load_manifest(root)
    _refuse_current(root, manifest)
    with StoreLock(root):
        crash_point("after-lock")
        store = TileStore.open(root)  # the manifest as it is now that the lock is held
        state = _manifest_state(root)
        manifest = store.manifest
        _refuse_current(root, manifest)
        was_signed = (root / signature_name(manifest["store_version"])).exists()
        with _Attempt(root, manifest["store_version"]) as attempt:
            record, new_manifest = _upgrade(root, store, attempt)
            commit(root, new_manifest, keep_files=[e["file"] for e in manifest["tiles"]], expect_state=state,
                   attempt=attempt)
    if was_signed:  # the signature went with the old version
        log.warning("%s: store version %d was signed; the upgraded store is not: sign it again with a signed "
                    "update (docs/signing.md)", root, manifest["store_version"])
    return record


def _refuse_current(root, manifest):
    # a quantised store (format 2 or later) is refused: its tiles may hold steps finer than
    # the manifest's (regional updates), which re-quantising would change; format 3 reads
    # its format-2 tiles as they are
    if manifest["spline"].get("value_step_m") is not None:
        raise StoreError(f"{root}: already in store format {manifest['format_version']} (quantised tiles, "
                         f"read as they are)")


def _upgrade(root, store, attempt):
    """Write every tile again in format 2; return (history record, new manifest)."""
    manifest = store.manifest
    meta = manifest["spline"]
    levels = len(meta["levels"])
    # the nodes are not at hand: the step whose proven bound fits in the room the fit left
    step = slack_step(tolerance_asked(manifest["fit"]), manifest["accuracy"]["node_max_error_m"] or 0.0, levels)
    store_id = manifest.get("store_id") or uuid.uuid4().hex  # every tile is rewritten: all will carry it
    spline_meta = {"order": meta["order"], "h0": meta["h0"], "tile_size": meta["tile_size"],
                   "value_step_m": step, "store_id": store_id}
    version = manifest["store_version"] + 1
    entries = []
    before = after = 0
    decoded = store.spline._decode([tuple(e["tile"]) for e in manifest["tiles"]])  # checked as any read
    crash_point("before-tiles")
    for entry in manifest["tiles"]:
        parts = decoded.pop(tuple(entry["tile"]))  # {level: (keys, values)}
        lvl = np.concatenate([np.full(k.size, level) for level, (k, _) in parts.items()])
        idx = np.concatenate([unpack_keys(k) for k, _ in parts.values()])
        val = np.concatenate([v for _, v in parts.values()])
        new = write_tile_entry(root, _tile_key(entry["tile"]), (lvl, idx, val), version, spline_meta,
                               {k: entry.get(k) for k in _STAT_KEYS if k in entry}, attempt, FORMAT_VERSION)
        entries.append(new)
        before += entry["bytes"]
        after += new["bytes"]
        crash_point("during-tiles")
    crash_point("after-tiles")
    record = {
        "action": "upgrade",
        "time": utc_now(),
        "store_version": version,
        "previous_version": manifest["store_version"],
        "from_format": manifest["format_version"],
        "to_format": FORMAT_VERSION,
        "tile_bytes_before": before,
        "tile_bytes_after": after,
        **quantisation_meta(step, levels),
    }
    return record, build_manifest(record, entries, manifest, store_id=store_id,
                                  coverage=manifest.get("coverage") or coverage_record(store.coverage),
                                  spline=dict(meta, **quantisation_meta(step, levels)))


def _tile_key(tile):
    return int(pack_keys(np.asarray(tile, dtype=np.int64)))
