"""A second worker forked from a warm first one (*shell*: processes and pipes).

:class:`~masking_lab.analysis.figure_pool.FigurePool`'s worker spends ~0.4 s of CPU importing
matplotlib before its first figure. A second worker forked from this process would import it
again; a :class:`ForkedLane` is forked from the first worker once its import is done, so two
workers draw for one import. Tasks reach it over a queue this process made before the first
worker was forked (the first worker, and so the second, inherit it); results come back in
order over another.

The second worker ends with the first (which ends with this process), and the first waits for
it at its own end, so that its CPU time is counted with the run's. A lane whose worker
is gone (never forked, killed, or the first worker died first) gives each of its tasks back to
be run in this process: :meth:`ForkedLane.result` raises :class:`LaneGone`.
"""

from __future__ import annotations

import multiprocessing
import multiprocessing.util
import os
import pickle
import queue
import time
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from masking_lab.core.worker_processes import (
    alive,
    end_with_parent,
    interruptible,
    interrupts_held,
    note_interrupts,
)

__all__ = ["ForkedLane", "LaneGone", "fork_second"]

_POLL_S = 0.2  # how often a wait for a result looks whether the worker still exists
_REAP_S = 2.0  # how long the first worker waits for the second at its end (it ends in ms)
_LANE: ForkedLane | None = None  # the lane being set up: what the first worker inherits


class LaneGone(Exception):
    """The lane's worker is gone: run the task here."""


class ForkedLane:
    """The queues of a second worker that :func:`fork_second` forks inside the first.

    Make it before the first worker is forked (with the ``fork`` start method), then have
    that worker run :func:`fork_second` once it is warm; ``forked`` is the future of that call.

    Examples
    --------
    >>> lane = ForkedLane.make()
    >>> lane is None or lane.busy == 0
    True
    """

    def __init__(self, context: Any) -> None:
        self._tasks = context.Queue()
        self._tasks.cancel_join_thread()  # exiting never waits on a worker that is gone
        self._results = context.Queue()
        self._sent = 0
        self._done: dict[int, tuple[bool, Any]] = {}  # kept: a result may be asked again
        self._gone = False
        self.forked: Future[int | None] | None = None

    @classmethod
    def make(cls) -> ForkedLane | None:
        """A lane, or None where processes cannot be forked (then use separate workers)."""
        global _LANE
        if "fork" not in multiprocessing.get_all_start_methods():
            return None
        try:
            _LANE = cls(multiprocessing.get_context("fork"))
        except OSError:
            return None
        return _LANE

    @property
    def busy(self) -> int:
        """Tasks sent and not yet answered (answers that have arrived are counted as such)."""
        self._drain(block=False)
        return self._sent - len(self._done)

    def submit(self, fn: Callable[..., Any], args: tuple, kwargs: dict) -> int:
        """Queue ``fn(*args, **kwargs)``; its ticket for :meth:`result`."""
        if self._gone:
            raise LaneGone
        ticket = self._sent
        self._tasks.put((ticket, fn, args, kwargs))
        self._sent += 1
        return ticket

    def result(self, ticket: int) -> Any:
        """The result of task ``ticket`` (its exception raised), as often as asked; LaneGone
        if the worker is gone without answering it."""
        while ticket not in self._done:
            if self._gone:
                raise LaneGone
            if not self._drain(block=True) and not self._worker_alive():
                self._gone = True
        ok, value = self._done[ticket]
        if ok:
            return value
        raise value

    def close(self) -> None:
        """Let the worker end after the tasks sent (it also ends with the first worker)."""
        if not self._gone:
            self._tasks.put(None)
        self._gone = True
        self._tasks.close()  # this process's feeder thread ends once the queue is written

    def _drain(self, *, block: bool) -> bool:
        """Take the answers that have arrived (waiting a little for one with ``block``)."""
        got = False
        while True:
            try:
                payload = self._results.get(block=block and not got, timeout=_POLL_S)
            except queue.Empty:
                return got
            ticket, ok, value = pickle.loads(payload)
            self._done[ticket] = (ok, value)
            got = True

    def _worker_alive(self) -> bool:
        forked = self.forked
        if forked is None or not forked.done():
            # the first worker is still warming up; if it died, its future says so
            return forked is not None
        try:
            pid = forked.result()
        except Exception:  # the first worker died or failed before forking: nobody serves
            return False
        return pid is not None and alive(pid)


def fork_second() -> int | None:
    """In the first worker, once warm: fork the second, which serves the lane made before
    this worker was forked; its pid (None when there is no lane or the fork fails)."""
    lane = _LANE
    if lane is None:
        return None
    first = os.getpid()
    try:
        # Ctrl-C while forking reaches the second worker once it only notes it (as the
        # first worker does while idle): a KeyboardInterrupt raised in its start-up could
        # land in a callback and print a traceback.
        with interrupts_held():
            pid = os.fork()
            if pid == 0:
                note_interrupts()
    except OSError:
        return None
    if pid == 0:  # the second worker
        try:
            end_with_parent(first)
            _serve(lane)
        finally:
            os._exit(0)
    # Waited for when this worker ends, so that its CPU time is counted with this one's (by
    # the run's wait4 and /usr/bin/time): not waited for, it was re-parented and never counted.
    multiprocessing.util.Finalize(None, _reap, args=(pid,), exitpriority=10)
    return pid


def _reap(pid: int, timeout_s: float = _REAP_S) -> None:
    """Wait (at most ``timeout_s``) for the second worker, which ends once the lane is
    closed (:meth:`ForkedLane.close`, before the first worker's pool is shut down); one still
    running then ends with this process, as before."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            done, _ = os.waitpid(pid, os.WNOHANG)
        except ChildProcessError:  # already waited for
            return
        if done or time.monotonic() > deadline:
            return
        time.sleep(0.002)


def _serve(lane: ForkedLane) -> None:
    while True:
        task = lane._tasks.get()
        if task is None:
            break
        ticket, fn, args, kwargs = task
        try:
            answer = (ticket, True, interruptible(fn, *args, **kwargs))
        except BaseException as exc:  # the caller re-raises it, as a worker pool would
            answer = (ticket, False, exc)
        try:
            payload = pickle.dumps(answer)
        except Exception as exc:  # an exception that cannot travel: its text does
            payload = pickle.dumps((ticket, False, RuntimeError(f"{type(exc).__name__}: {exc}")))
        lane._results.put(payload)
    lane._results.close()
    lane._results.join_thread()  # every answer written before this process ends
