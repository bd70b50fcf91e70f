"""The tile store format: names, the manifest and its checks, tile files.

Layout of a store directory::

    STORE/.geoidspline-store                 marker, written first: this directory is a store
    STORE/.lock                              the writers' lock file (never removed)
    STORE/manifest.json                      the commit point: lists the live tile files
    STORE/manifest.json.tmp                  the next manifest, before its atomic rename
    STORE/tiles/t+0001-0002+0000.v1.gst      one file per tile and store version (.nc: format 1)

These are the only names a store owns: a writer never removes any other file.

A tile file holds every coefficient, of every level, whose B-spline support centre
lies in the tile's cube. Format 2 (``.gst``, written now): runs of keys and quantised
values, see :mod:`geoidspline.store.codec`. Format 1 (``.nc``, still read, and written
by :func:`write_tile_file` with ``format_version=1``): netCDF4 variables ``index``
(coefficient, axis: the B-spline's integer position on its level's grid), ``level``
and ``value`` (metres). Readers tell them apart by the file's first bytes. Either
records what it holds (the tile, the store it belongs to, the spline's order, h0 and
tile size: netCDF attributes, or the format-2 header), and a reader refuses a tile
whose record or contents disagree with its manifest entry (a tile copied from another
store, or two tiles swapped, even when the manifest's sha256 was edited to match).

The manifest is checked against a schema written as code (:func:`validate_manifest`;
a schema library would not name the rule as plainly, nor bound nesting, sizes and
numbers before use); format 2 adds the coverage record, the store id, an integrity
digest of the manifest itself and the quantisation step of its ``.gst`` tiles.
Format 1 stores keep opening (their coverage is their region).
"""

from __future__ import annotations

import datetime as _dt
import errno
import hashlib
import json
import math
import os
import re
import stat
import threading
from pathlib import Path

import numpy as np

from .._files import atomic_path, atomic_write
from .._version import __version__  # noqa: F401 (recorded in manifests)
from ..bspline.keys import pack_keys, unpack_keys
from ..bspline.level import cube_of_support_centres
from ..errors import StoreCorruptError, StoreError, StoreFileMissingError
from .codec import TILE_FORMAT, decode_tile, encode_tile, is_coded_tile, runs_of

FORMAT_NAME = "geoidspline-tile-store"


#: The format this geoidspline writes; it reads every format from 1 to this one.
FORMAT_VERSION = 4


MANIFEST = "manifest.json"


MANIFEST_TMP = MANIFEST + ".tmp"


#: The detached signature of store version N (:mod:`geoidspline.store.signing`).
SIGNATURE_NAME = re.compile(re.escape(MANIFEST) + r"\.v([1-9]\d{0,9})\.sig")


TILE_DIR = "tiles"


LOCK = ".lock"


#: A fit written band by band records the bands it has committed here until its manifest
#: is written (:class:`geoidspline.store.writer.BandedWrite`); a store directory holding it
#: is an unfinished fit, which ``--resume`` continues.
PROGRESS = "fit-progress.json"


#: The temporary name :func:`geoidspline._files.atomic_path` writes the progress record under.
PROGRESS_TMP_NAME = re.compile(r"\.fit-progress\.json\.[A-Za-z0-9_]+\.tmp")


#: Written first into a new store directory: the directory is a store (or one being written).
MARKER = ".geoidspline-store"


#: A tile file's name: its tile (i, j, k) and the store version that wrote it.
TILE_NAME = re.compile(r"t([+-]\d{4,7})([+-]\d{4,7})([+-]\d{4,7})\.v([1-9]\d{0,9})\.(nc|gst)")


#: A tile file being written (:func:`geoidspline._files.atomic_path` temporaries).
TILE_TMP_NAME = re.compile(r"\.t[+-]\d{4,7}[+-]\d{4,7}[+-]\d{4,7}\.v\d{1,10}\.(nc|gst)\.[A-Za-z0-9_]+\.tmp")


#: Largest manifest read (bytes): a global store at 1' lists ~10^5 tiles in ~30 MB.
MAX_MANIFEST_BYTES = 64 * 1024 * 1024


#: Largest tile file read (bytes).
MAX_TILE_BYTES = 4 * 1024**3


#: Deepest nesting of JSON containers in a manifest (the writer's deepest is 5).
MAX_MANIFEST_DEPTH = 32


#: Largest |coefficient| (metres) a tile may hold: geoid undulations are within ±110 m,
#: their B-spline coefficients of the same order.
MAX_COEFFICIENT_M = 1.0e5


def tile_name(tile, version, format_version=FORMAT_VERSION):
    i, j, k = (int(v) for v in tile)
    return f"t{i:+05d}{j:+05d}{k:+05d}.v{version}.{'nc' if format_version == 1 else 'gst'}"


