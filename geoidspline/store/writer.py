"""Writing a store: the writer lock, tile files under new names, one atomic commit.

Writing is atomic: tile files are written under new names (they are never changed
once written), then ``manifest.json`` is replaced with :func:`os.replace`, so a crash
leaves either the old manifest with its old files or the new one with all of its own.
Tile files no manifest names are removed afterwards. A directory without
``manifest.json`` is not a store (a first write that crashed), and opening it says so.

One writer at a time, enforced by the kernel: a writer holds ``fcntl.flock`` on
``STORE/.lock`` (the file is never removed; the kernel releases the lock when its
holder exits or is killed) and reads the manifest only once it holds the lock.

A writer removes only names the store format owns (:func:`~.format.is_store_file`),
never another file: a directory holding anything else is refused, and with
``overwrite`` the other files are left where they are. A fault while writing (disk
full, read-only file system, no permission) is one :class:`StoreError` naming the file
and the cause; the store's previous version stays as it was.
"""

from __future__ import annotations

import errno
import hashlib
import logging
import os
import signal
import stat
import time
import uuid
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .._files import fault_cause, fsync_dir, sha256_file, write_fault
from ..bspline import keys as _keys
from ..bspline.level import cube_of_support_centres, tiles_of_directions
from ..errors import StoreCorruptError, StoreError
from ..sphere.coordinates import directions
from ..sphere.coverage import Coverage
from .codec import node_safe_step, quantisation_change, quantised_spline, value_error_bound
from .coverage import coverage_record
from .manifest import build_manifest
from .format import (
    FORMAT_VERSION,
    LOCK,
    MANIFEST,
    MANIFEST_TMP,
    MARKER,
    PROGRESS,
    SIGNATURE_NAME,
    TILE_DIR,
    error_stats,
    is_store_file,
    load_manifest,
    manifest_text,
    tile_name,
    utc_now,
    write_tile_file,
)
from .signing import load_private_key, signature_name, write_signature

if TYPE_CHECKING:  # annotations only
    from ..hierarchy.ambient import AmbientSpline

log = logging.getLogger("geoidspline.store")


_crash_counts: dict = {}


def crash_point(name):
    """Test hooks at the commit points of a write.

    ``GEOIDSPLINE_CRASH_AT=name``: die here like SIGKILL (no clean-up), the
    ``GEOIDSPLINE_CRASH_AFTER``-th time (default the first) the write gets here.
    ``GEOIDSPLINE_STOP_AT=name``: stop here (SIGSTOP), for a test to SIGKILL the process.
    """
    if os.environ.get("GEOIDSPLINE_CRASH_AT") == name:
        _crash_counts[name] = _crash_counts.get(name, 0) + 1
        if _crash_counts[name] >= int(os.environ.get("GEOIDSPLINE_CRASH_AFTER", "1")):
            os._exit(77)
    if os.environ.get("GEOIDSPLINE_STOP_AT") == name:
        os.kill(os.getpid(), signal.SIGSTOP)


# -- faults ---------------------------------------------------------------------------


class _Attempt:
    """The files one write creates; on an I/O fault they are removed again and the fault
    becomes one :class:`StoreError` naming the file being written and the cause."""

    def __init__(self, root: Path, previous_version):
        self.root = root
        self.previous_version = previous_version
        self.created: list[Path] = []
        self.current: Path = root

    def writing(self, path: Path):
        self.current = path
        return path

    def __enter__(self):
        return self

    def __exit__(self, kind, exc, tb):
        if exc is None or not isinstance(exc, (OSError, RuntimeError, MemoryError)) or isinstance(exc, StoreError):
            return False
        for path in self.created:
            try:
                path.unlink(missing_ok=True)
            except OSError:
                pass
        kept = (f"the store's version {self.previous_version} is unchanged" if self.previous_version
                else "no store was written")
        raise StoreError(f"{self.current}: cannot write the store {self.root}: {fault_cause(exc)}; {kept}") from None


def _write_tile(path: Path, tile, levels, indices, values, attrs, format_version=FORMAT_VERSION):
    try:
        write_tile_file(path, tile, levels, indices, values, attrs, format_version)
    except (RuntimeError, OSError) as exc:
        raise write_fault(path.parent, exc) from None


