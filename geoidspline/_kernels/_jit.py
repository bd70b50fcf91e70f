"""The numba decorators every kernel module uses, in one place.

``cache=True`` keeps compiled code in ``__pycache__`` (or ``NUMBA_CACHE_DIR``), so a
second process does not compile again; ``nogil`` lets threads run kernels at once.
"""

from __future__ import annotations

import numba

jit = numba.njit(cache=True, nogil=True, fastmath=False)
pjit = numba.njit(cache=True, nogil=True, parallel=True, fastmath=False)
# small helpers of the query loop, inlined into it at numba's IR level
ijit = numba.njit(cache=True, nogil=True, fastmath=False, inline="always")


def numba_threads() -> int:
    """Threads numba's parallel loops use now (``numba.set_num_threads``)."""
    return numba.get_num_threads()


