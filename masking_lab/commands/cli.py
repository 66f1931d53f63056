"""The ``masking-lab`` command line.

Each sub-command lives in ``masking_lab/commands/<name>.py`` and exposes
``register(subparsers)``; heavy imports happen inside the command's handler so that
``masking-lab --help`` stays fast and works without optional extras.
"""

from __future__ import annotations

import argparse
import gc
import importlib
import sys

from masking_lab import __version__
from masking_lab.commands.progress_bars import close_open_bars
from masking_lab.core.blas_threads import one_blas_thread_from_start
from masking_lab.core.errors import MaskingLabError

# Order is the order shown by --help.
COMMANDS = (
    "validate",
    "run",
    "resume",
    "watch",
    "emulate",
    "device",
    "analyze",
    "status",
    "fit",
    "usertest-report",
    "solve",
    "render",
    "gamut",
    "plan",
    "study",
    "demo",
)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="masking-lab",
        description="Tactile masking psychophysics after Ryu et al. (2020): run 3IFC threshold "
        "sessions, analyse them, fit masking functions and render masking-compensated scenes.",
    )
    parser.add_argument("--version", action="version", version=f"masking-lab {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMANDS:
        # A command with a hyphen lives in a module with an underscore (usertest-report).
        module = importlib.import_module(f"masking_lab.commands.{name.replace('-', '_')}")
        module.register(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.handler(args) or 0)
    except MaskingLabError as exc:
        close_open_bars()  # the message on a line of its own, not after a bar's text
        print(f"masking-lab {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        close_open_bars()
        print(f"masking-lab {args.command}: interrupted", file=sys.stderr)
        return 130


def console_main() -> int:
    """The ``masking-lab`` command: :func:`main` on ``sys.argv``, then a quick exit.

    What the run loaded and made lives until the process ends, so it is frozen out of the
    interpreter's last garbage collections (:func:`gc.freeze`): after an analysis those visit
    every object of pandas, SciPy and matplotlib and took ~0.12 s of a 1.4 s run. Everything is
    still released as at any exit (files closed, ``atexit`` handlers run); only objects in
    reference cycles are left to the operating system, as every exit leaves the memory.
    :func:`main` itself (called by the tests, many times in one process) does not freeze.

    Before anything loads numpy, the run asks for one BLAS thread per process
    (:func:`~masking_lab.core.blas_threads.one_blas_thread_from_start`; a user's own
    ``OPENBLAS_NUM_THREADS`` or ``MKL_NUM_THREADS`` is kept). Every heavy step already runs
    on one BLAS thread, in processes that fill the cores; a second thread only spun: ~0.1 s
    of CPU each time OpenBLAS started it, after each of a run's forks.

    Returns
    -------
    int
        The exit status: 0, 2 on a usage or input error, 130 when interrupted.

    Examples
    --------
    >>> import subprocess, sys
    >>> code = "from masking_lab.commands.cli import console_main; console_main()"
    >>> done = subprocess.run([sys.executable, "-c", code, "--version"], capture_output=True)
    >>> done.stdout.decode().startswith("masking-lab ")
    True
    """
    one_blas_thread_from_start()
    try:
        code = main()
    finally:
        # A pool an interrupted run left open (its readers, say) is stopped and joined now,
        # not raced by the interpreter's exit (core/worker_processes.cancel_open_pools).
        from masking_lab.core.worker_processes import cancel_open_pools

        cancel_open_pools()
    gc.freeze()
    return code


if __name__ == "__main__":
    sys.exit(console_main())
