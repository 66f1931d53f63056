"""One BLAS thread for a session, a plan or an analysis's statistics (*shell*: changes the
process's thread pools; here, at the bottom layer, so that every layer shares one helper).

A trial's placement multiplies one posterior by the likelihood table: a product of a few
million flops that one thread finishes in about a millisecond. OpenBLAS splits it over two
threads, and when the other core is busy (a browser, a figure, another analysis) the second
thread's wake-up stalls the trial 7 → 50–84 ms, a pause a participant can feel. ``plan``'s
batch products ((tracks × 131) · (131 × 131) per trial) are small too: on a shared two-core
machine its QUEST+ simulation took 2.9 s CPU on one thread and 8.4 s on two (spin-waits), 9 s
wall against 27 s. threadpoolctl is the maintained way to limit the BLAS/OpenMP pools already
loaded, whatever the build (OpenBLAS, MKL, BLIS), without environment variables that must be set
before numpy loads. ``analyze``'s statistics run on one thread too: their products are small,
and beside the figure workers a second OpenBLAS thread spin-waited (at 10,000 sessions 5.3 →
3.5 s CPU after the read); one thread also sums a long dot product in one order on any machine.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["one_blas_thread"]


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with every BLAS pool of this process limited to one thread.

    The previous limits come back when the block ends (also on an exception).

    Examples
    --------
    >>> from threadpoolctl import threadpool_info
    >>> with one_blas_thread():
    ...     {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} <= {1}
    True
    """
    from threadpoolctl import threadpool_limits

    with threadpool_limits(limits=1, user_api="blas"):
        yield
