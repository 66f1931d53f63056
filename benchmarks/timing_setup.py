"""Set a source tree up to be timed as an installed package runs: its bytecode compiled, and
its ``masking-lab`` command started through the console-script entry point it declares.

``pip install`` compiles every module's bytecode, and Python writes it on the first import
anyway; a benchmark run from a source tree under ``PYTHONDONTWRITEBYTECODE=1`` (as some
sandboxes and CI images set) would instead recompile ~200 masking_lab modules on every run,
about 0.3 s that no user pays. Both trees of a before/after comparison are compiled alike.
"""

from __future__ import annotations

import compileall
import ctypes
import os
import time
import tomllib
from pathlib import Path


def compile_tree(root: Path) -> None:
    """Write the bytecode of ``root``/masking_lab (a no-op where it is current)."""
    package = Path(root) / "masking_lab"
    if not compileall.compile_dir(str(package), quiet=1, workers=0):
        raise SystemExit(f"could not compile the bytecode of {package}")


def console_code(root: Path) -> str:
    """Python source (for ``python -c``) that runs the tree's ``masking-lab`` console script on
    ``sys.argv[1:]``: the entry point ``root``/pyproject.toml names (``module:function``), as
    the installed ``masking-lab`` calls it (an older tree's may be ``cli:main``)."""
    with open(Path(root) / "pyproject.toml", "rb") as fh:
        entry = tomllib.load(fh)["project"]["scripts"]["masking-lab"]
    module, function = entry.split(":")
    return f"import sys; from {module} import {function}; sys.exit({function}())"


def tree_console_code(root: Path, other_tree: bool) -> str:
    """:func:`console_code` of ``root``; with ``other_tree``, run from ``root`` even where this
    checkout is installed in editable mode (its import hook would win over ``sys.path``, so it
    is dropped first)."""
    code = console_code(root)
    if other_tree:
        code = (
            "import sys; sys.meta_path[:] = [f for f in sys.meta_path if 'editable' not in "
            f"repr(f).lower()]; sys.path.insert(0, {str(root)!r}); " + code
        )
    return code


def adopt_orphans() -> bool:
    """Make this process the reaper of its descendants' orphans (Linux ``prctl``
    ``PR_SET_CHILD_SUBREAPER``); False where that is not available.

    A worker forked by a worker that does not wait for it is re-parented when its parent ends,
    and its CPU time then never reaches the command's ``wait4``/``getrusage`` figures, nor
    ``/usr/bin/time``'s: ``analyze``'s second figure worker until session 45 (0.4–0.5 s of a
    3-session run's ~3 s; its first worker now waits for it). Adopted here, such a process is
    waited for by :func:`reap_orphans` and counted, so a baseline tree is measured like this one.
    """
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        return bool(libc.prctl(36, 1, 0, 0, 0) == 0)  # PR_SET_CHILD_SUBREAPER = 36
    except (OSError, AttributeError):
        return False


def reap_orphans(timeout_s: float = 30.0) -> float:
    """Wait for every descendant this process adopted (:func:`adopt_orphans`) and return their
    CPU seconds (user + system); call it when no child of its own is running. Orphans still
    running after ``timeout_s`` are left (their CPU is then missing from the figures)."""
    cpu = 0.0
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            pid, _, usage = os.wait4(-1, os.WNOHANG)
        except ChildProcessError:
            return cpu
        if pid == 0:  # adopted ones still running (they end with their own parents)
            if time.monotonic() > deadline:
                return cpu
            time.sleep(0.005)
            continue
        cpu += usage.ru_utime + usage.ru_stime
