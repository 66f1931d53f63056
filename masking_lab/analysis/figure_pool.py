"""Worker processes that draw a run's summary figures (*shell*).

Importing matplotlib and drawing the summary PNGs (the AL-shift and masking-function figures
of each experiment) is most of the fixed cost of ``analyze``. :class:`FigurePool` starts a
worker process when a run begins, before the main process imports pandas and SciPy; the worker
imports matplotlib and the figure modules meanwhile and draws each figure as soon as its data
are known, while the main process reads logs, fits and writes the other outputs. Once warm, it
forks a second worker (:mod:`~masking_lab.analysis.forked_lane`), so two workers draw for one
import: a second worker forked from the main process imported matplotlib again, ~0.4 s of CPU
while the logs were being read (1,000 sessions: 2.7–2.9 → 2.3–2.6 s, CPU 4.9–5.2 → 3.6–4.0 s).
The figure code is the same as in-process, so the bytes are too.

Without a worker (``enabled=False``, or a platform that cannot start one) every figure is drawn
in-process when its result is asked for; a worker that dies leaves its figures to the main
process likewise.
"""

from __future__ import annotations

import multiprocessing
import weakref
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from masking_lab.analysis.forked_lane import ForkedLane, LaneGone, fork_second
from masking_lab.core.worker_processes import cancel_pool, worker_pool

__all__ = ["FigurePool"]

T = TypeVar("T")


def _warm() -> None:
    """In the worker: load what drawing needs (matplotlib on Agg, the figure modules)."""
    import masking_lab.analysis.figures
    import masking_lab.analysis.lab_figures  # noqa: F401
    from masking_lab.formats.png_figure import pyplot

    pyplot()


def _warm_and_fork() -> int | None:
    """In the first worker: :func:`_warm`, then fork the second worker (its pid)."""
    _warm()
    return fork_second()


class FigurePool:
    """Figures drawn in worker processes (or in-process, see the module docstring).

    Parameters
    ----------
    enabled : bool
        Start the workers (False: draw in-process when asked).

    Examples
    --------
    >>> pool = FigurePool(enabled=False)
    >>> result = pool.submit(sum, [1, 2, 3])
    >>> result()
    6
    >>> pool.close()
    """

    def __init__(self, enabled: bool = True) -> None:
        self._lanes: list[tuple[ProcessPoolExecutor, list[Future[Any]]]] = []
        self._second: ForkedLane | None = None
        self._enabled = enabled
        if enabled:
            self._second = ForkedLane.make()
            if not self._add_lane() and self._second is not None:
                self._second.close()
                self._second = None

    def _add_lane(self) -> bool:
        first = not self._lanes and self._second is not None
        try:
            # ends with this process, even killed; forked, so the first inherits the lane
            pool = worker_pool(1, mp_context=multiprocessing.get_context("fork") if first else None)
            # the worker starts now, not at the first figure
            warming = pool.submit(_warm_and_fork if first else _warm)
        except (OSError, NotImplementedError, RuntimeError, ValueError):  # in-process, then
            return False
        if first and self._second is not None:
            self._second.forked = warming
        self._lanes.append((pool, []))
        # a run that fails before collecting its figures does not wait for them
        weakref.finalize(self, pool.shutdown, False, cancel_futures=True)
        return True

    def widen(self, workers: int) -> None:
        """Use up to ``workers`` worker processes (a large study's figures take seconds each;
        each is still drawn whole by one worker, so the bytes do not change). The second is
        forked from the first once warm, so it exists from the start where it can."""
        while self._enabled and self._workers() < workers and self._add_lane():
            pass

    def _workers(self) -> int:
        return len(self._lanes) + (self._second is not None)

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Callable[[], T]:
        """Start ``fn(*args, **kwargs)`` (a module-level ``fn``, picklable arguments; plain
        data keeps pandas out of the worker) in the least busy worker; returns a function
        giving its result (waiting for the worker, or drawing in-process)."""
        if not self._lanes:
            return lambda: fn(*args, **kwargs)
        busy = [sum(not f.done() for f in lane[1]) for lane in self._lanes]
        first = min(range(len(busy)), key=busy.__getitem__)  # the least busy, first of equals
        pool, queued = self._lanes[first]
        second = self._second
        if second is not None and second.busy < busy[first]:
            try:
                ticket = second.submit(fn, args, kwargs)
            except LaneGone:
                pass
            else:

                def from_second() -> T:
                    try:
                        return second.result(ticket)
                    except LaneGone:  # never forked, or died (e.g. killed for memory)
                        return fn(*args, **kwargs)

                return from_second
        try:
            future: Future[T] = pool.submit(fn, *args, **kwargs)
        except (BrokenProcessPool, RuntimeError):
            return lambda: fn(*args, **kwargs)
        queued.append(future)

        def result() -> T:
            try:
                return future.result()
            except BrokenProcessPool:  # the worker died (e.g. killed for memory): draw here
                return fn(*args, **kwargs)

        return result

    def close(self, *, cancel: bool = False) -> None:
        """Stop the workers: after their figures, or at once with ``cancel`` (a failed run)."""
        if self._second is not None:
            self._second.close()
            self._second = None
        for pool, _ in self._lanes:
            if cancel:
                cancel_pool(pool)
            else:
                pool.shutdown(wait=True)
        self._lanes = []