def is_store_file(relative: str) -> bool:
    """Whether a path relative to a store directory is one of the names the format owns."""
    if relative in (MANIFEST, MANIFEST_TMP, LOCK, MARKER, PROGRESS) or SIGNATURE_NAME.fullmatch(relative) \
            or PROGRESS_TMP_NAME.fullmatch(relative):
        return True
    head, _, name = relative.partition("/")
    return head == TILE_DIR and "/" not in name and bool(TILE_NAME.fullmatch(name) or TILE_TMP_NAME.fullmatch(name))


def utc_now():
    return _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat()


def error_stats(errors):
    errors = np.asarray(errors, dtype=float)
    if errors.size == 0:
        return {"count": 0, "max_error_m": None, "rms_error_m": None, "p99_error_m": None}
    absolute = np.abs(errors)
    return {
        "count": int(errors.size),
        "max_error_m": float(absolute.max()),
        "rms_error_m": float(np.sqrt(np.mean(errors**2))),
        "p99_error_m": float(np.percentile(absolute, 99)),
    }


#: What a format-2 tile's header records of the store beside its tile (format 1: attributes).
TILE_RECORD = ("store_id", "store_version", "order", "h0", "tile_size")


def write_tile_file(path, tile, levels, indices, values, attrs, format_version=FORMAT_VERSION):
    """Write one tile file; format 2 quantises with ``attrs["value_step_m"]``."""
    if format_version >= 2:
        record = {key: attrs[key] for key in TILE_RECORD if attrs.get(key) is not None}
        atomic_write(path, encode_tile(tile, levels, indices, values, attrs["value_step_m"], record,
                                       min(int(format_version), TILE_FORMAT)))
        return
    import netCDF4

    tile = np.asarray(tile, dtype=np.int64)
    size = float(attrs["tile_size"])
    with atomic_path(path) as tmp, netCDF4.Dataset(tmp, "w", format="NETCDF4") as ds:
        ds.setncattr("Conventions", "CF-1.8")
        ds.setncattr("title", "geoidspline ambient B-spline tile")
        ds.setncattr("format", FORMAT_NAME)
        ds.setncattr("format_version", 1)
        ds.setncattr("tile", tile.astype(np.int32))
        # the cube [tile·size, (tile+1)·size) holding every coefficient's support centre
        ds.setncattr("support_centre_min", tile * size)
        ds.setncattr("support_centre_max", (tile + 1) * size)
        ds.setncattr("levels", np.unique(levels).astype(np.int32))
        ds.setncattr("coefficients", np.int64(len(values)))
        for key, value in attrs.items():
            if value is not None and key != "value_step_m":
                ds.setncattr(key, value)
        ds.createDimension("coefficient", len(values))
        ds.createDimension("axis", 3)
        var = ds.createVariable("index", "i4", ("coefficient", "axis"), zlib=True, complevel=4)
        var.long_name = "integer position (i, j, k) of the B-spline on its level's grid: support [k h, (k + order) h) per axis"
        var.units = "1"
        var[:] = indices.astype(np.int32)
        var = ds.createVariable("level", "i1", ("coefficient",), zlib=True, complevel=4)
        var.long_name = "overlay level; grid spacing h = h0 / 2**level on the unit sphere"
        var.units = "1"
        var[:] = levels.astype(np.int8)
        var = ds.createVariable("value", "f8", ("coefficient",), zlib=True, complevel=4)
        var.long_name = "B-spline coefficient of the geoid undulation"
        var.units = "m"
        var[:] = values


def size_problem(path, entry, size) -> str | None:
    """The one message for a tile file whose size differs from its manifest entry, or None."""
    if size == entry["bytes"]:
        return None
    how = "truncated" if size < entry["bytes"] else "altered"
    return f"{path}: tile {entry['tile']} is {size} bytes, the manifest says {entry['bytes']} ({how})"


def _tile_dir_fd(root: Path):
    """A descriptor of STORE/tiles, refusing a symlink or anything but a directory."""
    path = Path(root) / TILE_DIR
    try:
        return os.open(path, os.O_RDONLY | os.O_DIRECTORY | os.O_NOFOLLOW | os.O_CLOEXEC)
    except FileNotFoundError:
        raise StoreFileMissingError(f"{path}: the store's tile directory is missing") from None
    except OSError as exc:
        if exc.errno in (errno.ELOOP, errno.ENOTDIR):
            raise StoreCorruptError(f"{path}: not a directory of the store (a symbolic link or a file)") from None
        raise StoreError(f"{path}: cannot be opened ({exc.strerror})") from None


def _file_kind(mode) -> str:
    for test, name in ((stat.S_ISLNK, "a symbolic link"), (stat.S_ISFIFO, "a FIFO"), (stat.S_ISCHR, "a device"),
                       (stat.S_ISBLK, "a device"), (stat.S_ISDIR, "a directory"), (stat.S_ISSOCK, "a socket")):
        if test(mode):
            return name
    return "not a regular file"


