"""Worker processes that draw a run's summary figures (*shell*).

Importing matplotlib and drawing the summary PNGs (the AL-shift and masking-function figures
of each experiment) is most of the fixed cost of ``analyze``. :class:`FigurePool` starts one
worker process when a run begins, before the main process imports pandas and SciPy; the worker
imports matplotlib and the figure modules meanwhile and draws each figure as soon as its data
are known, while the main process reads logs, fits and writes the other outputs. The figure
code is the same as in-process, so the bytes are too.

Without a worker (``enabled=False``, or a platform that cannot start one) every figure is drawn
in-process when its result is asked for; a worker that dies leaves its figures to the main
process likewise.
"""

from __future__ import annotations

import weakref
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from typing import Any, TypeVar

from masking_lab.core.worker_processes import worker_pool

__all__ = ["FigurePool"]

T = TypeVar("T")


def _warm() -> None:
    """In the worker: load what drawing needs (matplotlib on Agg, the figure modules)."""
    import masking_lab.analysis.figures
    import masking_lab.analysis.lab_figures  # noqa: F401
    from masking_lab.formats.png_figure import pyplot

    pyplot()


class FigurePool:
    """Figures drawn in worker processes (or in-process, see the module docstring).

    Parameters
    ----------
    enabled : bool
        Start the worker (False: draw in-process when asked).

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
        self._enabled = enabled
        if enabled:
            self._add_lane()

    def _add_lane(self) -> bool:
        try:
            pool = worker_pool(1)  # ends with this process, even killed
            pool.submit(_warm)  # the worker starts now, not at the first figure
        except (OSError, NotImplementedError, RuntimeError):  # no processes here: in-process
            return False
        self._lanes.append((pool, []))
        # a run that fails before collecting its figures does not wait for them
        weakref.finalize(self, pool.shutdown, False, cancel_futures=True)
        return True

    def widen(self, workers: int) -> None:
        """Use up to ``workers`` worker processes (a large study's figures take seconds each;
        each is still drawn whole by one worker, so the bytes do not change)."""
        while self._enabled and len(self._lanes) < workers and self._add_lane():
            pass

    def submit(self, fn: Callable[..., T], /, *args: Any, **kwargs: Any) -> Callable[[], T]:
        """Start ``fn(*args, **kwargs)`` (a module-level ``fn``, picklable arguments; plain
        data keeps pandas out of the worker) in the least busy worker; returns a function
        giving its result (waiting for the worker, or drawing in-process)."""
        if not self._lanes:
            return lambda: fn(*args, **kwargs)
        pool, queued = min(self._lanes, key=lambda lane: sum(not f.done() for f in lane[1]))
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
        for pool, _ in self._lanes:
            pool.shutdown(wait=not cancel, cancel_futures=cancel)
        self._lanes = []
