"""Simulations that scale out: chunks of replicates on Dask (*shell*: starts or joins a cluster).

A simulation is cut into chunks of a fixed number of replicates, each with its own seed from
``numpy.random.SeedSequence(seed).spawn(n_chunks)``; a chunk's result depends only on its
inputs, so the same seed gives the same tables however many workers run them, in process or
on a cluster. A chunk holds a bounded number of replicates, which bounds a worker's memory.

``scheduler``: ``"synchronous"`` runs the chunks one after another in this process (no Dask);
``"local"`` (or None) runs them on worker processes of this machine (one per core, at most
``max_workers``, forked from this one so they start with its imports: a local Dask cluster cost
seconds to start and, its idle workers polling, more system time than the simulation itself);
an address (``tcp://host:8786``) joins that Dask cluster's scheduler. Every chunk runs with one
BLAS thread wherever it runs, so its floating-point sums are the same everywhere.

:func:`run_tasks` waits for every result; :func:`started_tasks` starts the tasks and hands
back their results one range at a time, so the caller can work on the first ones (``plan``
assembles its staircase plan) while the workers compute the rest.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import Any

import numpy as np

from masking_lab.core.errors import AnalysisError
from masking_lab.core.worker_processes import result_or_here

__all__ = [
    "CONNECT_TIMEOUT_S",
    "Task",
    "TaskResults",
    "chunk_plan",
    "run_chunks",
    "run_tasks",
    "started_tasks",
]

#: Seconds to wait for a Dask scheduler to answer before giving up with a clear error.
CONNECT_TIMEOUT_S = 10.0
#: A chunk of work: a module-level function and its arguments (both picklable).
Task = tuple[Callable[..., Any], tuple[Any, ...]]


def chunk_plan(
    seed: int | Sequence[int], replicates: int, chunk: int
) -> list[tuple[int, np.random.SeedSequence]]:
    """(replicates, seed sequence) of every chunk, in order.

    ``seed`` is an int or a sequence of ints (a stream of its own, e.g. ``[seed, 1]``).

    Examples
    --------
    >>> [n for n, _ in chunk_plan(0, 25, 10)]
    [10, 10, 5]
    """
    if replicates < 1 or chunk < 1:
        raise ValueError(f"replicates and chunk must be ≥ 1, got {replicates}, {chunk}")
    sizes = [min(chunk, replicates - start) for start in range(0, replicates, chunk)]
    return list(zip(sizes, np.random.SeedSequence(seed).spawn(len(sizes)), strict=True))


def run_chunks(
    fn: Callable[..., Any],
    args: Sequence[tuple[Any, ...]],
    *,
    scheduler: str | None = "synchronous",
    max_workers: int = 4,
) -> list[Any]:
    """``[fn(*a) for a in args]``: in this process, on local worker processes, or on Dask.

    Results come back in the order of ``args``. ``fn`` must be a module-level function (it is
    pickled to the workers).

    Raises
    ------
    AnalysisError
        If no Dask scheduler answers at the address within :data:`CONNECT_TIMEOUT_S`.

    Examples
    --------
    >>> run_chunks(pow, [(2, 3), (3, 2)])
    [8, 9]
    """
    if scheduler == "synchronous":
        return [fn(*a) for a in args]
    if scheduler is None or scheduler == "local":
        return _local_pool(fn, args, max_workers)
    return _gather(_connect(scheduler), fn, args)


def run_tasks(tasks: Sequence[Task], *, scheduler: str | None = "synchronous") -> list[Any]:
    """Each task's ``fn(*args)``, in order, wherever ``scheduler`` says, each with one BLAS
    thread (a product's sums then do not depend on where it ran).

    Examples
    --------
    >>> run_tasks([(pow, (2, 3)), (divmod, (7, 2))])
    [8, (3, 1)]
    """
    return run_chunks(_one_thread_call, list(tasks), scheduler=scheduler)


class TaskResults:
    """The results of tasks started together (:func:`started_tasks`), each waited for when
    it is needed, so this process can use some while the workers compute the others.

    Examples
    --------
    >>> with started_tasks([(pow, (2, 3)), (divmod, (7, 2))]) as results:
    ...     results.wait(1, 2), results.wait(0, 1)
    ([(3, 1)], [8])
    """

    def __init__(self, fetch: Callable[[int], Any], n_tasks: int) -> None:
        self._fetch = fetch
        self._n = n_tasks

    def wait(self, start: int, stop: int) -> list[Any]:
        """The results of tasks ``start`` … ``stop − 1``, in order (waiting for them).

        Raises
        ------
        IndexError
            If the range is not within the tasks.
        """
        if not 0 <= start <= stop <= self._n:
            raise IndexError(f"tasks {start}…{stop - 1} are not among the {self._n} started")
        return [self._fetch(i) for i in range(start, stop)]


@contextmanager
def started_tasks(
    tasks: Sequence[Task], *, scheduler: str | None = "synchronous", max_workers: int = 4
) -> Iterator[TaskResults]:
    """Start every task where ``scheduler`` says (as :func:`run_tasks`) and hand back their
    results to wait for, in any order, while the workers go on; leaving the block waits for
    (or, on an error, cancels) whatever is still running.

    ``"synchronous"`` runs a task in this process when its result is first wanted (then keeps
    it): the same numbers, one task at a time.

    Raises
    ------
    AnalysisError
        If no Dask scheduler answers at the address within :data:`CONNECT_TIMEOUT_S`.

    Examples
    --------
    >>> with started_tasks([(pow, (2, 3)), (pow, (3, 2))], scheduler="local") as results:
    ...     results.wait(0, 2)
    [8, 9]
    """
    calls = [(_one_thread_call, task) for task in tasks]
    if scheduler == "synchronous" or (
        scheduler in (None, "local") and min(max_workers, _cores(), len(calls)) <= 1
    ):
        done: dict[int, Any] = {}

        def run_here(i: int) -> Any:
            if i not in done:
                fn, args = calls[i]
                done[i] = fn(*args)
            return done[i]

        yield TaskResults(run_here, len(calls))
    elif scheduler is None or scheduler == "local":
        with _forked_pool(min(max_workers, _cores(), len(calls))) as pool:
            futures = [pool.submit(fn, *args) for fn, args in calls]
            got: dict[int, Any] = {}

            def fetch(i: int) -> Any:
                # a worker that died (killed for memory, say) leaves its tasks to this process
                if i not in got:
                    fn, args = calls[i]
                    got[i] = result_or_here(futures[i], fn, *args)
                return got[i]

            # on an error the pool's block interrupts the chunks still running (worker_pool)
            yield TaskResults(fetch, len(calls))
    else:
        with _connect(scheduler) as client:
            futures = [client.submit(fn, *args, pure=False) for fn, args in calls]
            yield TaskResults(lambda i: futures[i].result(), len(calls))


def _one_thread_call(fn: Callable[..., Any], args: tuple[Any, ...]) -> Any:
    from masking_lab.core.blas_threads import one_blas_thread

    with one_blas_thread():
        return fn(*args)


def _connect(address: str) -> Any:
    """A Dask client of the scheduler at ``address`` (an error naming it if none answers)."""
    from distributed import Client

    try:
        return Client(address, timeout=CONNECT_TIMEOUT_S)
    except (OSError, TimeoutError, ValueError) as exc:
        raise AnalysisError(
            f"--scheduler {address}: no Dask scheduler answered there within "
            f"{CONNECT_TIMEOUT_S:g} s ({type(exc).__name__}: {str(exc)[:200]}); start one "
            "(`dask scheduler`, and `dask worker ADDRESS` on each machine) or use --scheduler "
            "local"
        ) from None


def _local_pool(
    fn: Callable[..., Any], args: Sequence[tuple[Any, ...]], max_workers: int
) -> list[Any]:
    """``[fn(*a) for a in args]`` on worker processes of this machine, in order."""
    workers = max(1, min(max_workers, _cores(), len(args)))
    if workers == 1:
        return [fn(*a) for a in args]
    with _forked_pool(workers) as pool:
        futures = [pool.submit(fn, *a) for a in args]
        # a worker that died (killed for memory, say) leaves its tasks to this process
        return [result_or_here(f, fn, *a) for f, a in zip(futures, args, strict=True)]


def _forked_pool(workers: int) -> Any:
    """A pool of ``workers`` processes forked from this one (they start with its imports)."""
    import multiprocessing

    from masking_lab.core.blas_threads import one_blas_thread_here
    from masking_lab.core.worker_processes import worker_pool

    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if "fork" in methods else None)
    # a worker's BLAS runs on one thread: the workers already fill the cores
    return worker_pool(workers, mp_context=context, initializer=one_blas_thread_here)


def _cores() -> int:
    import os

    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _gather(client: Any, fn: Callable[..., Any], args: Sequence[tuple[Any, ...]]) -> list[Any]:
    with client:
        futures = [client.submit(fn, *a, pure=False) for a in args]
        return list(client.gather(futures))