class TileDirectory:
    """STORE/tiles opened once: tile files are looked up in it by plain name only,
    never following a symbolic link, and must be regular files."""

    def __init__(self, root: Path):
        self.root = Path(root)
        self.fd = _tile_dir_fd(root)

    def close(self):
        if self.fd is not None:
            os.close(self.fd)
            self.fd = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False

    def _name(self, entry) -> str:
        return entry["file"].split("/", 1)[1]  # "tiles/NAME", checked by validate_manifest

    def stat_problem(self, entry) -> str | None:
        """None when the tile file is a regular file of the manifest's size, else the problem."""
        path = self.root / entry["file"]
        try:
            st = os.stat(self._name(entry), dir_fd=self.fd, follow_symlinks=False)
        except FileNotFoundError:
            return f"{path}: tile {entry['tile']} is missing"
        except OSError as exc:
            return f"{path}: tile {entry['tile']} cannot be read ({exc.strerror})"
        if not stat.S_ISREG(st.st_mode):
            return f"{path}: tile {entry['tile']} is {_file_kind(st.st_mode)}, not a regular file"
        return size_problem(path, entry, st.st_size)

    def read(self, entry) -> bytes:
        """The bytes of a tile file, after checking it is a regular file of the manifest's size."""
        path = self.root / entry["file"]
        flags = os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC  # a FIFO must not block
        try:
            fd = os.open(self._name(entry), flags, dir_fd=self.fd)
        except FileNotFoundError:
            raise
        except OSError as exc:
            if exc.errno == errno.ELOOP:
                raise StoreCorruptError(f"{path}: tile {entry['tile']} is a symbolic link, not a regular file") from None
            raise StoreError(f"{path}: tile {entry['tile']} cannot be read ({exc.strerror})") from None
        try:
            st = os.fstat(fd)
            if not stat.S_ISREG(st.st_mode):
                raise StoreCorruptError(f"{path}: tile {entry['tile']} is {_file_kind(st.st_mode)}, not a regular file")
            problem = size_problem(path, entry, st.st_size)
            if problem:
                raise StoreCorruptError(problem)
            data = _read_up_to(fd, st.st_size)
        except OSError as exc:
            raise StoreError(f"{path}: tile {entry['tile']} cannot be read ({exc.strerror})") from None
        finally:
            os.close(fd)
        if len(data) != entry["bytes"]:
            raise StoreCorruptError(size_problem(path, entry, len(data)))
        return data


def read_tile_levels(path, entry, data, manifest):
    """{level: (sorted packed keys, values in metres)} of a tile file's bytes ``data``
    (either format; format 2 decodes straight to keys, without index triples), checked
    as :func:`read_tile_file` checks it."""
    if not is_coded_tile(data):
        indices, levels, values = read_tile_file(path, entry, data, manifest)
        out = {}
        for level in np.unique(levels):
            sel = levels == level
            keys = pack_keys(indices[sel])
            order = np.argsort(keys)
            out[int(level)] = (keys[order], values[sel][order])
        return out
    refuse = _refusal(path, entry)
    try:
        header, out = decode_tile(data)
    except ValueError as exc:
        raise refuse(str(exc)) from None
    found = header.get("tile")
    found = [int(v) for v in found] if isinstance(found, list) and len(found) == 3 else found
    _check_record(refuse, entry, manifest, found, header)
    count = sum(v[0].size for v in out.values())
    if count != entry["coefficients"]:
        raise refuse(f"holds {count} coefficients, the manifest says {entry['coefficients']}")
    step = manifest["spline"].get("value_step_m")
    if step is not None and not steps_nest(float(header["value_step_m"]), float(step)):
        raise refuse(f"was quantised with step {header['value_step_m']} m, not the manifest's {step} m "
                     f"or a power-of-two fraction of it")
    if out:
        # the place of a run's first and last coefficient is the place of all of it: a
        # run varies k alone, and the cube of a support centre grows with k
        ends = {lv: _run_ends(k) for lv, (k, _) in out.items()}
        indices = np.concatenate([unpack_keys(k) for k in ends.values()])
        levels = np.concatenate([np.full(k.size, lv, np.int64) for lv, k in ends.items()])
        values = np.concatenate([v for _, v in out.values()])
        _check_contents(refuse, entry, manifest, indices, levels, values)
    return out


def read_tile_file(path, entry, data, manifest):
    """(indices (M, 3), levels (M,), values (M,)) of a tile file's bytes ``data`` (either format).

    Refuses (:class:`StoreCorruptError` naming the file) a tile whose record or
    contents disagree with its manifest entry: another tile, another store, another
    spline (order, h0, tile size), another number of coefficients or levels, a
    coefficient whose support centre is not in the tile's cube, a non-finite or
    implausibly large coefficient.
    """
    if data is None:
        data = Path(path).read_bytes()
    if is_coded_tile(data):
        out = read_tile_levels(path, entry, data, manifest)
        if not out:
            return np.zeros((0, 3), np.int64), np.zeros(0, np.int64), np.zeros(0)
        indices = np.concatenate([unpack_keys(k) for k, _ in out.values()])
        levels = np.concatenate([np.full(k.size, lv, np.int64) for lv, (k, _) in out.items()])
        values = np.concatenate([v for _, v in out.values()])
        return indices, levels, values
    return _read_tile_v1(path, entry, data, manifest)


