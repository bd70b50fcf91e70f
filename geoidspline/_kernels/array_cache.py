"""Reuse of large arrays' memory within a scope (``src/array_cache.c``): numpy's data
allocator (NEP 49's PyDataMem handler) swapped, for the current thread's context, for one
that keeps freed large blocks and hands them to the next request of their size class, or
remaps the kept block nearest in size to a request of a new size (only the pages it grows
by are new).

A band's fit makes many large temporaries; each fresh one is paged in and zeroed
by the kernel, much of the fit's system time (benchmarks/README.md). The kept
blocks never raise the allocator's resident bytes above the highest bytes its arrays held
at once since the scope opened, and closing the last scope releases them.

numpy's handler is installed through its C API table (``_ARRAY_API``, entry 304:
``PyDataMem_SetHandler``, stable since numpy 1.22), so the kernels need no Python headers.
"""

from __future__ import annotations

import contextlib
import ctypes

import numpy as np

from ._clib import _LIB, I64, function

_open = function("gs_array_cache_open")
_close = function("gs_array_cache_close")
_counts = function("gs_array_cache_counts", ctypes.POINTER(I64))

_SET_HANDLER_INDEX = 304  # PyDataMem_SetHandler in numpy's __multiarray_api.h


def _set_handler():
    """numpy's ``PyDataMem_SetHandler(capsule) -> previous capsule`` (called with the GIL)."""
    from numpy._core import _multiarray_umath

    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    get_pointer.restype = ctypes.c_void_p
    table = ctypes.cast(get_pointer(_multiarray_umath._ARRAY_API, None), ctypes.POINTER(ctypes.c_void_p))
    return ctypes.PYFUNCTYPE(ctypes.py_object, ctypes.py_object)(table[_SET_HANDLER_INDEX])


def _handler_capsule():
    new_capsule = ctypes.pythonapi.PyCapsule_New
    new_capsule.argtypes = [ctypes.c_void_p, ctypes.c_char_p, ctypes.c_void_p]
    new_capsule.restype = ctypes.py_object
    # numpy reads the handler through the capsule for as long as an array of it lives: the
    # struct is the library's static data, the capsule's name a constant bytes object
    return new_capsule(ctypes.addressof(ctypes.c_char.in_dll(_LIB, "gs_array_cache_handler")), _CAPSULE_NAME, None)


_CAPSULE_NAME = b"mem_handler"
_SET = _set_handler()
_HANDLER = _handler_capsule()
NAME = "geoidspline_array_cache"


@contextlib.contextmanager
def reused_array_memory():
    """Within the ``with`` block, this thread's new numpy arrays take their data from the
    caching allocator (see the module's docstring); nested and concurrent scopes share it."""
    _open()
    previous = _SET(_HANDLER)
    try:
        yield
    finally:
        _SET(previous)
        _close()


def counts() -> dict:
    """The allocator's counters since the cache last opened: large blocks ``reused`` (a kept
    block whole) and ``fresh`` (new, or a kept one remapped), bytes ``in_use``, ``kept`` and the ``high`` mark of bytes in use, ``fresh_bytes`` new (a remapped block's growth)."""
    out = np.zeros(6, dtype=np.int64)
    _counts(out.ctypes.data_as(ctypes.POINTER(I64)))
    return dict(zip(("reused", "fresh", "in_use", "kept", "high", "fresh_bytes"), (int(v) for v in out)))
