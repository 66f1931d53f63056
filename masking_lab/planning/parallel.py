"""Simulations that scale out: chunks of replicates on Dask (*shell*: starts or joins a cluster).

A simulation is cut into chunks of a fixed number of replicates, each with its own seed from
``numpy.random.SeedSequence(seed).spawn(n_chunks)``; a chunk's result depends only on its
inputs, so the same seed gives the same tables however many workers run them, in process or
on a cluster. A chunk holds a bounded number of replicates, which bounds a worker's memory.

``scheduler``: ``"synchronous"`` runs the chunks one after another in this process (no Dask);
None runs them on worker processes of this machine (one per core, at most ``max_workers``,
forked from this one so they start with its imports and one BLAS thread each: a local Dask
cluster cost seconds to start and, its idle workers polling, more system time than the
simulation itself); an address (``tcp://host:8786``) joins that Dask cluster's scheduler.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

__all__ = ["Pending", "chunk_plan", "in_background", "run_chunks"]


def chunk_plan(seed: int, replicates: int, chunk: int) -> list[tuple[int, np.random.SeedSequence]]:
    """(replicates, seed sequence) of every chunk, in order.

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

    Examples
    --------
    >>> run_chunks(pow, [(2, 3), (3, 2)])
    [8, 9]
    """
    if scheduler == "synchronous":
        return [fn(*a) for a in args]
    if scheduler is None:
        return _local_pool(fn, args, max_workers)
    from distributed import Client

    with Client(scheduler) as client:
        return _gather(client, fn, args)


def _local_pool(
    fn: Callable[..., Any], args: Sequence[tuple[Any, ...]], max_workers: int
) -> list[Any]:
    """``[fn(*a) for a in args]`` on worker processes of this machine, in order."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    workers = max(1, min(max_workers, _cores(), len(args)))
    if workers == 1:
        return [fn(*a) for a in args]
    methods = multiprocessing.get_all_start_methods()
    context = multiprocessing.get_context("fork" if "fork" in methods else None)
    with ProcessPoolExecutor(workers, mp_context=context, initializer=_one_blas_thread) as pool:
        futures = [pool.submit(fn, *a) for a in args]
        return [f.result() for f in futures]


def _one_blas_thread() -> None:
    """A worker's BLAS runs on one thread: the workers already fill the cores."""
    from threadpoolctl import threadpool_limits

    threadpool_limits(1, user_api="blas")


class Pending:
    """A call running in a forked worker process (or, without ``fork``, deferred to
    :meth:`result`); :meth:`result` waits for it and ends the worker."""

    def __init__(self, fn: Callable[..., Any], args: tuple[Any, ...], kwargs: dict[str, Any]):
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self._call = (fn, args, kwargs)
        self._pool = None
        self._future = None
        if "fork" in multiprocessing.get_all_start_methods() and _cores() > 1:
            context = multiprocessing.get_context("fork")
            self._pool = ProcessPoolExecutor(1, mp_context=context, initializer=_one_blas_thread)
            self._future = self._pool.submit(fn, *args, **kwargs)

    def result(self) -> Any:
        """The call's return value (its exception re-raised here); asked again, the same."""
        if self._future is None or self._pool is None:
            if not hasattr(self, "_value"):
                fn, args, kwargs = self._call
                self._value = fn(*args, **kwargs)
            return self._value
        try:
            return self._future.result()
        finally:
            self._pool.shutdown()


def in_background(fn: Callable[..., Any], *args: Any, **kwargs: Any) -> Pending:
    """Start ``fn(*args, **kwargs)`` on the machine's other core while this process goes on.

    ``fn`` must be a module-level function and its result picklable. On one core, or where
    processes cannot be forked, the call runs when its result is asked for instead.

    Examples
    --------
    >>> in_background(pow, 2, 10).result()
    1024
    """
    return Pending(fn, args, kwargs)


def _cores() -> int:
    import os

    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def _gather(client: Any, fn: Callable[..., Any], args: Sequence[tuple[Any, ...]]) -> list[Any]:
    futures = [client.submit(fn, *a, pure=False) for a in args]
    return list(client.gather(futures))