def steps_nest(tile_step: float, store_step: float) -> bool:
    """A tile's quantisation step is the store's or ``store_step / 2**k`` (a regional
    update writes its tiles with a finer step where its tolerance needs it; every
    multiple of the store's step is a multiple of those, so the untouched coefficients
    keep their values bit for bit)."""
    if not (0.0 < tile_step <= store_step):
        return False
    ratio = store_step / tile_step
    k = round(math.log2(ratio))
    return 0 <= k <= 30 and ratio == 2.0 ** k


def _refusal(path, entry):
    tile = [int(v) for v in entry["tile"]]

    def refuse(rule):
        return StoreCorruptError(f"{path}: tile {tile} {rule}")
    return refuse


def _check_record(refuse, entry, manifest, found, record):
    """The tile, store and spline a tile file records (netCDF attributes or the format-2
    header) against its manifest entry."""
    meta = manifest["spline"]
    if found != [int(v) for v in entry["tile"]]:
        raise refuse(f"holds tile {found}: it is not this tile's file (moved, swapped or copied)")
    store_id = manifest.get("store_id")
    if store_id is not None and record.get("store_id") != store_id:
        raise refuse("belongs to another store (its store_id differs from the manifest's)")
    for key in ("order", "h0", "tile_size"):
        want = float(meta[key])
        try:
            bad = key in record and float(record[key]) != want
        except (TypeError, ValueError):
            bad = True
        if bad:
            raise refuse(f"was written for {key} {record[key]}, the manifest says {want}")


def _run_ends(keys):
    """The first and last key of every run of consecutive keys (sorted keys)."""
    starts, lengths = runs_of(keys)
    return np.concatenate([keys[starts], keys[starts + lengths - 1]])


def _check_contents(refuse, entry, manifest, indices, levels, values):
    """Levels, values and the place of every coefficient of a tile against its manifest entry."""
    meta = manifest["spline"]
    order, h0, tile_size = int(meta["order"]), float(meta["h0"]), float(meta["tile_size"])
    present = sorted(set(np.unique(levels).tolist()))
    if present != list(entry["levels"]):
        raise refuse(f"holds levels {present}, the manifest says {entry['levels']}")
    known = {int(lv["level"]) for lv in meta["levels"]}
    if not set(present) <= known:
        raise refuse(f"holds levels {present}, the store has {sorted(known)}")
    if not np.all(np.isfinite(values)) or np.any(np.abs(values) > MAX_COEFFICIENT_M):
        raise refuse(f"holds coefficients that are not finite or beyond ±{MAX_COEFFICIENT_M:g} m")
    # every coefficient's support centre lies in this tile's cube (the writer's grouping)
    centre_tile = np.empty_like(indices)
    for level in present:
        sel = levels == level
        centre_tile[sel] = cube_of_support_centres(indices[sel], h0 / 2.0**level, order, tile_size)
    wrong = np.any(centre_tile != np.asarray([int(v) for v in entry["tile"]]), axis=1)
    if wrong.any():
        raise refuse(f"holds {int(wrong.sum())} coefficients whose support centre lies outside the tile's cube "
                     f"(first in tile {centre_tile[wrong][0].tolist()}): the file is in the wrong place")


#: netCDF4/HDF5 as built by the netCDF4 wheels is not thread-safe (a store's tiles are
#: decoded on several threads): one format-1 tile is read at a time.
_NETCDF_LOCK = threading.Lock()


def _read_tile_v1(path, entry, data, manifest):
    """A format-1 (netCDF4) tile file's (indices, levels, values), checked."""
    with _NETCDF_LOCK:
        indices, levels, values = _read_netcdf_tile(path, entry, data, manifest)
    _check_contents(_refusal(path, entry), entry, manifest, indices, levels, values)
    return indices, levels, values