# -- the lock -------------------------------------------------------------------------


#: How often a writer waiting for the lock tries it again (seconds).
LOCK_POLL_SECONDS = 0.2


def _pause(seconds: float) -> None:
    """Sleep between tries of the lock (a seam for tests)."""
    time.sleep(seconds)


class StoreLock:
    """Exclusive writer lock of a store: ``fcntl.flock`` on ``STORE/.lock``.

    A store another process is writing is refused with a :class:`StoreError` naming
    that process, at once or, with ``wait_seconds`` > 0, once the lock has stayed taken
    that long (the lock is tried every :data:`LOCK_POLL_SECONDS` meanwhile; whoever
    tries first after the holder is done gets it). The kernel releases the lock when
    its holder exits or is killed, so a dead writer never blocks the next one; the file
    itself is never removed (removing it would let two writers lock two different
    files) and holds the holder's pid for messages only. Worker processes forked while
    the lock is held share it until they exit.
    """

    def __init__(self, root: Path, wait_seconds: float = 0.0):
        self.root = Path(root)
        self.path = self.root / LOCK
        self.fd: int | None = None
        self.wait_seconds = float(wait_seconds)

    def __enter__(self):
        import fcntl

        try:
            fd = os.open(self.path, os.O_RDWR | os.O_CREAT | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC, 0o644)
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise StoreCorruptError(f"{self.path}: is a symbolic link, not the store's lock file") from None
            raise StoreError(f"{self.root}: cannot take the writer lock {LOCK}: {fault_cause(exc)}") from None
        try:
            mode = os.fstat(fd).st_mode
            if not stat.S_ISREG(mode):
                raise StoreCorruptError(f"{self.path}: is not a regular file, not the store's lock file")
            deadline = time.monotonic() + self.wait_seconds
            while True:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    left = deadline - time.monotonic()
                    if left <= 0.0:
                        raise _another_writer(self.root, _read_pid(fd), self.wait_seconds) from None
                    _pause(min(LOCK_POLL_SECONDS, left))
                except OSError as exc:
                    raise StoreError(f"{self.root}: cannot take the writer lock {LOCK}: {fault_cause(exc)}") from None
        except BaseException:
            os.close(fd)
            raise
        try:  # for messages only: a full disk must not stop the writer here
            os.ftruncate(fd, 0)
            os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        except OSError:
            pass
        self.fd = fd
        return self

    def __exit__(self, *exc):
        import fcntl

        fd, self.fd = self.fd, None
        if fd is not None:
            try:
                os.ftruncate(fd, 0)
            except OSError:
                pass
            fcntl.flock(fd, fcntl.LOCK_UN)
            os.close(fd)
        return False


def _another_writer(root: Path, holder: int | None, waited_seconds: float = 0.0) -> StoreError:
    """The refusal when another writer holds the lock of the store at ``root``."""
    waited = f" (waited {waited_seconds:g} s)" if waited_seconds > 0 else ""
    return StoreError(
        f"{root}: another writer{f' (pid {holder})' if holder else ''} is writing this "
        f"store{waited}; try again when it has finished, or let this command wait for it "
        f"(geoid-update --wait SECONDS; wait_seconds= in Python)")


