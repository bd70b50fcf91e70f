"""Writers under stress (issue 10 items 3, 5 and 6, store side): one writer at a time
enforced by the kernel, no lost update, faults (disk full, read-only file system, no
permission) as one message with the store intact, ``--out`` never deleting what it did
not write, and writers killed at every commit point.

Subprocesses stop themselves at a commit point (``GEOIDSPLINE_STOP_AT``: SIGSTOP) for a
real SIGKILL there, or die there (``GEOIDSPLINE_CRASH_AT``: ``os._exit``); nothing waits
on a timer. The exhaustive kill matrix is ``@pytest.mark.slow`` (``pytest --slow``).
"""

from __future__ import annotations

import errno
import hashlib
import json
import os
import pickle
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from conftest import stored_spline

import geoidspline
from geoidspline.api import build_store
from geoidspline.errors import StoreError
from geoidspline.fitting.parameters import FitParameters
from geoidspline.hierarchy.ambient import AmbientSpline
from geoidspline.sources.base import Provenance
from geoidspline.sources.grid import GeoidGrid
from geoidspline.sphere.region import Region
from geoidspline.store.format import MARKER, TILE_DIR
from geoidspline.store.reader import verify_store
from geoidspline.api.regional import update_store
from geoidspline.store.writer import StoreLock, commit, write_store

TESTS = str(Path(__file__).parent)

#: The store the concurrent updates share: few tiles (tile size 1), two levels.
RACE_REGION = Region(-48.0, -50.0, 48.0, 50.0)
RACE_PARAMS = FitParameters(h0=0.2, max_level=1, tolerance_m=0.05, tile_size=2.0)
#: Update k = p·ROUNDS + r of process p in round r replaces the geoid by base + OFFSET_M
#: in the 8°×8° region centred at (RACE_LATS[p], RACE_LONS[r]).
RACE_LATS = (-40.0, -24.0, -8.0, 8.0, 24.0, 40.0)
RACE_LONS = (-40.0, -20.0, 0.0, 20.0, 40.0)
PROCESSES, ROUNDS = 6, 5
OFFSET_M = 3.0

WRITE_POINTS = ("after-marker", "after-lock", "before-tiles", "during-tiles", "after-tiles", "before-manifest",
                "manifest-written", "after-manifest")


def snapshot(path: Path) -> dict:
    """Every file's sha256 but the lock file's (its pid is for messages only)."""
    return {p.relative_to(path).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(path).rglob("*")) if p.is_file() and p.name != ".lock"}


def _offset_grid(grid, name, offset=OFFSET_M):
    return GeoidGrid(grid.latitude, grid.longitude, grid.values + offset, Provenance(source=name, model=name))


@pytest.fixture(scope="module")
def race_base(tmp_path_factory, synthetic_grid):
    path = tmp_path_factory.mktemp("race") / "base"
    result, _ = build_store(synthetic_grid, path, RACE_REGION, RACE_PARAMS)
    return path, result


@pytest.fixture
def race_store(race_base, tmp_path):
    return Path(shutil.copytree(race_base[0], tmp_path / "store"))


# -- one writer, enforced by the kernel --------------------------------------------------