def _read_netcdf_tile(path, entry, data, manifest):
    """A format-1 tile file's arrays, its record checked."""
    import netCDF4

    refuse = _refusal(path, entry)
    try:
        ds = netCDF4.Dataset(str(path), "r", memory=data)
    except (OSError, RuntimeError, ValueError, MemoryError) as exc:
        raise refuse(f"cannot be read as a tile file ({exc})") from None
    try:
        with ds:
            ds.set_auto_mask(False)
            attrs = ds.__dict__  # every global attribute in one call
            if attrs.get("format") != FORMAT_NAME:
                raise refuse("is not a geoidspline tile file (no format attribute)")
            found = [int(v) for v in np.atleast_1d(attrs["tile"])] if "tile" in attrs else None
            _check_record(refuse, entry, manifest, found, attrs)
            dims = ds.dimensions
            if "coefficient" not in dims or "axis" not in dims or len(dims["axis"]) != 3:
                raise refuse("lacks the coefficient/axis dimensions")
            count = len(dims["coefficient"])
            if count != entry["coefficients"]:  # checked before reading the arrays
                raise refuse(f"holds {count} coefficients, the manifest says {entry['coefficients']}")
            for name, shape in (("index", (count, 3)), ("level", (count,)), ("value", (count,))):
                if name not in ds.variables or tuple(ds[name].shape) != shape:
                    raise refuse(f"lacks the variable {name!r} of shape {shape}")
            indices = np.asarray(ds["index"][:], dtype=np.int64).reshape(-1, 3)
            levels = np.asarray(ds["level"][:], dtype=np.int64)
            values = np.asarray(ds["value"][:], dtype=np.float64)
    except StoreCorruptError:
        raise
    except (OSError, KeyError, IndexError, RuntimeError, ValueError, TypeError, AttributeError) as exc:
        raise refuse(f"cannot be read as a tile file ({exc})") from None
    return indices, levels, values


# -- the manifest ---------------------------------------------------------------------


def _reject_constant(name):
    raise ValueError(f"{name} is not a JSON number")


def _finite_float(text):
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number {text[:40]} is out of range")
    return value


def parse_manifest(path, text: bytes) -> dict:
    """The manifest's JSON object, or :class:`StoreCorruptError` naming the file and the rule."""
    try:
        decoded = text.decode("utf-8")
        manifest = json.loads(decoded, parse_constant=_reject_constant, parse_float=_finite_float)
    except UnicodeDecodeError as exc:
        raise StoreCorruptError(f"{path}: manifest is not valid JSON (not UTF-8 text: {exc.reason})") from None
    except RecursionError:
        raise StoreCorruptError(f"{path}: manifest is not valid JSON (nested too deeply)") from None
    except ValueError as exc:  # JSONDecodeError, NaN/Infinity, huge numbers
        raise StoreCorruptError(f"{path}: manifest is not valid JSON ({str(exc)[:200]})") from None
    if not isinstance(manifest, dict):
        raise StoreCorruptError(f"{path}: manifest is not a JSON object")
    return manifest


def _read_up_to(fd: int, size: int) -> bytes:
    """Up to ``size`` bytes of an open file, fewer if it ends first (the caller compares
    the length with what it expects); OSError is the caller's to name."""
    chunks, left = [], size
    while left > 0:
        chunk = os.read(fd, min(left, 1 << 24))
        if not chunk:
            break
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def read_manifest_bytes(root: Path) -> bytes:
    """The bytes of STORE/manifest.json: a regular file (no symlink, FIFO or device) of at
    most :data:`MAX_MANIFEST_BYTES`."""
    path = root / MANIFEST
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NOFOLLOW | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        if not root.exists():
            raise StoreError(f"{root}: no such store") from None
        if not root.is_dir():
            raise StoreError(f"{root}: not a directory, not a geoidspline store") from None
        if (root / PROGRESS).exists():
            raise StoreError(f"{root}: an unfinished fit, not a store yet (no {MANIFEST}; {PROGRESS} records the "
                             "bands committed): continue it by fitting again with resume=True") from None
        raise StoreError(
            f"{root}: not a geoidspline store (no {MANIFEST}; a store whose first write did not finish has none)"
        ) from None
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise StoreCorruptError(f"{path}: is a symbolic link, not the store's manifest") from None
        if exc.errno == errno.ENOTDIR:
            raise StoreError(f"{root}: not a directory, not a geoidspline store") from None
        raise StoreError(f"{path}: cannot be read ({exc.strerror})") from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise StoreCorruptError(f"{path}: is {_file_kind(st.st_mode)}, not the store's manifest")
        if st.st_size > MAX_MANIFEST_BYTES:
            raise StoreCorruptError(f"{path}: manifest is {st.st_size:,} bytes, more than the "
                                    f"{MAX_MANIFEST_BYTES:,} a manifest may have")
        return _read_up_to(fd, st.st_size)
    except OSError as exc:
        raise StoreError(f"{path}: cannot be read ({exc.strerror})") from None
    finally:
        os.close(fd)


def load_manifest(root: Path) -> dict:
    """The store's manifest, read and checked: JSON, format, schema, integrity digest."""
    root = Path(root)
    path = root / MANIFEST
    manifest = parse_manifest(path, read_manifest_bytes(root))
    validate_manifest(path, manifest)
    return manifest


def integrity_digest(manifest: dict) -> str:
    """sha256 of the manifest's canonical JSON without its ``integrity`` record."""
    body = {k: v for k, v in manifest.items() if k != "integrity"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), ensure_ascii=True, allow_nan=False)
    return hashlib.sha256(text.encode("ascii")).hexdigest()


