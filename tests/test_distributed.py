"""Distributed solving: a process pool and a dask LocalCluster give the serial fit's
coefficients bit for bit, and bad scheduler values are refused up front."""

from __future__ import annotations

import numpy as np
import pytest
from test_fit import bumpy_field, lattice

from geoidspline.errors import FitError
from geoidspline.fitting.driver import fit_nodes
from geoidspline.fitting.executors import Executor, solve_problems
from geoidspline.fitting.parameters import FitParameters
from geoidspline.sphere.region import Region

REGION = Region(-20, -30, 20, 30)
# small blocks and no untiled levels: every level is split into many blocks
PARAMS = dict(h0=0.1, max_level=2, tolerance_m=0.01, block_cells=8, untiled_max_unknowns=0)


@pytest.fixture(scope="module")
def sample():
    return lattice(bumpy_field, 0.5, -60, 60, -90, 90)


@pytest.fixture(scope="module")
def recorded(sample):
    """The serial fit, and the local problems of its levels (recorded on the way)."""
    import geoidspline.fitting.executors as module

    levels = []
    real = module.solve_problems

    def record(problems, *args, **kwargs):
        levels.append(list(problems))
        return real(levels[-1], *args, **kwargs)

    module.solve_problems = record
    try:
        result = fit_nodes(sample, REGION, FitParameters(**PARAMS))
    finally:
        module.solve_problems = real
    return result, levels


@pytest.fixture(scope="module")
def serial(recorded):
    return recorded[0]


def assert_same_coefficients(a, b):
    assert len(a.spline.levels) == len(b.spline.levels)
    for la, lb in zip(a.spline.levels, b.spline.levels):
        assert la.h == lb.h
        assert np.array_equal(la.indices, lb.indices)
        # bitwise: a block is the same computation wherever it runs (a serial compiled
        # kernel builds the normal equations, qdldl factorises them: no threads, no BLAS)
        assert np.array_equal(la.coefficients, lb.coefficients)
    assert [r.blocks_solved for r in a.levels] == [r.blocks_solved for r in b.levels]


def test_the_serial_fit_has_many_blocks(serial):
    assert len(serial.levels) >= 2
    assert all(r.blocks_solved > 4 for r in serial.levels)  # measured: 3 levels of 8, 7 and 18 blocks


def test_process_pool_gives_the_serial_coefficients(sample, serial):
    pooled = fit_nodes(sample, REGION, FitParameters(**PARAMS), executor=Executor(workers=2))
    assert_same_coefficients(serial, pooled)


def test_dask_local_cluster_gives_the_serial_coefficients(sample, serial):
    pytest.importorskip("dask.distributed")
    calls = []
    on_dask = fit_nodes(sample, REGION, FitParameters(**PARAMS), executor=Executor(workers=2, scheduler="local"),
                        progress=calls.append)
    assert_same_coefficients(serial, on_dask)
    assert sum(calls) == sum(r.blocks_solved for r in serial.levels)


def test_dask_results_come_back_in_the_order_of_the_problems(recorded):
    """Submitted to a running cluster by address (in-process, inproc://), more blocks
    than are let in flight at once: the results are in the order of the problems,
    whatever order they finish in, each with the seconds its solve took."""
    distributed = pytest.importorskip("dask.distributed")
    _, levels = recorded
    problems = max(levels, key=len)
    expected = solve_problems(problems)
    with distributed.LocalCluster(n_workers=1, threads_per_worker=2, processes=False,
                                  dashboard_address=None) as cluster:
        # a generator: read as blocks are handed out, at most 8 at a time here
        got = solve_problems((p for p in problems), workers=5, scheduler=cluster.scheduler_address)
    assert len(got) == len(problems) > 4
    for (k1, c1, _), (k2, c2, seconds) in zip(expected, got):
        assert np.array_equal(k1, k2) and np.array_equal(c1, c2)
        assert seconds > 0


def test_a_failing_block_fails_the_dask_solve():
    distributed = pytest.importorskip("dask.distributed")
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False,
                                  dashboard_address=None) as cluster:
        with pytest.raises(AttributeError):
            solve_problems([object()], scheduler=cluster.scheduler_address)


@pytest.mark.parametrize("bad", ["tcp:/host:8786", "localhost:8786", "Local", "", "dask", 8786])
def test_an_invalid_scheduler_is_refused(bad):
    with pytest.raises(FitError, match="scheduler"):
        Executor(scheduler=bad)


@pytest.mark.parametrize("good", [None, "local", "tcp://10.0.0.1:8786", "tls://s:8786", "inproc://x", "ucx://y"])
def test_valid_schedulers_are_accepted(good):
    assert Executor(scheduler=good).scheduler == good


def test_an_unreachable_scheduler_is_a_fit_error():
    pytest.importorskip("dask.distributed")
    import dask

    with dask.config.set({"distributed.comm.timeouts.connect": "1s"}):
        with pytest.raises(FitError, match="cannot connect"):
            solve_problems([object()], scheduler="tcp://127.0.0.1:9")


def test_without_dask_a_scheduler_asks_for_the_extra(monkeypatch):
    import builtins

    real_import = builtins.__import__

    def no_dask(name, *args, **kwargs):
        if name == "dask.distributed" or name.startswith("distributed"):
            raise ImportError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", no_dask)
    with pytest.raises(FitError, match=r"pip install 'geoidspline\[dask\]'"):
        solve_problems([object()], scheduler="local")
