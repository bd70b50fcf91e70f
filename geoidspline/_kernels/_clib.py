"""The compiled kernels (C in ``src/``, built by setuptools into a shared library when the
package is installed) and the one way Python calls them: ctypes, which releases the GIL
for the call.

Each kernel module (:mod:`.coverage`, :mod:`.query`, ...) declares its C functions with
:func:`function` and keeps a thin wrapper of the same name and arguments as before. The
wrappers convert their inputs once (:func:`c_in`: contiguous, of the C type, a no-op for
arrays that already are) and check their outputs (:func:`c_out`); beyond that the kernels
trust their callers, as every kernel here does.

Threads: parallel kernels take a thread count, :func:`threads` (all the cores this process
may run on, or ``GEOIDSPLINE_THREADS``; :func:`set_threads` changes it). Threads are started
per call and joined (``src/gs_parallel.c``), so nothing survives into a forked process.
"""

from __future__ import annotations

import ctypes
import importlib.util
import os

import numpy as np


def _library_path() -> str:
    # The import system finds the built file (an in-place build of an editable install, or
    # site-packages), but it is not a Python module: ctypes loads it.
    spec = importlib.util.find_spec(f"{__package__}._libkernels")
    if spec is None or not spec.origin:
        raise ImportError(
            f"geoidspline's compiled kernels (_libkernels*.so) are missing in {os.path.dirname(__file__)}: "
            f"install the package (`pip install .`, or `pip install -e .` in a checkout; it needs a C "
            f"compiler), or run from outside the checkout to use the installed package")
    return spec.origin


_LIB = ctypes.CDLL(_library_path())

F64 = ctypes.c_double
I64 = ctypes.c_int64
PTR = ctypes.c_void_p


def function(name: str, *argtypes, restype=None):
    """The C function ``name`` of the kernel library with its argument and result types."""
    f = getattr(_LIB, name)
    f.argtypes = argtypes
    f.restype = restype
    return f


def c_in(array, dtype) -> np.ndarray:
    """``array`` as a C-contiguous array of ``dtype`` (no copy when it already is one).

    The caller keeps the result referenced for the duration of the C call."""
    return np.ascontiguousarray(array, dtype=dtype)


def c_out(array: np.ndarray, dtype) -> np.ndarray:
    """``array`` itself, checked to be a writable C-contiguous array of ``dtype``."""
    if array.dtype != np.dtype(dtype) or not array.flags.c_contiguous or not array.flags.writeable:
        raise TypeError(f"output array must be writable, C-contiguous {np.dtype(dtype)} (got {array.dtype})")
    return array


def ptr(array: np.ndarray) -> int:
    """The address of an array's first element, for a ``PTR`` argument."""
    return array.ctypes.data


def _default_threads() -> int:
    configured = os.environ.get("GEOIDSPLINE_THREADS", "").strip()
    if configured.isdigit() and int(configured) > 0:
        return int(configured)
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):  # pragma: no cover - not Linux
        return os.cpu_count() or 1


_threads = _default_threads()


def threads() -> int:
    """Threads the parallel kernels use now."""
    return _threads


def set_threads(count: int) -> int:
    """Use ``count`` threads (>= 1) in parallel kernels from now on; returns the previous count."""
    global _threads
    if int(count) < 1:
        raise ValueError(f"thread count must be at least 1, not {count}")
    previous, _threads = _threads, int(count)
    return previous