#: The integrity record's statement of its rule: checked word for word, since the digest
#: cannot cover its own record.
INTEGRITY_RULE = "sha256 of the manifest without this record as JSON with sorted keys, separators ',' and ':', ASCII"


def manifest_text(manifest: dict) -> bytes:
    """The manifest as written: with its integrity digest, NaN refused."""
    manifest = dict(manifest)
    manifest.pop("integrity", None)
    manifest["integrity"] = {"sha256": integrity_digest(manifest), "rule": INTEGRITY_RULE}
    # compact: a global store lists thousands of tiles (indent=1 added 0.78 MB of 3.7 at 1 cm)
    return json.dumps(manifest, separators=(",", ":"), allow_nan=False).encode("utf-8")


MANIFEST_KEYS = ("format_version", "store_version", "spline", "fit", "accuracy", "tiles", "region", "provenance")


class _Schema:
    """The manifest's schema as code: each check names the key (dotted path) and the rule."""

    def __init__(self, path):
        self.path = path

    def fail(self, key, rule):
        raise StoreCorruptError(f"{self.path}: manifest key '{key}' {rule}")

    def get(self, obj, name, where, optional=False):
        key = f"{where}.{name}" if where else name
        if name not in obj:
            if optional:
                return None
            self.fail(key, "is missing")
        return obj[name]

    @staticmethod
    def _kind(value):
        return "null" if value is None else type(value).__name__

    def integer(self, value, key, lo, hi):
        if isinstance(value, bool) or not isinstance(value, int):
            self.fail(key, f"must be an integer, got {self._kind(value)}")
        if not lo <= value <= hi:
            self.fail(key, f"must be within {lo}..{hi}, got {value if abs(value) < 10**20 else 'a huge number'}")
        return value

    def number(self, value, key, lo=-math.inf, hi=math.inf, nullable=False, open_lo=False):
        if value is None and nullable:
            return value
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            self.fail(key, f"must be a number{' or null' if nullable else ''}, got {self._kind(value)}")
        value = float(value) if not isinstance(value, int) or abs(value) < 2**63 else math.inf
        if not math.isfinite(value) or value < lo or value > hi or (open_lo and value == lo):
            self.fail(key, f"must be a finite number {'>' if open_lo else '>='} {lo} and <= {hi}, got {value:g}")
        return value

    def string(self, value, key, nullable=False, max_len=10_000):
        if value is None and nullable:
            return value
        if not isinstance(value, str):
            self.fail(key, f"must be a string{' or null' if nullable else ''}, got {self._kind(value)}")
        if len(value) > max_len:
            self.fail(key, f"is longer than {max_len} characters")
        return value

    def boolean(self, value, key):
        if not isinstance(value, bool):
            self.fail(key, f"must be true or false, got {self._kind(value)}")
        return value

    def mapping(self, value, key):
        if not isinstance(value, dict):
            self.fail(key, f"must be an object, got {self._kind(value)}")
        return value

    def array(self, value, key, min_len=0, max_len=10**7):
        if not isinstance(value, list):
            self.fail(key, f"must be a list, got {self._kind(value)}")
        if not min_len <= len(value) <= max_len:
            self.fail(key, f"must have {min_len}..{max_len} items, got {len(value)}")
        return value

    def region(self, value, key):
        from ..errors import CoordinateError
        from ..sphere.region import Region

        self.array(value, key, 4, 4)
        bounds = [self.number(v, f"{key}[{i}]", -1e4, 1e4) for i, v in enumerate(value)]
        try:
            region = Region(*bounds)
        except CoordinateError as exc:
            self.fail(key, f"is not a region (S W N E degrees): {exc}")
        if value[3] - value[1] > 360.0 + 1e-9:
            self.fail(key, "spans more than 360 degrees of longitude")
        return region


#: The keys of a tile entry; their values are checked one by one (other keys for depth).
TILE_KEYS = frozenset(("tile", "file", "bytes", "sha256", "coefficients", "levels", "max_error_m", "rms_error_m",
                       "check_points", "node_max_error_m", "node_rms_error_m", "nodes"))


def _check_depth(path, value, key="", depth=1):
    """Refuse containers nested deeper than :data:`MAX_MANIFEST_DEPTH` (iteratively)."""
    stack = [(value, depth, key)]
    while stack:
        value, depth, key = stack.pop()
        if depth > MAX_MANIFEST_DEPTH:
            raise StoreCorruptError(f"{path}: manifest key '{key}' is nested more than {MAX_MANIFEST_DEPTH} deep")
        if isinstance(value, dict):
            stack.extend((v, depth + 1, f"{key}.{k}" if key else str(k)) for k, v in value.items())
        elif isinstance(value, list):
            stack.extend((v, depth + 1, f"{key}[{i}]") for i, v in enumerate(value))


