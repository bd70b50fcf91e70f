"""The caching allocator of numpy's array data used while bands are fitted
(geoidspline/_kernels/array_cache.py, src/array_cache.c)."""

import numpy as np

from geoidspline._kernels import array_cache
from geoidspline._kernels.array_cache import reused_array_memory

LARGE = 3_000_000  # float64: 24 MB, above the 1 MiB from which blocks are kept


def _handler_name():
    return np._core.multiarray.get_handler_name()


def test_the_scope_swaps_numpy_allocator_and_restores_it():
    before = _handler_name()
    with reused_array_memory():
        assert _handler_name() == array_cache.NAME
        with reused_array_memory():  # nested: the same allocator
            assert _handler_name() == array_cache.NAME
        assert _handler_name() == array_cache.NAME
    assert _handler_name() == before
    assert np.empty(LARGE).__array_interface__ is not None  # the default allocator works again


def test_a_freed_large_block_is_reused_and_released_at_close():
    with reused_array_memory():
        first = np.full(LARGE, 7.0)
        address = first.ctypes.data
        del first
        assert array_cache.counts()["kept"] > 0
        second = np.empty(LARGE)  # the same size class: the kept block
        assert second.ctypes.data == address
        assert array_cache.counts()["reused"] == 1
        zeros = np.zeros(LARGE)  # a kept block handed to calloc is zeroed
        del second
        zeros_again = np.zeros(LARGE)
        assert not zeros.any() and not zeros_again.any()
        del zeros, zeros_again
    counts = array_cache.counts()
    assert counts["kept"] == 0 and counts["in_use"] == 0


def test_kept_blocks_never_raise_the_bytes_above_the_high_mark():
    with reused_array_memory():
        a = np.ones(LARGE)
        del a
        # a larger request cannot use the kept 24 MB block: it is released first, so
        # in use + kept stays at the larger array's size
        b = np.ones(4 * LARGE)
        counts = array_cache.counts()
        assert counts["kept"] == 0
        assert counts["in_use"] + counts["kept"] <= counts["high"]
        del b


def test_values_survive_a_resize_and_arrays_outlive_the_scope():
    with reused_array_memory():
        values = np.arange(LARGE, dtype=float)
        values.resize(2 * LARGE, refcheck=False)  # numpy reallocates through the handler
        small = np.arange(10.0)
    assert np.array_equal(values[:LARGE], np.arange(LARGE, dtype=float))
    assert not values[LARGE:].any()
    assert small.sum() == 45.0
    del values, small  # freed by the allocator after its scope closed
    assert array_cache.counts()["in_use"] == 0


def _capacity(nbytes):
    """The allocator's size class of a large request (2 MiB pages, a 64-byte header)."""
    page = 1 << 21
    return -(-(nbytes + 64) // page) * page - 64


def test_a_request_of_a_new_size_grows_a_kept_block_by_the_difference_only():
    with reused_array_memory():
        small = np.ones(8_000_000)  # 64 MB: mapped, remapped when its size class is not asked again
        del small
        before = array_cache.counts()
        large = np.zeros(12_000_000)  # 96 MB: the kept 64 MB block, grown
        after = array_cache.counts()
        assert after["kept"] == 0
        assert after["fresh_bytes"] - before["fresh_bytes"] == _capacity(96_000_000) - _capacity(64_000_000)
        assert not large.any()  # its old pages zeroed, its new ones zero
        large[:] = 2.0
        del large
        shrunk = np.zeros(4_500_000)  # 36 MB: the kept 96 MB block, shrunk, nothing new
        assert array_cache.counts()["fresh_bytes"] == after["fresh_bytes"]
        assert not shrunk.any()
        del shrunk
