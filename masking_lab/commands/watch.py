"""``masking-lab watch LOG``: a live view of a running session, read from its log as it grows.

Show the session's participant and protocol, the sets and trials done and left, the current
set's track so far (or its QUEST+ posterior) and every fault, redrawn whenever the log grows.
Ends when the session's end record appears, on Ctrl-C, or at once with --once. Reads only:
the session is never disturbed (the log is not locked).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TextIO

from masking_lab.commands.options import command_texts


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("watch", **command_texts(__doc__))
    p.add_argument("log", metavar="LOG", help="session log (.jsonl) of a running session")
    p.add_argument("--once", action="store_true", help="show the log as it is now and exit")
    p.add_argument(
        "--interval",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds between looks at the log (default 1)",
    )
    p.add_argument(
        "--width", type=int, default=60, metavar="N", help="trials shown in the track (default 60)"
    )
    p.set_defaults(handler=run)


def run(args: argparse.Namespace) -> int:
    if not args.interval > 0:
        from masking_lab.core.errors import MaskingLabError

        raise MaskingLabError(f"--interval must be > 0 s, got {args.interval}")
    try:
        return follow(
            Path(args.log),
            once=args.once,
            width=args.width,
            wait=lambda: time.sleep(args.interval),
        )
    except KeyboardInterrupt:
        print("\nwatch: stopped (the session goes on)", file=sys.stderr)
        return 0


def follow(
    path: Path,
    *,
    once: bool = False,
    width: int = 60,
    wait: Callable[[], None] = lambda: time.sleep(1.0),
    stream: TextIO | None = None,
) -> int:
    """Show the log, then redraw whenever it grows until its ``session_end`` record appears.

    ``wait`` is called between looks (the command sleeps; tests append records instead), so
    nothing here depends on the wall clock. Returns 0.
    """
    from masking_lab.core.errors import LogError
    from masking_lab.formats.session_log import read_log
    from masking_lab.session.watch_view import watch_view

    out = stream or sys.stdout
    tty = bool(getattr(out, "isatty", lambda: False)())
    last_size = -1
    shown: list[str] = []
    while True:
        try:
            size = path.stat().st_size
        except OSError as exc:
            raise LogError(f"{path}: cannot read the session log ({exc.strerror or exc})") from exc
        if size != last_size:
            log = read_log(path)  # a torn last line (a record being written) is left out
            lines = watch_view(log, width=width)
            if lines != shown:
                if tty:
                    out.write("\x1b[H\x1b[2J")  # redraw in place on a terminal
                elif shown:
                    out.write("\n")
                out.write("\n".join(lines) + "\n")
                out.flush()
                shown = lines
            last_size = size
            if once or log.ended:
                return 0
        elif once:
            return 0
        wait()