def validate_manifest(path, manifest: dict):
    """Check a parsed manifest against the format's schema; raise naming the key and the rule.

    :class:`StoreError` for a manifest that is not geoidspline's or is newer than this
    version reads; :class:`StoreCorruptError` for everything else (missing key, wrong
    type, number out of range, a tile file name that is not a plain tile name inside
    ``tiles/``, duplicated tiles, counts that do not add up, a format-2 manifest whose
    integrity digest does not match its content).
    """
    s = _Schema(path)
    if manifest.get("format") != FORMAT_NAME:
        found = manifest.get("format")
        found = found if isinstance(found, str) and len(found) < 100 else s._kind(found)
        raise StoreError(f"{path}: not a geoidspline manifest (format {found!r})")
    version = s.get(manifest, "format_version", "")
    if isinstance(version, int) and not isinstance(version, bool) and version > FORMAT_VERSION:
        shown = version if version < 10**9 else "a huge number"
        raise StoreError(f"{path}: store format {shown} is newer than this geoidspline reads ({FORMAT_VERSION})")
    s.integer(version, "format_version", 1, FORMAT_VERSION)
    # the tile entries' own keys are checked one by one below: no need to walk them
    _check_depth(path, {k: v for k, v in manifest.items() if k != "tiles"})
    missing = [key for key in MANIFEST_KEYS if key not in manifest]
    if missing:
        raise StoreCorruptError(f"{path}: manifest lacks {', '.join(missing)}")
    store_version = s.integer(manifest["store_version"], "store_version", 1, 2**31)
    for key in ("created", "updated", "software"):
        s.string(manifest.get(key, ""), key)
    s.mapping(manifest["provenance"], "provenance")
    for key in ("source", "model", "kind", "ellipsoid", "tide_system"):
        s.string(manifest["provenance"].get(key), f"provenance.{key}", nullable=True)
    s.region(manifest["region"], "region")

    spline = s.mapping(manifest["spline"], "spline")
    s.integer(s.get(spline, "order", "spline"), "spline.order", 2, 8)
    h0 = s.number(s.get(spline, "h0", "spline"), "spline.h0", 0.0, 1.0, open_lo=True)
    tile_size = s.number(s.get(spline, "tile_size", "spline"), "spline.tile_size", h0, 2.0)
    levels = s.array(s.get(spline, "levels", "spline"), "spline.levels", 1, 32)
    level_counts = {}
    for i, lv in enumerate(levels):
        key = f"spline.levels[{i}]"
        s.mapping(lv, key)
        level = s.integer(s.get(lv, "level", key), f"{key}.level", 0, 30)
        if level in level_counts:
            s.fail(f"{key}.level", f"repeats level {level}")
        h = s.number(s.get(lv, "h", key), f"{key}.h", 0.0, 1.0, open_lo=True)
        if h != h0 / 2.0**level:
            s.fail(f"{key}.h", f"must be h0 / 2**level = {h0 / 2.0 ** level!r}, got {h!r}")
        level_counts[level] = s.integer(s.get(lv, "coefficients", key), f"{key}.coefficients", 0, 2**40)
    total = s.integer(s.get(spline, "coefficients", "spline"), "spline.coefficients", 1, 2**40)
    if total != sum(level_counts.values()):
        s.fail("spline.coefficients", f"is {total}, the levels hold {sum(level_counts.values())}")

    fit = s.mapping(manifest["fit"], "fit")
    s.number(s.get(fit, "tolerance_m", "fit"), "fit.tolerance_m", 0.0, 1e6, open_lo=True)
    s.boolean(s.get(fit, "converged", "fit"), "fit.converged")
    s.number(s.get(fit, "seconds", "fit"), "fit.seconds", 0.0, 1e12)
    s.mapping(s.get(fit, "parameters", "fit"), "fit.parameters")

    accuracy = s.mapping(manifest["accuracy"], "accuracy")
    for key in ("nodes", "check_points"):
        s.integer(s.get(accuracy, key, "accuracy"), f"accuracy.{key}", 0, 2**50)
    for key in ("node_max_error_m", "node_rms_error_m", "max_error_m", "rms_error_m", "p99_error_m"):
        s.number(s.get(accuracy, key, "accuracy"), f"accuracy.{key}", 0.0, 1e9, nullable=True)
    s.number(accuracy.get("node_p99_error_m"), "accuracy.node_p99_error_m", 0.0, 1e9, nullable=True)
    s.number(accuracy.get("fit_node_max_error_m"), "accuracy.fit_node_max_error_m", 0.0, 1e9, nullable=True)
    s.number(accuracy.get("cell_centre_max_m"), "accuracy.cell_centre_max_m", 0.0, 1e9, nullable=True)
    s.string(s.get(accuracy, "check_truth", "accuracy"), "accuracy.check_truth", nullable=True)

    # tiles: format 2 (.gst, quantised with spline.value_step_m) or format 1 (.nc, in a
    # format-1 manifest, or in a format-2 one of a format-1 store updated since)
    step = s.number(spline.get("value_step_m"), "spline.value_step_m", 0.0, 1e6, nullable=True, open_lo=True)
    if step is not None and version < 2:
        s.fail("spline.value_step_m", "is format 2's: a format-1 manifest has none")
    if step is not None:
        s.number(s.get(spline, "value_error_bound_m", "spline"), "spline.value_error_bound_m", 0.0, 1e6)
    tile_suffix = "gst" if step is not None else "nc"
    bound = math.ceil(1.0 / tile_size) + 1  # the unit sphere lies within ±1 on each axis
    tiles = s.array(manifest["tiles"], "tiles", 1)
    seen_tiles, seen_files, counted = set(), set(), 0
    for i, entry in enumerate(tiles):
        key = f"tiles[{i}]"
        s.mapping(entry, key)
        tile = s.array(s.get(entry, "tile", key), f"{key}.tile", 3, 3)
        tile = tuple(s.integer(v, f"{key}.tile[{a}]", -bound, bound) for a, v in enumerate(tile))
        if tile in seen_tiles:
            s.fail(f"{key}.tile", f"repeats tile {list(tile)}")
        seen_tiles.add(tile)
        name = s.string(s.get(entry, "file", key), f"{key}.file", max_len=200)
        head, sep, base = name.partition("/")
        match = TILE_NAME.fullmatch(base) if (head == TILE_DIR and sep) else None
        if match is None or "\0" in name:
            s.fail(f"{key}.file", f"must be a plain tile file name inside {TILE_DIR}/ "
                                  f"(like {TILE_DIR}/{tile_name(tile, 1)}), got {name[:80]!r}")
        if tuple(int(v) for v in match.groups()[:3]) != tile or int(match.group(4)) > store_version:
            s.fail(f"{key}.file", f"names tile {[int(v) for v in match.groups()[:3]]} of version "
                                  f"{match.group(4)}, not tile {list(tile)} of version <= {store_version}")
        if match.group(5) != tile_suffix:
            s.fail(f"{key}.file", f"must be a .{tile_suffix} tile: the store's tiles are "
                                  f"{'format 2 (spline.value_step_m is given)' if step else 'format 1'}")
        if name in seen_files:
            s.fail(f"{key}.file", f"repeats the file {name}")
        seen_files.add(name)
        s.integer(s.get(entry, "bytes", key), f"{key}.bytes", 1, MAX_TILE_BYTES)
        digest = s.string(s.get(entry, "sha256", key), f"{key}.sha256")
        if not re.fullmatch(r"[0-9a-f]{64}", digest):
            s.fail(f"{key}.sha256", "must be 64 lowercase hex digits")
        counted += s.integer(s.get(entry, "coefficients", key), f"{key}.coefficients", 1, 2**40)
        entry_levels = s.array(s.get(entry, "levels", key), f"{key}.levels", 1, 32)
        for a, lv in enumerate(entry_levels):
            s.integer(lv, f"{key}.levels[{a}]", 0, 30)
            if lv not in level_counts:
                s.fail(f"{key}.levels[{a}]", f"names level {lv}, which the spline does not have")
        if entry_levels != sorted(set(entry_levels)):
            s.fail(f"{key}.levels", "must be ascending without repeats")
        for stat_key in ("max_error_m", "rms_error_m", "node_max_error_m", "node_rms_error_m"):
            s.number(entry.get(stat_key), f"{key}.{stat_key}", 0.0, 1e9, nullable=True)
        for stat_key in ("check_points", "nodes"):
            s.integer(entry.get(stat_key, 0), f"{key}.{stat_key}", 0, 2**50)
        for extra in entry.keys() - TILE_KEYS:
            _check_depth(path, entry[extra], f"{key}.{extra}", 3)
    if counted != total:
        s.fail("tiles", f"hold {counted} coefficients, the spline has {total}")

    history = s.array(manifest.get("history", []), "history")
    for i, record in enumerate(history):
        s.mapping(record, f"history[{i}]")

    store_id = s.string(manifest.get("store_id"), "store_id", nullable=True)
    if store_id is not None and not re.fullmatch(r"[0-9a-f]{32}", store_id):
        s.fail("store_id", "must be 32 lowercase hex digits")
    if version >= 2:  # a format-1 store updated since has no store_id: its old tiles have none
        from .coverage import validate_coverage_record

        validate_coverage_record(s, s.get(manifest, "coverage", ""))
        integrity = s.mapping(s.get(manifest, "integrity", ""), "integrity")
        digest = s.string(s.get(integrity, "sha256", "integrity"), "integrity.sha256")
        if integrity.get("rule") != INTEGRITY_RULE or set(integrity) != {"sha256", "rule"}:
            raise StoreCorruptError(f"{path}: manifest's integrity record was altered (its rule or keys differ "
                                    "from what the writer states)")
        if digest != integrity_digest(manifest):
            raise StoreCorruptError(f"{path}: manifest was altered after it was written (its content does not "
                                    f"match integrity.sha256)")