def _lock_holder(root: Path) -> tuple[bool, int | None]:
    """Whether another open file holds the writer lock of ``root`` now (and its pid when
    it wrote one), for the checks made before this writer takes the lock: an unfinished
    write's files are then another writer's work in progress, not leftovers. A lock file
    that cannot be opened or locked counts as free (StoreLock reports it when taken)."""
    import fcntl

    try:
        fd = os.open(root / LOCK, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError:
        return False, None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # released by the close below
    except BlockingIOError:
        return True, _read_pid(fd)
    except OSError:
        return False, None
    finally:
        os.close(fd)
    return False, None


def _read_pid(fd) -> int | None:
    try:
        text = os.pread(fd, 32, 0).decode("ascii", "replace").strip()
        return int(text) if text.isdigit() else None
    except (OSError, ValueError):
        return None


# -- the directory --------------------------------------------------------------------


def scan_directory(root: Path) -> tuple[list[str], list[str]]:
    """(names the store format owns, every other name) in ``root`` and ``root/tiles``,
    relative to ``root``; an empty ``tiles`` directory counts as neither."""
    ours, others = [], []
    with os.scandir(root) as entries:
        for entry in entries:
            name = entry.name
            if name == TILE_DIR and entry.is_dir(follow_symlinks=False):
                with os.scandir(entry.path) as tiles:
                    for tile in tiles:
                        rel = f"{TILE_DIR}/{tile.name}"
                        (ours if is_store_file(rel) and tile.is_file(follow_symlinks=False) else others).append(rel)
            elif is_store_file(name) and entry.is_file(follow_symlinks=False):
                ours.append(name)
            else:
                others.append(name)
    return sorted(ours), sorted(others)


def _manifest_state(root: Path) -> str | None:
    """sha256 of the bytes of manifest.json, None when there is none (to see a change)."""
    try:
        with open(root / MANIFEST, "rb") as fh:
            return hashlib.sha256(fh.read()).hexdigest()
    except FileNotFoundError:
        return None


def _previous_store(root: Path, overwrite: bool, locked: bool = False) -> dict | None:
    """The manifest of the store at ``root`` that a new write replaces, or None.

    Refuses (before anything is written) a directory that is not a store, a store
    without ``overwrite``, and leftovers of an unfinished write without ``overwrite``;
    before the lock is taken (not ``locked``), such files while another writer holds the
    lock as that writer's work in progress.
    """
    if not root.exists():
        return None
    if not root.is_dir():
        raise StoreError(f"{root}: exists and is not a directory")
    try:
        ours, others = scan_directory(root)
    except OSError as exc:
        raise StoreError(f"{root}: cannot be listed: {fault_cause(exc)}") from None
    if (root / TILE_DIR).is_symlink() or ((root / TILE_DIR).exists() and not (root / TILE_DIR).is_dir()):
        raise StoreError(f"{root / TILE_DIR}: is not a directory of a store (a symbolic link or a file); refusing "
                         f"to write through it")
    if MANIFEST in ours:
        try:
            previous = load_manifest(root)
        except StoreCorruptError as exc:
            if not overwrite:
                raise StoreError(f"{root}: a damaged store is here ({exc}); pass overwrite=True to replace it") \
                    from None
            return None  # replacing a damaged store is what --overwrite is for
        except StoreError as exc:
            raise StoreError(f"{root}: {exc}; refusing to replace it") from None
        if not overwrite:
            raise StoreError(f"{root}: a store already exists here (pass overwrite=True to replace it)")
        return previous
    leftovers = [name for name in ours if name not in (LOCK, MARKER)]
    if leftovers:
        held, holder = (False, None) if locked else _lock_holder(root)
        if held:  # another writer's work in progress, not leftovers: its lock refuses this write
            raise _another_writer(root, holder)
        if not overwrite:
            raise StoreError(
                f"{root}: holds the leftovers of a store write that did not finish ({len(leftovers)} files such as "
                f"{leftovers[0]}) and no {MANIFEST}; pass overwrite=True to clear them")
        return None
    if others and MARKER not in ours:
        raise StoreError(f"{root}: directory is not empty and is not a geoidspline store "
                         f"(it holds {others[0]}); nothing was written")
    return None


def _create_store_directory(root: Path):
    """Create ``root`` (if needed), its marker and ``tiles/``; the marker comes first so
    that a write killed at any later point leaves a directory recognised as a store's."""
    try:
        root.mkdir(parents=True, exist_ok=True)
        marker = root / MARKER
        if not marker.exists():
            fd = os.open(marker, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
            try:
                os.write(fd, b"geoidspline tile store: written by geoidspline, do not put other files here\n")
            finally:
                os.close(fd)
        crash_point("after-marker")
        (root / TILE_DIR).mkdir(exist_ok=True)
    except OSError as exc:
        raise StoreError(f"{root}: cannot create the store directory: {fault_cause(exc)}; no store was written") \
            from None
    if (root / TILE_DIR).is_symlink() or not (root / TILE_DIR).is_dir():
        raise StoreError(f"{root / TILE_DIR}: is not a directory of a store (a symbolic link or a file)")


# -- tiles ----------------------------------------------------------------------------


def tile_groups(spline: AmbientSpline, tile_size: float) -> dict:
    """Coefficients of every level grouped by tile: {tile key: (levels, indices, values)}."""
    all_idx, all_lvl, all_val, all_tile = [], [], [], []
    for lv in spline.levels:
        idx = lv.indices
        all_idx.append(idx)
        all_lvl.append(np.full(len(lv), lv.level))
        all_val.append(lv.coefficients)
        all_tile.append(_keys.pack_keys(cube_of_support_centres(idx, lv.h, lv.order, tile_size)))
    if not all_idx:
        return {}
    idx = np.concatenate(all_idx)
    lvl = np.concatenate(all_lvl)
    val = np.concatenate(all_val)
    tile_keys = np.concatenate(all_tile)
    order = np.argsort(tile_keys, kind="stable")
    unique, starts = np.unique(tile_keys[order], return_index=True)
    stops = np.append(starts[1:], order.size)
    return {int(key): (lvl[order[a:b]], idx[order[a:b]], val[order[a:b]]) for key, a, b in zip(unique, starts, stops)}


def write_tile_entry(root, key, group, version, spline_meta, stats, attempt: _Attempt | None = None,
                     format_version=FORMAT_VERSION) -> dict:
    """Write one tile file (of tile format ``format_version``) under a new name and return
    its manifest entry."""
    lvl, idx, val = group
    tile = _keys.unpack_keys(np.array([key]))[0]
    name = tile_name(tile, version, format_version)
    path = root / TILE_DIR / name
    if attempt is not None:
        attempt.writing(path)
        attempt.created.append(path)
    _write_tile(path, tile, lvl, idx, val, {**spline_meta, "store_version": version}, format_version)
    return {
        "tile": [int(v) for v in tile],
        "file": f"{TILE_DIR}/{name}",
        "bytes": path.stat().st_size,
        "sha256": sha256_file(path),
        "coefficients": int(val.size),
        "levels": [int(v) for v in np.unique(lvl)],
        **stats,
    }


def quantisation_meta(step, levels, bound_m: float | None = None, nudged: bool = False) -> dict:
    """The manifest's statement of a format-2 store's quantisation (``spline`` keys);
    ``bound_m`` when the levels' steps differ (a regional update's finer tiles), else
    ``levels · step / 2``, or ``levels · step`` when ``nudged`` (a banded fit's rounding,
    corrected at its nodes: :func:`geoidspline.fitting.bands.band_step`)."""
    if nudged:
        return {"value_step_m": step,
                "value_error_bound_m": 2.0 * value_error_bound(step, levels) if bound_m is None else float(bound_m),
                "value_error_rule": "each coefficient within step/2, or within a step where the rounding was "
                                    "corrected at the nodes; B-splines of a level are non-negative and sum to at "
                                    "most 1, so the value moves by at most a step per level"}
    return {
        "value_step_m": step,
        "value_error_bound_m": value_error_bound(step, levels) if bound_m is None else float(bound_m),
        "value_error_rule": "each coefficient within step/2; B-splines of a level are non-negative and sum "
                            "to at most 1, so the value moves by at most step/2 per level",
    }


def tolerance_asked(fit: dict) -> float:
    """The tolerance a store promises at its nodes, from its manifest's ``fit`` section:
    the one asked for (``choices``: a model fit works to 0.8 of it at the nodes) or the
    fit's own ``tolerance_m``."""
    choices = fit.get("choices") or {}
    return float(choices.get("tolerance_asked_m") or fit["tolerance_m"])


def tile_encoding(manifest) -> tuple[int, dict]:
    """(tile format, tile attributes) with which new tiles of a store are written: its own
    tiles' format and step, so that an update of a format-1 store keeps netCDF4 tiles
    (its manifest becomes the current format: coverage and integrity; ``--upgrade``
    re-encodes) and one of a format-2 store keeps format-2 tiles (format 3 reads both)."""
    step = manifest["spline"].get("value_step_m")
    return (min(int(manifest["format_version"]), FORMAT_VERSION), {"value_step_m": step}) if step is not None \
        else (1, {})


def tile_stats(node_errors, check_errors):
    nodes = error_stats(node_errors)
    checks = error_stats(check_errors)
    return {
        "max_error_m": checks["max_error_m"],
        "rms_error_m": checks["rms_error_m"],
        "check_points": checks["count"],
        "node_max_error_m": nodes["max_error_m"],
        "node_rms_error_m": nodes["rms_error_m"],
        "nodes": nodes["count"],
    }


# -- the commit -----------------------------------------------------------------------


def _write_all(fd, data: bytes):
    view = memoryview(data)
    while view:
        written = os.write(fd, view)
        view = view[written:]


def commit(root: Path, manifest: dict, keep_files=(), expect_state: str | None = None,
           attempt: _Attempt | None = None, signing_key=None):
    """Make ``manifest`` the store's state in one atomic rename, then remove tile files
    that neither it nor ``keep_files`` (the previous version's, for readers that
    opened it just before) name. Only names the store format owns are removed.

    ``expect_state`` is :func:`_manifest_state` as the writer read it under the lock:
    a manifest changed since (a writer that ignored the lock) is never overwritten.

    ``signing_key`` (an Ed25519 private key, :mod:`~geoidspline.store.signing`): the
    signature of the new manifest's bytes is written and flushed under its version's
    own name before the rename, and the previous version's removed only after it, so a
    crash leaves each manifest with its own signature (or none, if it had none).
    """
    fsync_dir(root / TILE_DIR)
    crash_point("before-manifest")
    if _manifest_state(root) != expect_state:
        raise StoreError(f"{root}: the store changed while this write ran (another writer ignored the lock); "
                         "nothing was committed: run it again")
    tmp = root / MANIFEST_TMP
    if attempt is not None:
        attempt.writing(tmp)
        attempt.created.append(tmp)
    tmp.unlink(missing_ok=True)  # a killed writer's; never followed if a symlink
    text = manifest_text(manifest)
    signature = signature_name(manifest["store_version"])
    if signing_key is not None:
        if attempt is not None:
            attempt.writing(root / signature)
            attempt.created.append(root / signature)
        write_signature(root, text, manifest["store_version"], signing_key)
        fsync_dir(root)
        crash_point("signature-written")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC, 0o644)
    try:
        _write_all(fd, text)
        os.fsync(fd)
    finally:
        os.close(fd)
    crash_point("manifest-written")
    os.replace(tmp, root / MANIFEST)
    if attempt is not None:
        attempt.created.clear()  # committed: nothing of this write is to be undone now
    fsync_dir(root)
    crash_point("after-manifest")
    live = {e["file"] for e in manifest["tiles"]} | set(keep_files)
    try:
        ours, _ = scan_directory(root)
        for rel in ours:
            stale_signature = SIGNATURE_NAME.fullmatch(rel) and (signing_key is None or rel != signature)
            if (rel.startswith(f"{TILE_DIR}/") and rel not in live) or stale_signature:
                (root / rel).unlink(missing_ok=True)
    except OSError as exc:  # committed already: stale files are removed by the next write
        log.warning("%s: stale tile files not removed (%s)", root, fault_cause(exc))


def write_store(path, result, provenance, check=None,
                overwrite=False, extra=None, format_version=FORMAT_VERSION, value_step_m=None,
                sign=None) -> Path:
    """Write a fit (:class:`geoidspline.fitting.driver.FitResult`) as a tile store at ``path``.

    An existing store is refused unless ``overwrite``; even then its files stay valid
    until the new manifest replaces the old one. A directory that is not a store is
    refused; leftovers of an unfinished write need ``overwrite``; nothing but the
    names the store format owns is ever removed. ``format_version=1`` writes the old
    format (netCDF4 tiles, float64 values), kept for tests of older stores; format 2
    quantises the coefficients with ``value_step_m`` (default
    :func:`~geoidspline.store.codec.node_safe_step`: the largest step at which the stored
    spline still meets the tolerance asked for at every node, and keeps a grid's check
    points within the tolerance, or the fit's own figure, of their interval); the node and check-point
    errors in the manifest are those of the stored (quantised) spline (``accuracy.
    fit_node_max_error_m`` keeps the fit's), each within ``value_error_bound_m`` of the fit's.
    ``check``: points that were not fit sites (``latitude``, ``longitude``, ``truth``
    arrays and a ``description``, as :func:`geoidspline.fitting.check_points.check_points`
    gives), or None.
    ``sign``: an Ed25519 private key (object or PEM file) that signs the manifest
    (:mod:`geoidspline.store.signing`).
    """
    root = Path(path)
    signing_key = load_private_key(sign) if sign is not None else None  # a bad key before any work
    _previous_store(root, overwrite)  # refuse before writing anything
    _create_store_directory(root)
    with StoreLock(root):
        crash_point("after-lock")
        previous = _previous_store(root, overwrite, locked=True)  # again, under the lock
        state = _manifest_state(root)
        version = (previous["store_version"] + 1) if previous else 1
        with _Attempt(root, previous["store_version"] if previous else None) as attempt:
            manifest = _fit_manifest(root, result, provenance, check, previous, version, extra, attempt,
                                     format_version, value_step_m)
            keep = [e["file"] for e in previous["tiles"]] if previous else []
            commit(root, manifest, keep, expect_state=state, attempt=attempt, signing_key=signing_key)
    return root


def _fit_manifest(root, result, provenance, check, previous, version, extra, attempt,
                  format_version=FORMAT_VERSION, value_step_m=None) -> dict:
    """Write the fit's tile files; return the manifest naming them."""
    params = result.parameters
    spline = result.spline
    store_id = uuid.uuid4().hex
    quantisation = {}
    stored = spline  # what the store will give: the node and check errors are its own
    node_errors = result.node_errors
    if format_version >= 2:
        if value_step_m:
            step = value_step_m
            node_errors = node_errors - quantisation_change(spline, step, result.node_directions)
        else:
            # a grid's cell centres keep their figure too: the store, not only the fit
            interval = getattr(check, "interval", None) if check is not None else None
            between = None if interval is None else (directions(check.latitude, check.longitude), *interval)
            step, node_errors = node_safe_step(spline, result.node_directions, node_errors,
                                               tolerance_asked({"tolerance_m": params.tolerance_m, **(extra or {})}),
                                               between=between)
        quantisation = quantisation_meta(step, len(spline.levels))
        stored = quantised_spline(spline, step)
    node_tile = tiles_of_directions(result.node_directions, params.tile_size)
    check_errors = cell_centre = None
    if check is not None:
        stored_values = stored.undulation(check.latitude, check.longitude)
        check_errors = check.truth - stored_values
        outside = check.interval_distance(stored_values) if hasattr(check, "interval_distance") else None
        if outside is not None:  # a grid: how far the store leaves its interpolants' interval
            cell_centre = float(outside.max()) if outside.size else 0.0
        check_tile = tiles_of_directions(directions(check.latitude, check.longitude), params.tile_size)
    spline_meta = {"order": params.order, "h0": params.h0, "tile_size": params.tile_size, "store_id": store_id}
    if format_version >= 2:
        spline_meta["value_step_m"] = quantisation["value_step_m"]
    entries = []
    crash_point("before-tiles")
    for key, group in tile_groups(spline, params.tile_size).items():
        stats = tile_stats(node_errors[node_tile == key],
                           check_errors[check_tile == key] if check is not None else [])
        entries.append(write_tile_entry(root, key, group, version, spline_meta, stats, attempt, format_version))
        crash_point("during-tiles")
    crash_point("after-tiles")

    coverage = result.coverage if result.coverage is not None else Coverage.of_region(result.region)
    return fit_manifest(
        entries, previous, version, store_id, provenance, result.region, coverage, params, quantisation,
        [{"level": lv.level, "h": lv.h, "coefficients": len(lv)} for lv in spline.levels],
        {"method": result.method, "converged": bool(result.converged), "seconds": round(result.seconds, 3),
         "level_reports": [vars(r) for r in result.levels], **(extra or {})},
        error_stats(node_errors), error_stats(result.node_errors)["max_error_m"],
        error_stats(check_errors if check is not None else []), check.description if check is not None else None,
        cell_centre, format_version)


def fit_manifest(entries, previous, version, store_id, provenance, region, coverage, params, quantisation,
                 level_counts, fit, node_stats, fit_node_max, check_stats, check_description, cell_centre=None,
                 format_version=FORMAT_VERSION) -> dict:
    """The manifest of a fit's store version ``version`` from its tile ``entries``, the
    levels' coefficient counts (``[{level, h, coefficients}]``), the ``fit`` section's
    account (method, converged, seconds, level reports, choices) and the stored spline's
    statistics at the nodes and check points (:func:`~.format.error_stats`)."""
    record = {
        "action": "fit",
        "time": utc_now(),
        "store_version": version,
        "source": provenance.source,
        "sha256": provenance.sha256,
        "region": list(region.as_tuple()),
    }
    return build_manifest(
        record, entries, previous,
        format_version=format_version,
        store_id=store_id,
        provenance=provenance.as_dict(),
        region=list(region.as_tuple()),
        coverage=coverage_record(coverage, provenance.source),
        spline={
            "reference_manifold": "unit sphere; direction u = (cos lat cos lon, cos lat sin lon, sin lat)",
            "order": params.order,
            "h0": params.h0,
            "tile_size": params.tile_size,
            "levels": level_counts,
            "coefficients": sum(lv["coefficients"] for lv in level_counts),
            **quantisation,
        },
        fit={
            "method": fit["method"],
            "parameters": params.as_dict(),
            "tolerance_m": params.tolerance_m,
            **fit,
        },
        accuracy={
            "nodes": node_stats["count"],
            "node_max_error_m": node_stats["max_error_m"],
            "node_rms_error_m": node_stats["rms_error_m"],
            "node_p99_error_m": node_stats["p99_error_m"],
            "fit_node_max_error_m": fit_node_max,
            "check_points": check_stats["count"],
            "check_truth": check_description,
            "max_error_m": check_stats["max_error_m"],
            "rms_error_m": check_stats["rms_error_m"],
            "p99_error_m": check_stats["p99_error_m"],
            # a grid: the largest distance of the store, at the centres of the grid's cells,
            # from the interval its bilinear and bicubic interpolants span there
            "cell_centre_max_m": cell_centre,
            "units": "m",
        },
    )


# -- a store written band by band -------------------------------------------------------


class BandedWrite:
    """A fit's store written band by band, each band committed on its own, so that an
    interrupted fit resumes where it stopped.

    Under the writer lock (held from :meth:`__enter__` to :meth:`__exit__`) a band's
    tiles are written under new names, flushed, and then the band is recorded in the
    progress record ``fit-progress.json`` (:data:`~.format.PROGRESS`), replaced
    atomically: a crash leaves every band recorded there with all its tiles, and a band
    not recorded is fitted again. A store directory holding that record is an unfinished
    fit, not a store: it has no manifest (or still the previous version's, which stays
    valid until :meth:`finish` commits the new one and removes the record). The record
    names the fit (``identity``: source, parameters, quantisation step, check points); a
    resumed fit must have the same one.

    ``overwrite``: replace a store (or an unfinished fit) there; ``resume``: continue the
    unfinished fit there (a directory without one starts a new fit).
    """

    def __init__(self, path, identity: dict, overwrite: bool = False, resume: bool = False, sign=None):
        self.root = Path(path)
        self.identity = identity
        self.overwrite = overwrite
        self.resume = resume
        self.signing_key = load_private_key(sign) if sign is not None else None
        self.lock: StoreLock | None = None
        self.progress: dict | None = None
        self.previous: dict | None = None
        self.state: str | None = None

    # the record of committed bands
    def _read_progress(self) -> dict | None:
        import json

        path = self.root / PROGRESS
        try:
            text = path.read_text(encoding="utf-8")
        except FileNotFoundError:
            return None
        except OSError as exc:
            raise StoreError(f"{path}: cannot be read: {fault_cause(exc)}") from None
        try:
            record = json.loads(text)
            record["bands"]  # noqa: B018 - the key a record must have
        except (ValueError, KeyError, TypeError):
            raise StoreCorruptError(f"{path}: is not a progress record of a banded fit; pass overwrite=True to "
                                    "start the fit again") from None
        return record

    def _write_progress(self):
        import json

        from .._files import atomic_write

        try:
            atomic_write(self.root / PROGRESS, json.dumps(self.progress, separators=(",", ":")).encode())
            fsync_dir(self.root)
        except OSError as exc:
            raise StoreError(f"{self.root / PROGRESS}: cannot record the band: {fault_cause(exc)}; the bands "
                             "recorded before are kept (resume the fit)") from None

    def _check_directory(self):
        """Refuse, before anything is written, what this write may not replace; return the
        unfinished fit's record to continue, or None."""
        record = self._read_progress() if self.root.is_dir() else None
        if record is not None:
            if self.resume:
                if record.get("identity") != self.identity:
                    theirs, ours = record.get("identity") or {}, self.identity
                    differ = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
                    raise StoreError(f"{self.root}: the unfinished fit there is not this one (its {', '.join(differ)} "
                                     "differ); fit with the same source and options, or pass overwrite=True "
                                     "to start again")
                return record
            if not self.overwrite:
                raise StoreError(f"{self.root}: holds an unfinished fit ({len(record['bands'])} bands committed); "
                                 "pass resume=True to continue it, or overwrite=True to start again")
            return None
        if self.resume and (self.root / MANIFEST).exists() and not self.overwrite:
            raise StoreError(f"{self.root}: holds a finished store, no unfinished fit to resume (pass "
                             "overwrite=True to fit it again)")
        return None

    def __enter__(self):
        record = self._check_directory()
        if record is None:
            self.previous = _previous_store(self.root, self.overwrite)
        _create_store_directory(self.root)
        self.lock = StoreLock(self.root)
        self.lock.__enter__()
        try:
            record = self._check_directory()  # again, under the lock
            if record is None:
                self.previous = _previous_store(self.root, self.overwrite, locked=True)
                version = (self.previous["store_version"] + 1) if self.previous else 1
                self.progress = {"identity": self.identity, "store_id": uuid.uuid4().hex, "store_version": version,
                                 "started": utc_now(), "bands": {}}
                self._write_progress()
            else:
                self.progress = record
                self.previous = load_manifest(self.root) if (self.root / MANIFEST).exists() else None
            self.state = _manifest_state(self.root)  # as read under the lock, for the commit
        except BaseException:
            self.lock.__exit__(None, None, None)
            raise
        return self

    def __exit__(self, *exc):
        if self.lock is not None:
            self.lock.__exit__(*exc)
            self.lock = None
        return False

    @property
    def store_id(self) -> str:
        return self.progress["store_id"]

    @property
    def version(self) -> int:
        return self.progress["store_version"]

    def done(self) -> dict:
        """{band: its record} of the bands committed already."""
        return {int(band): entry for band, entry in self.progress["bands"].items()}

    def commit_band(self, band: int, groups: dict, tile_stats: dict, spline_meta: dict, summary: dict):
        """Write band ``band``'s tiles (``groups``: {tile key: (levels, indices, values)},
        ``tile_stats``: {tile key: its manifest statistics}) and record it with ``summary``
        (what the manifest will need of it, JSON), atomically."""
        entries = []
        for key in sorted(groups):
            try:
                entries.append(write_tile_entry(self.root, key, groups[key], self.version,
                                                {**spline_meta, "store_id": self.store_id}, tile_stats[key]))
            except OSError as exc:
                raise StoreError(f"{self.root}: cannot write band {band}'s tiles: {fault_cause(exc)}; the bands "
                                 "recorded before are kept (resume the fit)") from None
            crash_point("during-band")
        try:
            fsync_dir(self.root / TILE_DIR)
        except OSError as exc:
            raise StoreError(f"{self.root}: cannot flush band {band}'s tiles: {fault_cause(exc)}") from None
        self.progress["bands"][str(band)] = {**summary, "tiles": entries}
        self._write_progress()
        crash_point("band-committed")

    def finish(self, manifest: dict):
        """Commit ``manifest`` (naming every band's tiles) as the store's new version and
        remove the progress record."""
        keep = [e["file"] for e in self.previous["tiles"]] if self.previous else []
        commit(self.root, manifest, keep, expect_state=self.state, signing_key=self.signing_key)
        try:
            (self.root / PROGRESS).unlink(missing_ok=True)
            fsync_dir(self.root)
        except OSError as exc:  # committed already: the next write removes it
            log.warning("%s: the progress record was not removed (%s)", self.root, fault_cause(exc))
