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
before numpy loads (the command line sets those too, below). ``analyze``'s statistics run on
one thread too: their products are small, and beside the figure workers a second OpenBLAS
thread spin-waited (at 10,000 sessions 5.3 → 3.5 s CPU after the read); one thread also sums a
long dot product in one order on any machine.

A BLAS thread costs CPU even when it has no work. OpenBLAS's server threads spin for about
2**28 cycles (~0.1 s) each time they are started before they sleep, and OpenBLAS stops them
before every ``fork`` of the process (``subprocess`` with a ``preexec_fn`` included); the next
call that sets a thread count, even to one (a :func:`one_blas_thread` block's start or end),
starts new ones, which spin again. A demo session run on the C firmware's host build forks
once, so each of its 30 sessions cost ~0.1 s of CPU in such spins (the demo took 0.8–2.8 s
less of its ~20 s of CPU without them, in three pairs; session 49). So the ``masking-lab``
command asks for one BLAS thread per process before numpy loads
(:func:`one_blas_thread_from_start`, an environment default that a user's own setting
overrides: OpenBLAS then starts no thread at all), pool workers limit the pools already loaded
for good (:func:`one_blas_thread_here`), and :func:`one_blas_thread` leaves pools that are at
one thread already alone.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, MutableMapping
from contextlib import contextmanager

__all__ = [
    "BLAS_THREAD_VARIABLES",
    "one_blas_thread",
    "one_blas_thread_from_start",
    "one_blas_thread_here",
]

#: Read once, when the library loads: OpenBLAS (numpy's and SciPy's wheels) and MKL (conda's).
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


@contextmanager
def one_blas_thread() -> Iterator[None]:
    """Run the block with every BLAS pool of this process limited to one thread.

    The previous limits come back when the block ends (also on an exception). Pools already
    at one thread (the ``masking-lab`` command's, a pool worker's) are left alone: after a
    fork, asking OpenBLAS for one thread again starts a fresh, spinning one.

    Examples
    --------
    >>> from threadpoolctl import threadpool_info
    >>> with one_blas_thread():
    ...     {p["num_threads"] for p in threadpool_info() if p["user_api"] == "blas"} <= {1}
    True
    """
    from threadpoolctl import threadpool_limits

    if _at_one_thread():
        yield
        return
    with threadpool_limits(limits=1, user_api="blas"):
        yield


def _at_one_thread() -> bool:
    """Whether every BLAS pool loaded here has at most one thread (~0.5 ms to ask; asking
    starts no thread)."""
    from threadpoolctl import threadpool_info

    return all(p["num_threads"] <= 1 for p in threadpool_info() if p["user_api"] == "blas")


def one_blas_thread_here() -> None:
    """Limit every BLAS pool loaded in this process to one thread, for the rest of the process.

    For a pool worker's ``initializer``: its workers already fill the cores, and a
    :func:`one_blas_thread` block inside it then ends at one thread, starting no new (spinning)
    BLAS threads.

    Examples
    --------
    In a process of its own (it changes the process it runs in):

    >>> import subprocess, sys
    >>> code = (
    ...     "from masking_lab.core.blas_threads import one_blas_thread_here; "
    ...     "import numpy; from threadpoolctl import threadpool_info; one_blas_thread_here(); "
    ...     "print({p['num_threads'] for p in threadpool_info() if p['user_api'] == 'blas'})"
    ... )
    >>> subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout
    '{1}\\n'
    """
    from threadpoolctl import threadpool_limits

    if not _at_one_thread():
        threadpool_limits(limits=1, user_api="blas")


def one_blas_thread_from_start(
    environ: MutableMapping[str, str] | None = None,
) -> dict[str, str]:
    """Ask the BLAS libraries this process has not loaded yet for one thread each.

    Sets each of :data:`BLAS_THREAD_VARIABLES` that is unset to ``"1"`` in ``environ`` (the
    process's environment by default, where child processes inherit it). A library already
    loaded is not affected (use :func:`one_blas_thread_here`), and a user's own value is kept:
    ``OPENBLAS_NUM_THREADS=4 masking-lab ...`` runs with four.

    Parameters
    ----------
    environ : mutable mapping, optional
        The environment to change; ``os.environ`` when None.

    Returns
    -------
    dict
        The variables set (empty when the user had set them all).

    Examples
    --------
    >>> one_blas_thread_from_start({"MKL_NUM_THREADS": "4"})
    {'OPENBLAS_NUM_THREADS': '1'}
    """
    env = os.environ if environ is None else environ
    made = {name: "1" for name in BLAS_THREAD_VARIABLES if not env.get(name)}
    env.update(made)
    return made
