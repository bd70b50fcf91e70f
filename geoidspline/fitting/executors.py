"""Where the local problems of a level are solved: in process, in a process pool, or on dask.

The blocks of a level (:class:`geoidspline.fitting.least_squares.LocalProblem`) are independent: each one
carries its sites, values and unknowns and returns only its own coefficients. So they
can be solved anywhere, in any order, and merged afterwards.
:func:`solve_problems` does that, serially, in a pool of local worker processes, or as
tasks on a dask.distributed cluster (a :class:`~dask.distributed.LocalCluster` started
for the call, or an existing cluster given by its scheduler's address).

dask is optional (``pip install 'geoidspline[dask]'``) and imported only when a
scheduler is given. Every way gives the same coefficients bit for bit: a block is
solved by the same code on the same inputs wherever it runs (the normal equations are
built by a serial C kernel and factorised by qdldl, neither of which depends on the
thread count or on which process runs it).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import multiprocessing
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass

from ..errors import FitError
from ..options import check_number

__all__ = ["Executor", "solve_problems", "SCHEDULER_PREFIXES"]


log = logging.getLogger(__name__)


#: Address schemes of a dask scheduler that ``scheduler`` may name.
SCHEDULER_PREFIXES = ("tcp://", "tls://", "inproc://", "ucx://")


#: Environment of the worker processes of a LocalCluster: one solver per process, so
#: the kernels' threads stay at one (dask already pins OpenMP/MKL/OpenBLAS).
_WORKER_ENV = {"GEOIDSPLINE_THREADS": "1"}


@dataclass(frozen=True)
class Executor:
    """Where the blocks of a level are solved; it changes no coefficient, so it is never
    part of :class:`~geoidspline.fitting.parameters.FitParameters` nor of a store.

    ``scheduler=None``: this process (``workers == 1``) or a pool of ``workers`` spawned
    processes; ``"local"``: a dask ``LocalCluster`` of ``workers`` single-threaded
    processes started for each level; any other value: the address of a running dask
    scheduler (``tcp://``, ``tls://``, ``inproc://`` or ``ucx://``), whose workers solve the
    blocks. ``max_memory_bytes``: the memory the fit plans against.
    """

    workers: int = 1
    scheduler: str | None = None
    #: memory (bytes) the fit plans against (:func:`geoidspline._memory.memory_budget`:
    #: default a share of the machine's), like the workers a resource of the run
    max_memory_bytes: float | None = None

    def __post_init__(self):
        if self.max_memory_bytes is not None:
            check_number("max_memory_gb", self.max_memory_bytes / 1e9)
        if not isinstance(self.workers, int):  # 2.0 is not a count of processes
            raise FitError(f"workers must be a whole number >= 1, got {self.workers!r}")
        check_number("workers", self.workers)
        if self.scheduler is not None and not (
            isinstance(self.scheduler, str)
            and (self.scheduler == "local" or self.scheduler.startswith(SCHEDULER_PREFIXES))
        ):
            raise FitError(
                f"scheduler must be 'local' or a dask scheduler address (tcp://, tls://, inproc:// "
                f"or ucx://), got {self.scheduler!r}"
            )

    @property
    def memory_budget(self) -> float | None:
        """Bytes the fit may plan for (:func:`geoidspline._memory.memory_budget`)."""
        from .._memory import memory_budget

        return memory_budget(self.max_memory_bytes)

    def solve(self, problems, progress=None) -> list:
        """:func:`solve_problems` with this executor's workers and scheduler."""
        return solve_problems(problems, self.workers, self.scheduler, progress)


def solve_problems(problems, workers: int = 1, scheduler: str | None = None, progress=None) -> list:
    """Solve every local problem; return ``(own_keys, own_coefs, seconds)`` per problem.

    ``problems`` may be any iterable; on dask it is read only as fast as blocks are
    handed out (a bounded number are in flight), so a generator of blocks is never
    held in memory whole. The results are in the order of ``problems``; ``seconds``
    is the time the solve itself took where it ran (building and factorising the
    normal equations, without transfer or queueing). ``progress``, when given, is
    called with 1 as each problem finishes (in completion order).

    ``scheduler=None`` solves in this process (``workers == 1``) or in a pool of
    ``workers`` spawned processes; ``"local"`` starts a dask ``LocalCluster`` of
    ``workers`` single-threaded worker processes for this call and closes it after;
    an address (``"tcp://host:8786"``) submits to that running dask cluster, whose own
    workers do the work (``workers`` is then ignored).
    """
    problems = iter(problems)
    first = next(problems, None)
    if first is None:  # nothing to do: start no pool and no cluster
        return []
    problems = itertools.chain([first], problems)
    if scheduler is None:
        if workers > 1:
            return _solve_pool(problems, workers, progress)
        return _solve_serial(problems, progress)
    return _solve_dask(problems, workers, scheduler, progress)


def solve_problem(problem):
    """``problem.solve()``: a local problem (a level's block,
    :class:`geoidspline.fitting.least_squares.LocalProblem`, or a block of the
    hierarchical basis, :class:`geoidspline.fitting.hierarchical.HierarchicalProblem`)
    carries its own solver; this module-level function is what pools and dask ship."""
    return problem.solve()


def _solve_serial(problems, progress):
    results = []
    for problem in problems:
        results.append(solve_problem(problem))
        if progress:
            progress(1)
    return results


def _worker_init():
    # one solver per process: one kernel thread in each, so processes do not oversubscribe the cores
    from .._kernels import _clib

    _clib.set_threads(1)


def _solve_pool(problems, workers, progress):
    results = []
    ctx = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_worker_init) as pool:
        for result in pool.map(solve_problem, problems):
            results.append(result)
            if progress:
                progress(1)
    return results


