"""Worker processes that end with the process that started them (*shell*: processes and
signals; here, at the bottom layer, so that every layer's pools share one helper).

A ``ProcessPoolExecutor`` worker waits on its task queue for as long as that queue's pipe is
open, and a forked worker holds the pipe's write end itself. So when the run that started the
workers is killed (SIGKILL from a job scheduler or the kernel's out-of-memory killer runs no
shutdown), they sleep forever, each holding its copy of the run's memory and the run's stdout.
:func:`worker_pool` starts every worker with :func:`end_with_parent`: on Linux the kernel
kills the worker when its parent dies (``prctl(PR_SET_PDEATHSIG)``); elsewhere a thread in the
worker looks for its parent now and then and ends the worker once it is gone.

Ctrl-C at a terminal signals every process of the foreground group, the workers included. A
worker waiting for work only notes it (Python's handler printed each idle worker's
``KeyboardInterrupt`` traceback under the run's own "interrupted"); a task is interrupted as in
the calling process, so its own clean-up runs (a session zeroes its device); and the tasks
still queued for the worker are refused at once. SIGINT is held back while a pool forks its
workers, so none starts with Python's handler (:func:`worker_pool`). A failed run's pool is
interrupted and joined (:func:`cancel_pool`), and ``masking-lab`` does that to every pool still
open before it exits (:func:`cancel_open_pools`), so none is left running at the exit.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Generic, TypeVar

if TYPE_CHECKING:  # loaded when a pool is made: output folders only ask whether a pid runs
    from concurrent.futures import Future, ProcessPoolExecutor
    from multiprocessing.context import BaseContext

__all__ = [
    "Beside",
    "alive",
    "cancel_open_pools",
    "cancel_pool",
    "end_with_parent",
    "interruptible",
    "interrupts_held",
    "note_interrupts",
    "parent_death_signal",
    "rest_here",
    "result_or_here",
    "worker_pool",
]

A = TypeVar("A")
R = TypeVar("R")

_PR_SET_PDEATHSIG = 1  # <linux/prctl.h>
_POLL_S = 0.5  # the watching thread's look at its parent (where the kernel cannot be asked)


def end_with_parent(parent: int) -> None:
    """In a worker, first: end this process when process ``parent`` ends, even killed.

    Parameters
    ----------
    parent : int
        Process id of the process that started the pool.

    Notes
    -----
    The kernel's parent-death signal follows the thread that forked the worker; the pools
    of this package are made by their process's main thread. A worker whose parent is not
    ``parent`` (a fork server's child) is watched by a thread instead.

    Examples
    --------
    >>> pool = worker_pool(1)
    >>> pool.submit(os.getppid).result() == os.getpid()
    True
    >>> pool.shutdown()
    """
    armed = False
    if os.getppid() == parent:
        armed = _arm_parent_death_signal()
        if os.getppid() != parent:  # the parent died before the signal was armed
            os._exit(0)
    elif not alive(parent):
        os._exit(0)
    if not armed:
        threading.Thread(target=_watch_parent, args=(parent,), daemon=True).start()


def _arm_parent_death_signal() -> bool:
    arm = parent_death_signal(signal.SIGKILL)
    return arm is not None and arm()


def parent_death_signal(sig: int) -> Callable[[], bool] | None:
    """A function asking the kernel to send ``sig`` to the process that calls it when that
    process's parent ends (Linux ``prctl(PR_SET_PDEATHSIG)``); None where there is none.

    It is resolved here, so a child can call it between fork and exec (a ``preexec_fn``)
    without importing anything. It returns whether the kernel took the request.

    Examples
    --------
    >>> arm = parent_death_signal(signal.SIGTERM)
    >>> arm is None or callable(arm)
    True
    """
    try:
        import ctypes

        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):  # no prctl: not Linux
        return None

    def arm() -> bool:
        return bool(prctl(_PR_SET_PDEATHSIG, sig, 0, 0, 0) == 0)

    return arm


def alive(pid: int) -> bool:
    """Whether process ``pid`` runs (a zombie, ended and not yet reaped, does not; nor does a
    pid no system has). On Windows every pid counts as running: there ``os.kill(pid, 0)``
    would end the process instead of asking about it.

    Examples
    --------
    >>> alive(os.getpid()), alive(2**70)
    (True, False)
    """
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except (ProcessLookupError, OverflowError):  # gone, or a pid no system has
        return False
    except PermissionError:  # someone else's process: it exists
        pass
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as fh:
            return fh.read().rsplit(")", 1)[1].split()[0] != "Z"
    except (OSError, IndexError):  # no /proc here: existing is all that can be known
        return True


def _watch_parent(parent: int) -> None:
    # A child of ``parent`` is re-parented when it dies (no pid-reuse question); another
    # process's child can only ask whether ``parent`` still exists.
    direct = os.getppid() == parent
    while (os.getppid() == parent) if direct else alive(parent):
        time.sleep(_POLL_S)
    os._exit(0)


def _start_worker(parent: int, initializer: Callable[..., object] | None, args: tuple) -> None:
    end_with_parent(parent)
    # Idle, a worker only notes Ctrl-C (each task turns it back on: interruptible); a SIGINT
    # that came while the pool forked this worker, held back since, is noted here.
    note_interrupts()
    if hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # A worker dies of SIGTERM, whatever handler it inherited: when a worker is killed, the
    # pool terminates the others with it, and a forked worker blocked on its full result pipe
    # ran an inherited Python handler (device.safety's), whose SystemExit the pool's sending
    # code swallows before it blocks again: the run hung.
    for sig in (signal.SIGTERM, signal.SIGHUP) if hasattr(signal, "SIGHUP") else (signal.SIGTERM,):
        signal.signal(sig, signal.SIG_DFL)
    if initializer is not None:
        initializer(*args)


def worker_pool(
    max_workers: int,
    *,
    mp_context: BaseContext | None = None,
    initializer: Callable[..., object] | None = None,
    initargs: tuple[Any, ...] = (),
) -> ProcessPoolExecutor:
    """A ``ProcessPoolExecutor`` whose workers end with this process (see the module docstring).

    Parameters
    ----------
    max_workers : int
        Worker processes.
    mp_context : multiprocessing context, optional
        How workers start (the platform's default when None).
    initializer, initargs
        Run in each worker after it has arranged to end with this process (and set SIGTERM
        and SIGHUP back to their default action, so that the pool can end it).

    Returns
    -------
    ProcessPoolExecutor
        Use it as any executor (``submit``, ``map``, ``shutdown``, ``with``); a ``with``
        block left by an exception ends the pool with :func:`cancel_pool`, not after every
        queued task.

    Examples
    --------
    >>> with worker_pool(2) as pool:
    ...     list(pool.map(abs, [-1, 2, -3]))
    [1, 2, 3]
    """
    pool = _pool_class()(
        max_workers=max_workers,
        mp_context=mp_context,
        initializer=_start_worker,
        initargs=(os.getpid(), initializer, initargs),
    )
    _open_pools.add(pool)
    return pool


#: Every pool made here and not yet shut down with a wait (see :func:`cancel_open_pools`); held
#: strongly: a pool collected unclosed would shut down on its own thread, racing the exit.
_open_pools: set[ProcessPoolExecutor] = set()


def cancel_open_pools() -> None:
    """:func:`cancel_pool` on every pool of this process that is still open: at the end of a
    run, whatever way it ends (``masking-lab`` calls it before exiting).

    A pool its run left open (an interrupted run's log readers, whose reading had not begun)
    would still be running when the interpreter exits, where Python 3.11's exit handler races
    a pool thread that shuts down meanwhile (an ``OSError`` traceback after the run's last
    line).

    Examples
    --------
    In a process of its own (it stops every pool of the process that calls it):

    >>> import subprocess, sys
    >>> code = '''
    ... from masking_lab.core.worker_processes import cancel_open_pools, worker_pool
    ... pool = worker_pool(1)
    ... pool.submit(abs, -1)
    ... cancel_open_pools()
    ... try:
    ...     pool.submit(abs, -1)
    ... except RuntimeError as exc:
    ...     print(exc)
    ... '''
    >>> subprocess.run([sys.executable, "-c", code], capture_output=True, text=True).stdout.strip()
    'cannot schedule new futures after shutdown'
    """
    for pool in list(_open_pools):
        cancel_pool(pool)


@functools.cache
def _pool_class() -> type[ProcessPoolExecutor]:
    """``ProcessPoolExecutor`` whose tasks take Ctrl-C as the caller does (the class is made
    when the first pool is: ``concurrent.futures`` loads only then)."""
    from concurrent.futures import ProcessPoolExecutor

    class WorkerPool(ProcessPoolExecutor):
        def submit(self, fn: Callable[..., R], /, *args: Any, **kwargs: Any) -> Future[R]:
            # A pool forks its workers in a submit (the first, or each, by start method): a
            # child starts with this thread's signal mask, so SIGINT is held back until the
            # child has set it aside (_start_worker). Held here, it arrives after the submit.
            with interrupts_held():
                return super().submit(interruptible, fn, *args, **kwargs)

        def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
            super().shutdown(wait, cancel_futures=cancel_futures)
            if wait:  # its thread and workers joined: nothing of it runs any more
                _open_pools.discard(self)

        def __exit__(self, exc_type: Any, *exc: Any) -> None:
            # A block that fails does not wait for the rest of its tasks (the executor's own
            # exit ran every queued one first): they are interrupted or cancelled.
            if exc_type is None:
                self.shutdown(wait=True)
            else:
                cancel_pool(self)

    return WorkerPool


@contextmanager
def interrupts_held() -> Iterator[list[object]]:
    """Ctrl-C held back for the block, then delivered: around forking a worker.

    SIGINT is blocked in this thread, so a process forked in the block starts with it held
    back until it has set up its own handler (:func:`note_interrupts`). In this process,
    another thread may still take the signal, and Python then runs the handler in the main
    thread at once, inside fork's after-fork callbacks, where a ``KeyboardInterrupt`` prints
    an "Exception ignored" traceback; so, in the main thread, the handler only notes it for
    the block, and the ``KeyboardInterrupt`` (or whatever the handler does) comes after it.

    Yields the list in which the block's handler notes each SIGINT it took (empty: none yet;
    a signal that another thread takes reaches it only when that thread next runs).

    Examples
    --------
    >>> with interrupts_held():
    ...     signal.SIGINT in signal.pthread_sigmask(signal.SIG_BLOCK, set())
    True
    """
    came: list[object] = []
    if not hasattr(signal, "pthread_sigmask"):
        yield came
        return
    handler = None  # also when a handler not set from Python is there: it stays
    if threading.current_thread() is threading.main_thread() and signal.getsignal(signal.SIGINT):
        handler = signal.signal(signal.SIGINT, lambda *_: came.append(True))
    before = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield came
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, before)  # one held back arrives here
        if handler is not None:
            signal.signal(signal.SIGINT, handler)
            if came:
                signal.raise_signal(signal.SIGINT)


def note_interrupts() -> None:
    """In a worker, when it starts: Ctrl-C only notes, quietly, that the run is ending (no
    ``KeyboardInterrupt``, no traceback); :func:`interruptible` then refuses further tasks.

    Examples
    --------
    >>> with worker_pool(1) as pool:  # its workers call it when they start
    ...     os.kill(pool.submit(os.getpid).result(), signal.SIGINT)  # Ctrl-C, the worker idle
    ...     type(pool.submit(abs, -1).exception()).__name__  # a task after it is refused
    'KeyboardInterrupt'
    """
    global _interrupted
    _interrupted = False  # not a Ctrl-C of the process it was forked from
    signal.signal(signal.SIGINT, _note_interrupt)
    sys.unraisablehook = _unraisable_in_worker


def _unraisable_in_worker(unraisable: Any) -> None:
    # A Ctrl-C that lands in a callback (a weakref's, run by garbage collection in the middle
    # of a task) cannot interrupt the task: Python prints it as "Exception ignored" and goes
    # on. The worker has noted it (_interrupt_task), so it refuses the tasks after this one.
    if not isinstance(unraisable.exc_value, KeyboardInterrupt):
        sys.__unraisablehook__(unraisable)


def interruptible(fn: Callable[..., R], *args: Any, **kwargs: Any) -> R:
    """In a worker: ``fn(*args, **kwargs)`` with Ctrl-C raising ``KeyboardInterrupt`` in it, as
    in the calling process (its own clean-up runs). After a Ctrl-C (in a task or while idle)
    the worker refuses the tasks still queued for it: the run is ending, and its pool's
    shutdown need not wait for them (a ``plan`` chunk takes seconds).

    :func:`worker_pool`'s workers run every task through it.

    Examples
    --------
    >>> interruptible(pow, 2, 3)
    8
    """
    if _interrupted:
        raise KeyboardInterrupt
    idle = signal.signal(signal.SIGINT, _interrupt_task)
    try:
        return fn(*args, **kwargs)
    except KeyboardInterrupt:
        _note_interrupt()
        raise
    finally:
        signal.signal(signal.SIGINT, idle)


_interrupted = False  # in a worker: Ctrl-C came (see interruptible)


def _note_interrupt(*_signal: object) -> None:
    global _interrupted
    _interrupted = True


def _interrupt_task(*_signal: object) -> None:
    _note_interrupt()
    raise KeyboardInterrupt


def rest_here(results: Iterator[R], fn: Callable[[A], R], items: Sequence[A]) -> Iterator[R]:
    """The results of ``pool.map(fn, items)``, in order, also when a worker dies.

    A worker killed from outside (the kernel's out-of-memory killer, say) breaks the whole
    pool: every result not yet returned raises ``BrokenProcessPool``. From the first of them
    on, ``fn`` is called on the remaining items in this process, so the caller gets every
    result, computed by the same function, instead of a traceback.

    Parameters
    ----------
    results : iterator
        ``pool.map(fn, items)``, already started (the workers run while the caller does other
        work).
    fn : callable
        The mapped function (module-level, as the pool needs).
    items : sequence
        The mapped items.

    Yields
    ------
    object
        ``fn(item)`` for each item, in order.

    Examples
    --------
    >>> with worker_pool(2) as pool:
    ...     list(rest_here(pool.map(abs, [-1, 2, -3]), abs, [-1, 2, -3]))
    [1, 2, 3]
    """
    from concurrent.futures.process import BrokenProcessPool

    done = 0
    try:
        for result in results:
            yield result
            done += 1
    except BrokenProcessPool:
        for item in items[done:]:
            yield fn(item)


def cancel_pool(pool: ProcessPoolExecutor) -> None:
    """End ``pool`` without waiting for its work (a failed or interrupted run): its queued
    tasks cancelled, a task still running interrupted as by Ctrl-C (:func:`interruptible`),
    then its workers and its thread joined.

    Nothing of the pool is left running when the interpreter exits: Python 3.11's exit
    handler wakes every pool's thread without a lock, and one still closing its pipes (a
    pool shut down without waiting) made that print an ``OSError`` traceback after the run's
    last line. Interrupting, rather than killing, the workers never cuts a result in half in
    the pipe, which would leave the pool's thread waiting for the rest.

    Examples
    --------
    >>> pool = worker_pool(1)
    >>> busy = pool.submit(time.sleep, 600)
    >>> cancel_pool(pool)  # at once, not after 600 s
    >>> busy.done()  # interrupted, or cancelled before it started
    True
    """
    # Interrupted first: from then on a worker refuses whatever reaches it, so the shutdown's
    # wait is short. A worker not yet reaped still has its pid.
    for worker in list((getattr(pool, "_processes", None) or {}).values()):
        if worker.is_alive():
            with contextlib.suppress(OSError):
                os.kill(worker.pid, signal.SIGINT)
    pool.shutdown(wait=True, cancel_futures=True)


def result_or_here(future: Future[R], fn: Callable[..., R], *args: Any) -> R:
    """``future.result()`` of ``pool.submit(fn, *args)``, or, when the pool broke because a
    worker died (see :func:`rest_here`), ``fn(*args)`` computed in this process.

    Examples
    --------
    >>> with worker_pool(1) as pool:
    ...     result_or_here(pool.submit(pow, 2, 3), pow, 2, 3)
    8
    """
    from concurrent.futures.process import BrokenProcessPool

    try:
        return future.result()
    except BrokenProcessPool:
        return fn(*args)


class Beside(Generic[R]):
    """``fn(*args)`` computed by a worker process of its own while the caller goes on.

    :meth:`result` waits for the worker and ends it. Where no worker can start, or when the
    worker died (killed for memory, say), ``fn(*args)`` is computed in this process instead:
    the same function, so the same result. With ``worker=False`` (no core would be free for
    it) it is computed here at once, as a plain call would. ``fn`` must be a module-level
    function and its arguments and result picklable. Use it as a context manager, so that a
    caller that fails before asking for the result does not leave the worker behind.

    Examples
    --------
    >>> with Beside(pow, 2, 10) as power:
    ...     power.result()
    1024
    >>> Beside(pow, 2, 3, worker=False).result()  # computed in the constructor
    8
    """

    def __init__(self, fn: Callable[..., R], *args: Any, worker: bool = True) -> None:
        self._fn, self._args = fn, args
        self._pool: ProcessPoolExecutor | None = None
        self._future: Future[R] | None = None
        self._done: tuple[R] | None = None
        if worker:
            try:
                self._pool = worker_pool(1)
                self._future = self._pool.submit(fn, *args)
                return
            except (OSError, NotImplementedError, RuntimeError):  # no process to start
                self.close()
        self._done = (fn(*args),)

    def result(self) -> R:
        """``fn(*args)``, from the worker or computed here (see the class docstring).

        Raises
        ------
        Exception
            Whatever ``fn`` raised, in the worker or here.
        """
        if self._done is not None:
            return self._done[0]
        assert self._future is not None  # started in the constructor, or _done is set
        try:
            return result_or_here(self._future, self._fn, *self._args)
        finally:
            self.close()

    def close(self) -> None:
        """End the worker (waiting for its task, if that still runs)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        self._pool = None

    def __enter__(self) -> Beside[R]:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
