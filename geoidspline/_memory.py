"""Large freed arrays go back to the system (glibc's mmap threshold pinned).

glibc serves allocations from 128 KiB up by ``mmap`` and returns them to the system
when freed, but after the first such free it raises that threshold to the freed size
(up to 32 MiB): from then on, arrays of a few MiB come from the heap, and the heap keeps
what is freed between arrays still alive. Reading a store and building its query
index allocate and free many arrays of that size among the ones they keep: the EGM96
2 mm store's build peaked at 535 MB of resident memory for 225 MB of live arrays,
415-423 MB with the threshold pinned at 128 KiB or 1 MiB (``benchmarks/README.md``,
"Compact stores"). Pinning it (``mallopt(M_MMAP_THRESHOLD, 1 MiB)``, which also stops
the raising) is what ``MALLOC_MMAP_THRESHOLD_=1048576`` in the environment does. Not
glibc (macOS, musl): nothing is done.

The command-line tools call :func:`pin_mmap_threshold` when they start (they own their
process); the library never does, since the setting is the whole process's: a program
using geoidspline as a library can call it, or set the environment variable.
"""

from __future__ import annotations

import ctypes
import threading

MMAP_THRESHOLD_BYTES = 1 << 20
_M_MMAP_THRESHOLD = -3  # glibc's malloc.h
_lock = threading.Lock()
_pinned = False


def pin_mmap_threshold() -> bool:
    """Pin glibc's mmap threshold at :data:`MMAP_THRESHOLD_BYTES` once per process;
    False where there is no glibc ``mallopt``."""
    global _pinned
    with _lock:
        if not _pinned:
            try:
                # the process's own symbols: ctypes.util.find_library runs ldconfig (12 ms
                # of every command's start)
                mallopt = ctypes.CDLL(None).mallopt
                mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
                _pinned = bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES))
            except (OSError, AttributeError):
                _pinned = None
        return bool(_pinned)


def _meminfo_bytes(field: str) -> float | None:
    """A field of Linux's ``/proc/meminfo`` in bytes; ``None`` where it is not known."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith(field + ":"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    return None


def available_bytes() -> float | None:
    """Memory the system can give this process without swapping (Linux's
    ``MemAvailable``), in bytes; ``None`` where it is not known."""
    return _meminfo_bytes("MemAvailable")


#: Share of the machine's memory a fit plans against when no ``max_memory`` is given:
#: the machine is often shared (other fits, the desktop), and a fit's estimate is a
#: measured average, not a bound.
MEMORY_FRACTION = 0.6


def total_bytes() -> float | None:
    """The machine's memory (Linux's ``MemTotal``), in bytes; ``None`` where not known."""
    return _meminfo_bytes("MemTotal")


def memory_budget(max_memory_bytes: float | None = None) -> float | None:
    """The memory a fit may plan for, in bytes: ``max_memory_bytes`` when given, else
    :data:`MEMORY_FRACTION` of the machine's; never more than the system has available
    now. ``None`` where neither is known."""
    limit = float(max_memory_bytes) if max_memory_bytes is not None else None
    if limit is None:
        total = total_bytes()
        limit = MEMORY_FRACTION * total if total is not None else None
    available = available_bytes()
    if limit is None:
        return available
    return limit if available is None else min(limit, available)