RACE_SCRIPT = textwrap.dedent("""
    import json, os, random, sys, time
    sys.path.insert(0, {tests!r})
    from conftest import make_synthetic_grid
    from test_store_faults import RACE_LATS, RACE_LONS, _offset_grid
    from geoidspline.errors import StoreError
    from geoidspline.sphere.region import Region
    import geoidspline.store.update as update
    from geoidspline.api.regional import update_store

    store, log, p, rounds = sys.argv[1], sys.argv[2], int(sys.argv[3]), int(sys.argv[4])

    def note(what):
        fd = os.open(log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        os.write(fd, f"{{what}} {{os.getpid()}}\\n".encode())
        os.close(fd)

    class LoggedLock(update.StoreLock):  # notes taking and releasing, while holding it
        def __enter__(self):
            super().__enter__()
            note("enter")
            return self

        def __exit__(self, *exc):
            note("exit")
            return super().__exit__(*exc)

    update.StoreLock = LoggedLock
    grid = make_synthetic_grid()
    rng = random.Random(p)
    refused = 0
    for r in range(rounds):
        k = p * rounds + r
        lat, lon = RACE_LATS[p], RACE_LONS[r]
        source = _offset_grid(grid, f"race-{{k}}")
        while True:
            try:
                record = update_store(store, source, Region(lat - 4, lon - 4, lat + 4, lon + 4),
                                      blend_width_km=300)
                break
            except StoreError as exc:
                if "another writer" not in str(exc):
                    raise
                refused += 1
                time.sleep(rng.uniform(0.02, 0.2))  # busy: try again (not a correctness wait)
        print(json.dumps({{"k": k, "version": record["store_version"], "refused": refused}}), flush=True)
""")


