"""Real-time priority for the next trial's placement (*shell*: changes the thread's scheduler).

Between a participant's answer and the next stimulus the session updates the procedure: for
QUEST+ and the functional procedure a posterior update and an entropy placement of 1–8 ms of
CPU. One BLAS thread (:mod:`masking_lab.core.blas_threads`) keeps a busy core from stalling
that product, but the time-sharing scheduler still hands the core to whatever else is runnable:
on a two-core machine shared with a figure, a browser or an analysis, the 99th percentile of
the step measured 14–23 ms for 3 ms of CPU. Linux's autogroups make ``nice`` useless against
processes started from another terminal; a real-time policy is not. The thread runs
``SCHED_RR`` at the lowest real-time priority only while it computes the placement, and goes
back to its previous policy at once, so a loop that never ends cannot keep the core (the kernel
also reserves 5 % of every second for other tasks).

The policy needs ``CAP_SYS_NICE`` or an ``rtprio`` limit of at least 1
(``/etc/security/limits.conf``: ``@lab - rtprio 1``). Without either, the step runs at normal
priority and :func:`placement_priority_note` says how to grant it; nothing else changes.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["placement_priority", "placement_priority_note", "realtime_permitted"]

_SCHED_RR = getattr(os, "SCHED_RR", None)


def realtime_permitted() -> bool:
    """Whether this thread may switch to ``SCHED_RR`` (tried once, then put back).

    Returns
    -------
    bool
        False on systems without POSIX real-time scheduling or without the permission.

    Examples
    --------
    >>> realtime_permitted() in (True, False)
    True
    """
    if _SCHED_RR is None or not hasattr(os, "sched_setscheduler"):
        return False
    try:
        _leave(_enter_realtime())
    except OSError:
        return False
    return True


def _enter_realtime() -> tuple[int, os.sched_param]:
    """Switch the calling thread to SCHED_RR at its lowest priority; the policy it had."""
    previous = (os.sched_getscheduler(0), os.sched_getparam(0))
    lowest = os.sched_get_priority_min(_SCHED_RR)  # type: ignore[arg-type]
    os.sched_setscheduler(0, _SCHED_RR, os.sched_param(lowest))  # type: ignore[arg-type]
    return previous


def _leave(previous: tuple[int, os.sched_param]) -> None:
    os.sched_setscheduler(0, *previous)


@contextmanager
def placement_priority(enabled: bool = True) -> Iterator[None]:
    """Run the block (one procedure update) at the lowest real-time priority when permitted.

    Parameters
    ----------
    enabled : bool
        False runs the block unchanged: a simulated session in virtual time has no participant
        waiting and thousands of updates, so it never asks.

    Notes
    -----
    Applies to the calling thread only (Linux ``sched_setscheduler(0, …)``), which is the thread
    that computes the placement: BLAS runs on that thread alone during a session. A refusal
    (no permission, or a kernel or container without real-time scheduling) leaves the block at
    normal priority: the priority shortens a pause, it never stops a session.

    Examples
    --------
    >>> with placement_priority():
    ...     level = 1.0 + 1.0
    >>> os.sched_getscheduler(0) == os.SCHED_OTHER
    True
    """
    if not enabled or _SCHED_RR is None or not hasattr(os, "sched_setscheduler"):
        yield
        return
    try:
        previous = _enter_realtime()
    except OSError:
        yield
        return
    try:
        yield
    finally:
        _leave(previous)


def placement_priority_note() -> str:
    """One line for the experimenter: the priority the placement will run at, and how to raise it.

    Returns
    -------
    str
        ``"placement: real-time priority (SCHED_RR)"`` or the normal-priority line with the way
        to grant the permission.

    Examples
    --------
    >>> placement_priority_note().startswith("placement: ")
    True
    """
    if realtime_permitted():
        return "placement: real-time priority (SCHED_RR) while the next trial is computed"
    return (
        "placement: normal priority (no permission for SCHED_RR); a busy machine can delay the "
        "next trial by tens of ms. Grant it with an rtprio limit of 1 for the session's user "
        "(/etc/security/limits.conf) or CAP_SYS_NICE: see docs/sessions.md"
    )
