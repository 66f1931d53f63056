"""Progress bars for long commands (*shell*), drawn by tqdm on stderr.

Shown on a terminal, quiet otherwise unless asked (``--progress``); ``--no-progress`` (or
``analyze --quiet``) silences them. Two kinds: :func:`count_bar` for a known number of items
(logs read, sets fitted), :func:`step_bar` for commands that report steps as text (``plan``,
``study``): the bar counts the steps and shows the current one.
"""

from __future__ import annotations

import sys
import weakref
from collections.abc import Callable
from typing import Any, TextIO

__all__ = ["add_progress_options", "close_open_bars", "count_bar", "progress_wanted", "step_bar"]

# The bars drawn and not yet closed, so an error message can first end their line.
_OPEN: weakref.WeakSet[Any] = weakref.WeakSet()


def close_open_bars() -> None:
    r"""Close every bar still drawn: what is printed next starts on a line of its own.

    Examples
    --------
    >>> import io
    >>> buf = io.StringIO()
    >>> step_bar("plan", True, buf)("schedule 1/3")
    >>> close_open_bars()
    >>> buf.getvalue().endswith("\n")
    True
    """
    for bar in list(_OPEN):
        bar.close()
        _OPEN.discard(bar)


def add_progress_options(p: Any) -> None:
    """``--progress`` / ``--no-progress`` (default: on a terminal only)."""
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--progress",
        dest="progress",
        action="store_true",
        default=None,
        help="show progress bars even when stderr is not a terminal",
    )
    g.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bars")


def progress_wanted(flag: bool | None, stream: TextIO | None = None) -> bool:
    """Whether to draw: the flag if given, else whether ``stream`` (stderr) is a terminal.

    Examples
    --------
    >>> import io
    >>> progress_wanted(None, io.StringIO()), progress_wanted(True, io.StringIO())
    (False, True)
    """
    if flag is not None:
        return bool(flag)
    s = stream if stream is not None else sys.stderr
    try:
        return bool(s.isatty())
    except (AttributeError, ValueError):
        return False


def count_bar(
    label: str, enabled: bool, stream: TextIO | None = None
) -> Callable[[int, int], None]:
    """A callback ``(done, total)`` that draws a bar; a no-op when not ``enabled``.

    Examples
    --------
    >>> import io
    >>> buf = io.StringIO()
    >>> show = count_bar("logs read", True, buf)
    >>> for i in range(1, 4):
    ...     show(i, 3)
    >>> "logs read" in buf.getvalue() and "3/3" in buf.getvalue()
    True
    """
    if not enabled:
        return lambda _done, _total: None
    from tqdm import tqdm

    state: dict[str, Any] = {}

    def show(done: int, total: int) -> None:
        bar = state.get("bar")
        if bar is None or bar.total != total:
            if bar is not None:
                bar.close()
            bar = state["bar"] = tqdm(
                total=total, desc=label, unit="", file=stream or sys.stderr, leave=True,
                dynamic_ncols=True, mininterval=0.2,
            )  # fmt: skip
            _OPEN.add(bar)
        bar.update(done - bar.n)
        if done >= total:
            bar.close()

    return show


def step_bar(
    label: str,
    enabled: bool,
    stream: TextIO | None = None,
    total: int | None = None,
    *,
    lines_when_off: bool = True,
) -> Callable[[str], None]:
    """A callback ``(message)`` counting steps, the message as the bar's text.

    Without ``enabled`` the messages are printed as lines (``label: message``), as ``plan``
    and ``study`` did before the bars, or dropped with ``lines_when_off=False`` (commands that
    printed no progress before: ``render``). With ``total`` the bar closes (ends its line) at
    the last step, so the command's own output starts on a fresh line.

    Examples
    --------
    >>> import io
    >>> buf = io.StringIO()
    >>> say = step_bar("plan", True, buf)
    >>> say("schedule 1/3"); say("schedule 2/3")
    >>> "schedule 2/3" in buf.getvalue()
    True
    """
    out = stream or sys.stderr
    if not enabled:
        if not lines_when_off:
            return lambda _msg: None
        return lambda msg: print(f"{label}: {msg}", file=out, flush=True)
    from tqdm import tqdm

    bar = tqdm(total=total, desc=label, unit=" steps", file=out, dynamic_ncols=True, leave=True)
    _OPEN.add(bar)

    def say(msg: str) -> None:
        bar.update(1)
        bar.set_postfix_str(msg)  # redraws, so the current step always shows
        if total is not None and bar.n >= total:
            bar.close()

    return say