def test_concurrent_updates_never_overlap_and_none_is_lost(race_base, race_store, tmp_path):
    """Seen: an empty lock file was taken as stale by a second writer (two holders in 8 of
    40 rounds), and two updates 2 s apart both wrote version 2, losing the first. Here
    6 processes × 5 rounds of updates contend for one store: the lock is never held twice,
    every update that exited 0 is in the history, in order, and in the values."""
    log = tmp_path / "lock.log"
    script = RACE_SCRIPT.format(tests=TESTS)
    procs = [subprocess.Popen([sys.executable, "-c", script, str(race_store), str(log), str(p), str(ROUNDS)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for p in range(PROCESSES)]
    outputs = [proc.communicate(timeout=900) for proc in procs]
    for proc, (out, err) in zip(procs, outputs):
        assert proc.returncode == 0, err[-3000:]
    done, refused = {}, 0
    for out, _ in outputs:
        for line in out.splitlines():
            item = json.loads(line)
            done[item["k"]] = item["version"]
        refused += item["refused"]
    assert sorted(done) == list(range(PROCESSES * ROUNDS))
    assert refused > 0  # the writers did contend for the lock
    # never two holders: every "enter" is followed by the same process's "exit"
    events = log.read_text().split("\n")[:-1]
    assert len(events) == 2 * PROCESSES * ROUNDS
    for enter, leave in zip(events[::2], events[1::2]):
        assert enter.startswith("enter ") and leave == "exit " + enter.split()[1], (enter, leave)
    # every update in the history, one version each, none lost or repeated
    manifest = json.loads((race_store / "manifest.json").read_text())
    updates = [h for h in manifest["history"] if h["action"] == "update"]
    assert [h["store_version"] for h in updates] == list(range(2, 2 + PROCESSES * ROUNDS))
    assert {h["source"]: h["store_version"] for h in updates} == {f"race-{k}": v for k, v in done.items()}
    assert manifest["store_version"] == 1 + PROCESSES * ROUNDS
    assert verify_store(race_store) == []
    # and in the values: each update's offset at its region's centre
    store = geoidspline.open_store(race_store)
    base = race_base[1].spline
    for p, lat in enumerate(RACE_LATS):
        for r, lon in enumerate(RACE_LONS):
            change = store.undulation(lat, lon) - base.undulation(lat, lon)
            assert 0.5 * OFFSET_M < change < 1.5 * OFFSET_M, (p, r, change)


HOLD_SCRIPT = textwrap.dedent("""
    import fcntl, os, signal, sys
    from geoidspline.store.writer import StoreLock
    if sys.argv[2] == "raw":  # a holder that has not written its pid (yet)
        fd = os.open(os.path.join(sys.argv[1], ".lock"), os.O_RDWR | os.O_CREAT)
        fcntl.flock(fd, fcntl.LOCK_EX)
        os.kill(os.getpid(), signal.SIGSTOP)
    else:
        with StoreLock(sys.argv[1]):
            os.kill(os.getpid(), signal.SIGSTOP)
""")


def _stopped_holder(store, how="lock"):
    proc = subprocess.Popen([sys.executable, "-c", HOLD_SCRIPT, str(store), how], stderr=subprocess.PIPE)
    _, status = os.waitpid(proc.pid, os.WUNTRACED)
    assert os.WIFSTOPPED(status), proc.stderr.read()
    return proc


@pytest.mark.parametrize("how", ["lock", "raw"])
def test_a_killed_holder_releases_the_lock(race_store, how):
    (race_store / ".lock").write_text("")  # exists, holds no pid: not a lock by itself
    with StoreLock(race_store):
        pass
    holder = _stopped_holder(race_store, how)
    try:
        want = rf"another writer \(pid {holder.pid}\)" if how == "lock" else "another writer is writing"
        for _ in range(3):  # refused every time, and the lock file is never taken over
            with pytest.raises(StoreError, match=want), StoreLock(race_store):
                pass
        assert (race_store / ".lock").exists()
    finally:
        holder.send_signal(signal.SIGKILL)
        assert holder.wait(timeout=60) == -signal.SIGKILL
    with StoreLock(race_store):  # the kernel released it
        pass
    assert (race_store / ".lock").exists()


UPDATE_ONE = textwrap.dedent("""
    import sys
    sys.path.insert(0, {tests!r})
    from conftest import make_synthetic_grid
    from test_store_faults import _offset_grid
    from geoidspline.sphere.region import Region
    from geoidspline.api.regional import update_store
    update_store(sys.argv[1], _offset_grid(make_synthetic_grid(), sys.argv[2]), Region(-4, -4, 4, 4),
                 blend_width_km=300)
""")


def test_an_update_started_during_another_is_refused_not_lost(race_store, synthetic_grid):
    """Seen: update A read the manifest, B read it too, both wrote version 2. Now the
    manifest is read under the lock: B is refused while A runs, then applies after it."""
    env = dict(os.environ, GEOIDSPLINE_STOP_AT="before-tiles")  # A has read the manifest
    a = subprocess.Popen([sys.executable, "-c", UPDATE_ONE.format(tests=TESTS), str(race_store), "A"], env=env,
                         stderr=subprocess.PIPE)
    _, status = os.waitpid(a.pid, os.WUNTRACED)
    assert os.WIFSTOPPED(status), a.stderr.read()
    b_source = _offset_grid(synthetic_grid, "B")
    with pytest.raises(StoreError, match="another writer"):
        update_store(race_store, b_source, Region(-4, -4, 4, 4), blend_width_km=300)
    a.send_signal(signal.SIGCONT)
    assert a.wait(timeout=600) == 0, a.stderr.read()
    update_store(race_store, b_source, Region(-4, -4, 4, 4), blend_width_km=300)
    history = geoidspline.open_store(race_store).manifest["history"]
    assert [(h["action"], h["store_version"], h.get("source")) for h in history[1:]] == [
        ("update", 2, "A"), ("update", 3, "B")]
    assert verify_store(race_store) == []


def test_commit_never_replaces_a_manifest_changed_under_it(race_store):
    manifest = json.loads((race_store / "manifest.json").read_text())
    before = snapshot(race_store)
    with pytest.raises(StoreError, match="changed while this write ran"):
        commit(race_store, dict(manifest, store_version=2), expect_state="0" * 64)
    assert snapshot(race_store) == before


# -- faults are messages ------------------------------------------------------------------


@pytest.fixture
def tmpfs(tmp_path):
    """A fresh 4 MiB tmpfs (root only; skipped elsewhere)."""
    mount = tmp_path / "mnt"
    mount.mkdir()
    run = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4m", "tmpfs", str(mount)], capture_output=True, text=True)
    if run.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({run.stderr.strip() or 'not root'})")
    try:
        yield mount
    finally:
        subprocess.run(["umount", "-l", str(mount)], check=False)


def _fill(mount: Path, leave=2048):
    """Fill the file system but ``leave`` bytes."""
    st = os.statvfs(mount)
    free = st.f_bavail * st.f_frsize
    filler = mount / "filler"
    with open(filler, "wb") as fh:
        fh.write(b"\0" * max(0, free - leave))
    return filler


def _no_stray_files(store: Path, manifest: dict, keep=()):
    live = {e["file"] for e in manifest["tiles"]} | set(keep)
    stray = [p.name for p in (store / "tiles").iterdir() if f"tiles/{p.name}" not in live]
    assert not stray and not (store / "manifest.json.tmp").exists(), stray


def test_disk_full_during_an_update(race_base, tmpfs, synthetic_grid):
    store = Path(shutil.copytree(race_base[0], tmpfs / "store"))
    before, manifest = snapshot(store), json.loads((store / "manifest.json").read_text())
    filler = _fill(tmpfs)
    with pytest.raises(StoreError) as err:
        update_store(store, _offset_grid(synthetic_grid, "new"), Region(-4, -4, 4, 4), blend_width_km=300)
    message = str(err.value)
    assert "no space left on the device (disk full)" in message and str(store) in message
    assert "ermission" not in message and "version 1 is unchanged" in message
    assert snapshot(store) == before and verify_store(store) == []
    _no_stray_files(store, manifest)
    filler.unlink()
    assert update_store(store, _offset_grid(synthetic_grid, "new"), Region(-4, -4, 4, 4))["store_version"] == 2


def test_disk_full_during_an_overwrite_and_a_first_write(race_base, tmpfs):
    store = Path(shutil.copytree(race_base[0], tmpfs / "store"))
    before, manifest = snapshot(store), json.loads((store / "manifest.json").read_text())
    result, provenance = race_base[1], Provenance(source="again")
    filler = _fill(tmpfs)
    with pytest.raises(StoreError, match=r"no space left on the device .*version 1 is unchanged"):
        write_store(store, result, provenance, overwrite=True)
    assert snapshot(store) == before and verify_store(store) == []
    _no_stray_files(store, manifest)
    with pytest.raises(StoreError, match=r"no space left on the device .*no store was written") as err:
        write_store(tmpfs / "new", result, provenance)
    assert str(tmpfs / "new") in str(err.value)
    filler.unlink()
    write_store(tmpfs / "new", result, provenance)  # nothing to clear: no overwrite needed
    assert verify_store(tmpfs / "new") == []


def test_a_read_only_file_system(race_base, tmpfs, synthetic_grid):
    store = Path(shutil.copytree(race_base[0], tmpfs / "store"))
    before = snapshot(store)
    subprocess.run(["mount", "-o", "remount,ro", str(tmpfs)], check=True)
    with pytest.raises(StoreError, match=r"read-only \(read-only file system\)") as err:
        update_store(store, _offset_grid(synthetic_grid, "new"), Region(-4, -4, 4, 4))
    assert str(store) in str(err.value)
    with pytest.raises(StoreError, match="read-only file system"):
        write_store(store, race_base[1], Provenance(source="again"), overwrite=True)
    with pytest.raises(StoreError, match="read-only file system"):
        write_store(tmpfs / "new", race_base[1], Provenance(source="again"))
    assert snapshot(store) == before and verify_store(store) == []
    stored = stored_spline(race_base[1].spline, store)
    assert geoidspline.open_store(store).undulation(0.0, 0.0) == stored.undulation(0.0, 0.0)


def _inject(monkeypatch, target, fault, after=0):
    """Make ``target`` (a writer-module attribute) raise ``fault`` from its (after+1)-th call."""
    import geoidspline.store.writer as writer

    real = getattr(writer, target)
    calls = []

    def failing(*args, **kwargs):
        calls.append(1)
        if len(calls) > after:
            raise fault
        return real(*args, **kwargs)

    monkeypatch.setattr(writer, target, failing)


@pytest.mark.parametrize("target, fault, words", [
    ("_write_all", OSError(errno.ENOSPC, "No space left on device"), "no space left on the device"),
    ("_write_tile", OSError(errno.ENOSPC, "No space left on device"), "no space left on the device"),
    ("_write_tile", OSError(errno.EDQUOT, "Disk quota exceeded"), "disk quota exceeded"),
    ("_write_tile", PermissionError(errno.EACCES, "Permission denied"), "permission denied"),
    ("_write_tile", OSError(errno.EIO, "Input/output error"), "input/output error"),
    ("write_tile_file", RuntimeError("NetCDF: HDF error"), "no space left on the device"),
    ("write_tile_file", MemoryError(), "out of memory"),
], ids=["enospc-manifest", "enospc-tile", "edquot", "eacces", "eio", "netcdf-hdf-error-disk-full", "memory"])
def test_injected_write_faults(race_base, race_store, monkeypatch, target, fault, words):
    """One StoreError naming the store, the file and the cause; the files of the failed
    write removed; the previous version intact."""
    before, manifest = snapshot(race_store), json.loads((race_store / "manifest.json").read_text())
    if target == "write_tile_file":  # netCDF says only "HDF error": the file system says why
        import geoidspline.store.writer as writer

        full = os.statvfs_result((4096, 4096, 1000, 0, 0, 1000, 10, 10, 0, 255))
        monkeypatch.setattr(writer.os, "statvfs", lambda path: full)
    _inject(monkeypatch, target, fault, after=2 if target != "_write_all" else 0)
    with pytest.raises(StoreError, match=words) as err:
        write_store(race_store, race_base[1], Provenance(source="again"), overwrite=True)
    message = str(err.value)
    assert str(race_store) in message and "version 1 is unchanged" in message
    assert words == "permission denied" or "ermission" not in message
    monkeypatch.undo()
    assert snapshot(race_store) == before and verify_store(race_store) == []
    _no_stray_files(race_store, manifest)


# -- --out never deletes what it did not write ----------------------------------------------


def test_a_directory_of_user_files_is_never_taken(race_base, tmp_path):
    """Seen: a directory holding only the user's tiles/notes.txt was taken as the store
    and notes.txt deleted."""
    out = tmp_path / "out"
    (out / "tiles").mkdir(parents=True)
    (out / "tiles" / "notes.txt").write_text("my notes")
    before = snapshot(out)
    for overwrite in (False, True):
        with pytest.raises(StoreError, match="not empty and is not a geoidspline store"):
            write_store(out, race_base[1], Provenance(source="x"), overwrite=overwrite)
        assert snapshot(out) == before and sorted(p.name for p in out.iterdir()) == ["tiles"]


def test_a_first_write_in_progress_is_named_as_another_writer_not_leftovers(race_base, tmp_path):
    """Seen: two geoid-fit into one new directory; the second, at its write, found the
    first's tiles in progress and called them leftovers of a write that did not finish,
    to be cleared with --overwrite. While another writer holds the lock it names that
    writer, with or without overwrite, and nothing changes; once the holder is gone the
    same files are leftovers again."""
    out = tmp_path / "out"
    (out / TILE_DIR).mkdir(parents=True)
    (out / MARKER).write_text("")
    (out / TILE_DIR / ".t+0000-0003-0001.v1.gst.51xqddvn.tmp").write_bytes(b"a tile being written")
    holder = _stopped_holder(out)
    try:
        before = snapshot(out)
        for overwrite in (False, True):
            with pytest.raises(StoreError, match=rf"another writer \(pid {holder.pid}\) is writing this store"):
                write_store(out, race_base[1], Provenance(source="x"), overwrite=overwrite)
            assert snapshot(out) == before
    finally:
        holder.send_signal(signal.SIGKILL)
        assert holder.wait(timeout=60) == -signal.SIGKILL
    with pytest.raises(StoreError, match="leftovers of a store write.*overwrite"):
        write_store(out, race_base[1], Provenance(source="x"))
    write_store(out, race_base[1], Provenance(source="x"), overwrite=True)
    assert verify_store(out) == []


def test_old_tiles_without_a_manifest_need_overwrite_and_keep_the_rest(race_base, tmp_path):
    """Seen: a directory with old tiles but no manifest was overwritten without --overwrite."""
    out = tmp_path / "out"
    (out / "tiles").mkdir(parents=True)
    old_tile = out / "tiles" / "t+0005+0005+0005.v3.nc"
    old_tile.write_bytes(b"an old tile of some store")
    (out / "README").write_text("mine")
    (out / "tiles" / "mine.txt").write_text("mine too")
    before = snapshot(out)
    with pytest.raises(StoreError, match="leftovers of a store write.*overwrite"):
        write_store(out, race_base[1], Provenance(source="x"))
    assert snapshot(out) == before
    write_store(out, race_base[1], Provenance(source="x"), overwrite=True)
    assert not old_tile.exists()  # a name the store format owns
    assert (out / "README").read_text() == "mine" and (out / "tiles" / "mine.txt").read_text() == "mine too"
    assert verify_store(out) == []


def test_overwriting_a_store_keeps_the_users_files_in_it(race_base, race_store):
    (race_store / "notes.txt").write_text("mine")
    (race_store / "tiles" / "mine.txt").write_text("mine too")
    (race_store / "tiles" / "t+0000+0000+0000.v1.nc.bak").write_text("not a tile name")
    for _ in range(2):  # the second overwrite removes the first version's tiles
        write_store(race_store, race_base[1], Provenance(source="again"), overwrite=True)
    assert (race_store / "notes.txt").read_text() == "mine"
    assert (race_store / "tiles" / "mine.txt").read_text() == "mine too"
    assert (race_store / "tiles" / "t+0000+0000+0000.v1.nc.bak").exists()
    assert not [p for p in (race_store / "tiles").glob("*.v1.gst")]


def test_a_foreign_manifest_is_never_replaced(race_base, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "manifest.json").write_text(json.dumps({"name": "another tool's manifest"}))
    for overwrite in (False, True):
        with pytest.raises(StoreError, match="not a geoidspline manifest"):
            write_store(out, race_base[1], Provenance(source="x"), overwrite=overwrite)
    assert json.loads((out / "manifest.json").read_text()) == {"name": "another tool's manifest"}


# -- writers killed at every commit point ----------------------------------------------------

WRITE_SCRIPT = textwrap.dedent("""
    import pickle, sys, types
    from geoidspline.store.writer import write_store
    with open(sys.argv[1], "rb") as fh:
        payload = pickle.load(fh)
    write_store(sys.argv[2], types.SimpleNamespace(**payload["result"]), payload["provenance"],
                overwrite=sys.argv[3] == "1")
""")


@pytest.fixture(scope="module")
def payload(race_base, tmp_path_factory):
    """The fit, pickled without the fitting package (its subprocesses stay light)."""
    result = race_base[1]
    spline = AmbientSpline(list(result.spline.levels))
    fields = dict(spline=spline, parameters=result.parameters, region=result.region, coverage=result.coverage,
                  node_directions=result.node_directions, node_errors=result.node_errors,
                  converged=result.converged, seconds=result.seconds, levels=[], method=result.method)
    path = tmp_path_factory.mktemp("payload") / "fit.pickle"
    with open(path, "wb") as fh:
        pickle.dump({"result": fields, "provenance": Provenance(source="rewrite")}, fh)
    return path


def _kill_writers(payload, targets, points, overwrite, kill):
    """Start one writer per (target, point), each dying at its point; wait for all."""
    procs = []
    for target, point in zip(targets, points):
        var = "GEOIDSPLINE_CRASH_AT" if kill == "exit" else "GEOIDSPLINE_STOP_AT"
        env = dict(os.environ, **{var: point})
        procs.append(subprocess.Popen([sys.executable, "-c", WRITE_SCRIPT, str(payload), str(target),
                                       "1" if overwrite else "0"], env=env, stderr=subprocess.PIPE))
    for proc in procs:
        if kill == "exit":
            assert proc.wait(timeout=600) == 77, proc.stderr.read()
        else:
            _, status = os.waitpid(proc.pid, os.WUNTRACED)
            assert os.WIFSTOPPED(status), proc.stderr.read()
            proc.send_signal(signal.SIGKILL)
            assert proc.wait(timeout=60) == -signal.SIGKILL


def _check_overwrite_survivors(race_base, payload, stores, points):
    lat, lon = np.array([0.0, 30.0, -45.0]), np.array([0.0, 45.0, -45.0])
    for store, point in zip(stores, points):
        want = stored_spline(race_base[1].spline, store).undulation(lat, lon)
        manifest = json.loads((store / "manifest.json").read_text())
        assert manifest["store_version"] == (2 if point == "after-manifest" else 1), point
        assert verify_store(store) == [], point
        np.testing.assert_array_equal(geoidspline.open_store(store).undulation(lat, lon), want)
        assert (store / "notes.txt").read_text() == "mine" and (store / "tiles" / "mine.txt").exists(), point
        write_store(store, race_base[1], Provenance(source="next"), overwrite=True)  # the next writer
        assert verify_store(store) == [] and (store / "tiles" / "mine.txt").exists()


def _check_first_write_survivors(race_base, targets, points):
    for target, point in zip(targets, points):
        if point == "after-manifest":
            assert verify_store(target) == []
            continue
        with pytest.raises(StoreError, match="not a geoidspline store"):
            geoidspline.open_store(target)
        leftovers = point in ("during-tiles", "after-tiles", "before-manifest", "manifest-written")
        if leftovers:  # recognised: refused without overwrite, cleared with it
            with pytest.raises(StoreError, match="leftovers"):
                write_store(target, race_base[1], Provenance(source="next"))
        write_store(target, race_base[1], Provenance(source="next"), overwrite=leftovers)
        assert verify_store(target) == [], point
        assert sorted(p.name for p in target.iterdir()) == [".geoidspline-store", ".lock", "manifest.json", "tiles"]


def _overwrite_targets(race_base, tmp_path, points, kill):
    stores = []
    for point in points:
        store = Path(shutil.copytree(race_base[0], tmp_path / f"{kill}-{point}"))
        (store / "notes.txt").write_text("mine")  # the user's files in the store
        (store / "tiles" / "mine.txt").write_text("mine too")
        stores.append(store)
    return stores


@pytest.mark.parametrize("kill", ["exit", "sigkill"])
def test_an_overwrite_killed_at_each_commit_point(race_base, payload, tmp_path, kill, request):
    """At every commit point (os._exit, or a real SIGKILL where the writer stopped): the
    store is the old or the new version, opens and verifies, the user's files are there,
    and the next writer succeeds."""
    points = WRITE_POINTS if (kill == "exit" or request.config.getoption("--slow")) else ("after-lock", "during-tiles", "manifest-written")
    stores = _overwrite_targets(race_base, tmp_path, points, kill)
    _kill_writers(payload, stores, points, overwrite=True, kill=kill)
    _check_overwrite_survivors(race_base, payload, stores, points)


@pytest.mark.parametrize("kill", ["exit", pytest.param("sigkill", marks=pytest.mark.slow)])
def test_a_first_write_killed_at_each_commit_point(race_base, payload, tmp_path, kill):
    """Seen: a fit killed between writing manifest.json.tmp and the rename left a
    directory that even --overwrite refused."""
    targets = [tmp_path / f"{kill}-{point}" for point in WRITE_POINTS]
    _kill_writers(payload, targets, WRITE_POINTS, overwrite=False, kill=kill)
    _check_first_write_survivors(race_base, targets, WRITE_POINTS)