def _import_dask():
    try:
        import dask
        from dask.distributed import Client, LocalCluster, as_completed
    except ImportError as exc:
        raise FitError(
            "a dask scheduler was given but dask.distributed is not installed: "
            "pip install 'geoidspline[dask]'"
        ) from exc
    return dask, Client, LocalCluster, as_completed


@contextlib.contextmanager
def _quiet_dask_logs():
    """dask logs every cluster start, connection and stop at INFO (dozens of lines per
    level): keep those for geoidspline's DEBUG logging (``geoid-fit -vv``) only."""
    logger = logging.getLogger("distributed")
    old = logger.level
    if not log.isEnabledFor(logging.DEBUG) and logger.getEffectiveLevel() < logging.WARNING:
        logger.setLevel(logging.WARNING)
    try:
        yield
    finally:
        logger.setLevel(old)


@contextlib.contextmanager
def _dask_client(workers, scheduler):
    """A dask client for a call: on a ``LocalCluster`` of ``workers`` single-threaded
    processes started for it (``scheduler == "local"``), or on the running cluster at the
    address ``scheduler``; dask's INFO logs quieted and its large-graph warning off for
    the call."""
    dask, Client, LocalCluster, _ = _import_dask()
    with contextlib.ExitStack() as stack:
        stack.enter_context(_quiet_dask_logs())
        if scheduler == "local":
            cluster = stack.enter_context(LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, env=dict(_WORKER_ENV),
                # no dashboard; the scheduler's HTTP endpoints (health, metrics) on a free
                # port rather than 8787, which another cluster may hold
                dashboard_address=":0", scheduler_kwargs={"dashboard": False},
            ))
            client = stack.enter_context(Client(cluster))
        else:
            try:
                client = Client(scheduler)
            except (OSError, TimeoutError) as exc:
                raise FitError(f"cannot connect to the dask scheduler at {scheduler}: {exc}") from exc
            stack.enter_context(client)
        # A block (or a band's shared inputs) travels inside its task, so that the
        # scheduler hands it to whichever worker is free; dask's warning about large
        # graphs is expected here and says nothing useful to the user.
        stack.enter_context(dask.config.set({"distributed.admin.large-graph-warning-threshold": "1 TiB"}))
        yield client


def _solve_dask(problems, workers, scheduler, progress):
    *_, as_completed = _import_dask()
    with _dask_client(workers, scheduler) as client:
        # At most `window` blocks are submitted and not yet finished, so neither the
        # scheduler nor the workers hold a whole level's data at once.
        window = max(8, 4 * sum(client.nthreads().values()))
        log.debug("solving problems on dask (%s), at most %d in flight", scheduler, window)
        results = []
        position = {}  # key of an unfinished future -> index of its problem
        exhausted = False

        def submit(count):
            nonlocal exhausted
            batch = list(itertools.islice(problems, count))
            exhausted = len(batch) < count
            if not batch:
                return []
            # pure=False: every block is its own task (no hashing of the data for a key)
            futures = client.map(solve_problem, batch, pure=False)
            for future in futures:
                position[future.key] = len(results)
                results.append(None)
            return futures

        finished = as_completed(submit(window), with_results=True)
        for future, result in finished:
            results[position.pop(future.key)] = result
            if progress:
                progress(1)
            if not exhausted and len(position) <= window // 2:
                finished.update(submit(window - len(position)))
        return results


def run_tasks(function, items, executor: Executor, shared=None):
    """``function(shared, item)`` for every item, yielding ``(item, result)`` as each
    finishes: here, one after the other, when ``executor`` has no scheduler (its
    ``workers`` then solve the blocks inside each task); on its dask cluster otherwise,
    at most one task per worker thread in flight (a task is a band of a fit: its
    working set, not a share of it). ``shared`` (the source, say) is sent to the
    cluster once. Every way runs the same code on the same inputs: the same results
    bit for bit.
    """
    items = list(items)
    if executor.scheduler is None:
        for item in items:
            yield item, function(shared, item)
        return
    *_, as_completed = _import_dask()
    with _dask_client(executor.workers, executor.scheduler) as client:
        shared_future = client.scatter(shared, broadcast=True) if shared is not None else None
        window = max(1, sum(client.nthreads().values()))
        pending = iter(items)
        which = {}

        def submit(count):
            futures = []
            for item in itertools.islice(pending, count):
                future = client.submit(function, shared_future, item, pure=False)
                which[future.key] = item
                futures.append(future)
            return futures

        finished = as_completed(submit(window), with_results=True)
        for future, result in finished:
            yield which.pop(future.key), result
            finished.update(submit(1))
