"""File plumbing shared by the readers and the store: digests, atomic writes, fsync.

One implementation each, so that every file geoidspline writes is written the same
crash-safe way: to a temporary name beside the target, flushed to disk, then renamed
over the target in one :func:`os.replace` (a reader sees the old file or the new one,
never half of one).
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import tempfile
from pathlib import Path

__all__ = ["sha256_file", "atomic_path", "atomic_write", "fsync_dir", "fault_cause", "write_fault"]


def sha256_file(path) -> str:
    """Hex sha256 of a file's bytes, read in 1 MiB blocks."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def fsync_dir(path):
    """Flush a directory's entries (new names, renames) to disk."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


@contextlib.contextmanager
def atomic_path(path, suffix=".tmp"):
    """A temporary path beside ``path`` to write to; on success it is fsynced and renamed
    to ``path``, on failure removed. ``suffix`` keeps writers that choose the format by
    extension (GDAL) happy. A write fault is raised as the OSError behind it
    (:func:`write_fault`: a full disk is ENOSPC even where netCDF says 'HDF error'),
    found before the partial file is removed."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=suffix)
    os.close(fd)
    try:
        yield Path(tmp)
        with open(tmp, "rb+") as fh:
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes it 0600: give it a new file's usual mode
        os.replace(tmp, path)
    except (OSError, RuntimeError) as exc:
        fault = write_fault(path.parent, exc)
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        if fault is exc:
            raise
        raise fault from exc
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp)
        raise


def _umask() -> int:
    """The process's umask (read by setting and restoring it: there is no getter)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


def atomic_write(path, payload: bytes):
    """Write ``payload`` to ``path`` atomically (see :func:`atomic_path`)."""
    with atomic_path(path) as tmp:
        Path(tmp).write_bytes(payload)


# -- faults ---------------------------------------------------------------------------

_CAUSES = {
    errno.ENOSPC: "no space left on the device (disk full)",
    errno.EDQUOT: "disk quota exceeded",
    errno.EROFS: "read-only file system",
    errno.EACCES: "permission denied",
    errno.EPERM: "operation not permitted",
    errno.EIO: "input/output error",
    errno.EFBIG: "file too large for the file system",
}


def fault_cause(exc: BaseException) -> str:
    """What went wrong, in words, for an I/O fault (errno first, never a guess)."""
    if isinstance(exc, OSError) and exc.errno is not None:
        return _CAUSES.get(exc.errno, exc.strerror or str(exc))
    if isinstance(exc, MemoryError):
        return "out of memory"
    return str(exc) or type(exc).__name__


def write_fault(directory, exc: Exception) -> BaseException:
    """The fault behind a failed write into ``directory``: netCDF/HDF5 report a full disk
    as 'NetCDF: HDF error' (a RuntimeError) or as 'Permission denied', so the cause is
    found from the file system while the partial file still exists; an OSError that
    names its cause is returned as it is."""
    if isinstance(exc, OSError) and exc.errno not in (errno.EACCES, errno.EPERM, None):
        return exc  # a cause the library did name
    try:
        st = os.statvfs(directory)
    except OSError:
        return exc
    if st.f_flag & os.ST_RDONLY:
        return OSError(errno.EROFS, f"Read-only file system ({exc})")
    if isinstance(exc, OSError) and not os.access(directory, os.W_OK):
        return exc  # really no permission
    if st.f_bavail * st.f_frsize < (1 << 20) or (st.f_files and st.f_favail == 0):
        return OSError(errno.ENOSPC, f"No space left on device ({exc}; {st.f_bavail * st.f_frsize} bytes free)")
    return exc
