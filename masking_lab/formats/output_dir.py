"""Output folders that change all at once: write into a fresh sibling, swap it in when complete.

``analyze``, ``fit`` and ``usertest-report`` write a dozen files into one folder. Writing them in
place would leave a folder half from this run and half from the last one when a run fails
midway; :func:`staged_output` instead hands out a fresh hidden sibling folder, and only when the
``with`` block finishes does it swap the new folder in. A run that fails leaves the previous
results untouched and says so in its error; what it wrote (often the explanation, e.g. a report
of which sets were completed) goes to ``<OUT>.failed`` next to them, or into ``OUT`` itself when
there was nothing to keep. A full disk (or any other write error) is such a failure too.

The swap survives a ``SIGKILL`` at any instant. On Linux it is one atomic
``renameat2(RENAME_EXCHANGE)`` of the two folders (the name ``OUT`` always points at a complete
folder, old or new); elsewhere, or on a file system without it, two renames (``OUT`` →
``.OUT.old-PID``, staging → ``OUT``), with a window between them in which ``OUT`` is missing.
Every run first tidies what a killed run left beside ``OUT`` (:func:`recover_leftovers`):
a ``.OUT.old-PID`` with no ``OUT`` is renamed back (the previous results, restored), and the
``.OUT.partial-PID`` and ``.OUT.old-PID`` folders of processes no longer running are deleted.

For tests, ``MASKING_LAB_TEST_KILL_AT`` names a step at which the process kills itself
(:func:`masking_lab.formats.fileio.kill_point`; steps: ``staged``, ``written``,
``moved_aside``, ``swapped``, and ``file:N`` inside the N-th atomic file write), and
``MASKING_LAB_TEST_NO_EXCHANGE=1`` forces the two-rename fallback.

This is the shell: it touches the file system.
"""

from __future__ import annotations

import ctypes
import errno
import os
import re
import shutil
import sys
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from typing import Literal

from masking_lab.core.errors import MaskingLabError, OutputFolderError
from masking_lab.core.worker_processes import alive
from masking_lab.formats.fileio import fsync_dir, kill_point

__all__ = ["MARKER_FILES", "recover_leftovers", "staged_output"]

# A folder holding one of these is a previous run's output and may be replaced as a whole.
MARKER_FILES = ("report.txt", "report.html")


class _SharedFolder(OutputFolderError):
    """``out`` holds an input or files that are not outputs: it cannot be swapped as a whole."""


def _check_replaceable(
    out: Path, protect: Sequence[Path], markers: Sequence[str] = MARKER_FILES
) -> bool:
    """Whether ``out`` holds previous results; raise if replacing it could lose other files."""
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"--out {out}: is a file; give a folder for the outputs")
    resolved = out.resolve()
    for p in protect:
        inside = Path(p).resolve()
        if inside == resolved or resolved in inside.parents:
            raise _SharedFolder(
                f"--out {out}: holds the input {p}; the output folder is replaced as a whole "
                "when a run completes, so give a folder outside the inputs (e.g. a sibling)"
            )
    if not out.is_dir() or not any(out.iterdir()):
        return False
    if any((out / name).is_file() for name in markers):
        return True
    raise _SharedFolder(
        f"--out {out}: holds files that are not masking-lab outputs (no {markers[0]}); the output "
        "folder is replaced as a whole when a run completes, so give a new or empty folder"
    )


@contextmanager
def staged_output(
    out: str | Path,
    *,
    protect: Sequence[str | Path] = (),
    markers: Sequence[str] = MARKER_FILES,
    shared: Literal["refuse", "in_place"] = "refuse",
) -> Iterator[Path]:
    """A fresh folder to write into, swapped in as ``out`` when the ``with`` block completes.

    Parameters
    ----------
    out : str or Path
        The output folder: missing, empty, or holding a previous run's outputs (a
        ``report.txt`` or ``report.html``), which are replaced as a whole.
    protect : sequence of path
        Inputs of the run; ``out`` must not contain them.
    markers : sequence of str
        File names that mark a folder as a previous run's outputs (default: the reports).
    shared : {"refuse", "in_place"}
        What to do with an ``out`` that holds an input or other files: refuse
        (``OutputFolderError``), or yield ``out`` itself, each file then written atomically on
        its own (``plan`` and ``render``, often pointed at a working folder).

    Yields
    ------
    Path
        The staging folder (``.<name>.partial-<pid>`` beside ``out``). Write every output there.

    Raises
    ------
    OutputFolderError
        ``out`` is a file, contains an input, or holds files that are not outputs.
    MaskingLabError
        The error of a failed block, re-raised with the same type and a sentence saying where
        the previous results and the partial outputs are.

    Examples
    --------
    >>> import tempfile
    >>> root = Path(tempfile.mkdtemp())
    >>> with staged_output(root / "out") as tmp:
    ...     _ = (tmp / "report.txt").write_text("done\\n")
    >>> (root / "out" / "report.txt").read_text()
    'done\\n'
    """
    out = Path(out)
    recover_leftovers(out)
    try:
        had_results = _check_replaceable(out, [Path(p) for p in protect], markers)
    except _SharedFolder:
        if shared != "in_place":
            raise
        with _in_place(out) as folder:
            yield folder
        return
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        shutil.rmtree(staging, ignore_errors=True)
        staging.mkdir()
    except OSError as exc:
        raise OutputFolderError(
            f"--out {out}: cannot make a folder beside it ({exc.strerror or exc}); choose a "
            "folder you can write to"
        ) from exc
    kill_point("staged")
    try:
        yield staging
    except MaskingLabError as exc:
        message = f"{exc}\n{_keep_failed(out, staging, had_results)}"
        try:
            again = type(exc)(message)
        except TypeError:  # an error type built from more than a message (ProtocolError)
            again = MaskingLabError(message)
        raise again from exc
    except OSError as exc:  # a full disk, an I/O error: never a traceback
        shutil.rmtree(staging, ignore_errors=True)
        kept = (
            f"the previous results in {out} are left untouched"
            if had_results
            else f"nothing was written to {out}"
        )
        raise OutputFolderError(
            f"--out {out}: cannot write the outputs ({exc.strerror or exc}); {kept}. Free "
            "disk space (or fix the disk) and run again"
        ) from exc
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    kill_point("written")
    try:
        _swap_in(out, staging)
    except OSError as exc:
        shutil.rmtree(staging, ignore_errors=True)
        raise OutputFolderError(
            f"--out {out}: cannot put the new outputs in place ({exc.strerror or exc}); "
            "the previous results, if any, are left untouched"
        ) from exc


@contextmanager
def _in_place(out: Path) -> Iterator[Path]:
    """``out`` itself, with write errors made clean (files written before the error are new)."""
    try:
        out.mkdir(parents=True, exist_ok=True)
        yield out
    except OSError as exc:
        raise OutputFolderError(
            f"--out {out}: cannot write the outputs ({exc.strerror or exc}); the folder holds "
            "other files too, so its outputs are written one by one: those written before the "
            "error are new, the others are from before. Free disk space (or fix the disk) and "
            "run again"
        ) from exc


def _keep_failed(out: Path, staging: Path, had_results: bool) -> str:
    """Put a failed run's partial outputs where they harm nothing; say where everything is."""
    if not any(staging.iterdir()):
        shutil.rmtree(staging, ignore_errors=True)
        if had_results:
            return f"The previous results in {out} are left untouched."
        return f"Nothing was written to {out}."
    if not had_results:
        _swap_in(out, staging)
        return f"The partial outputs of this run are in {out}."
    failed = out.parent / f"{out.name}.failed"
    shutil.rmtree(failed, ignore_errors=True)
    os.rename(staging, failed)
    return (
        f"The previous results in {out} are left untouched; the partial outputs of this run "
        f"are in {failed}."
    )


def _swap_in(out: Path, staging: Path) -> None:
    """Put ``staging`` in place as ``out``: one atomic exchange where the system has it, else
    ``out`` renamed aside, then ``staging`` renamed in; the previous folder deleted after."""
    if out.exists() and _exchange(staging, out):
        fsync_dir(out.parent)
        kill_point("swapped")
        shutil.rmtree(staging, ignore_errors=True)  # the previous results, now at this name
        return
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    if out.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.rename(out, old)
        kill_point("moved_aside")
    os.rename(staging, out)
    fsync_dir(out.parent)
    kill_point("swapped")
    shutil.rmtree(old, ignore_errors=True)


_RENAME_EXCHANGE = 2  # linux/fs.h
_AT_FDCWD = -100


def _exchange(a: Path, b: Path) -> bool:
    """Swap the names ``a`` and ``b`` atomically (Linux ``renameat2``); False where the
    system or the file system cannot (then the caller falls back to two renames)."""
    if not sys.platform.startswith("linux") or os.environ.get("MASKING_LAB_TEST_NO_EXCHANGE"):
        return False
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):  # glibc < 2.28, musl: no wrapper
        return False
    renameat2.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p]
    renameat2.argtypes += [ctypes.c_uint]
    renameat2.restype = ctypes.c_int
    if renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE) == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP, errno.EOPNOTSUPP):
        return False  # the file system cannot exchange (e.g. some network file systems)
    raise OSError(err, os.strerror(err), str(b))


_LEFTOVER = re.compile(r"\.(?P<name>.+)\.(?P<kind>partial|old)-(?P<pid>\d+)")


def recover_leftovers(out: str | Path) -> list[str]:
    """Tidy what a killed run left beside ``out``; return what was done, one line each.

    A ``.OUT.old-PID`` folder while ``OUT`` is missing holds the previous complete results (the
    run was killed between its two renames): it is renamed back to ``OUT``. Other
    ``.OUT.old-PID`` and ``.OUT.partial-PID`` folders of processes that are no longer running
    are deleted (a running process's staging folder is left alone).

    Examples
    --------
    >>> import tempfile
    >>> root = Path(tempfile.mkdtemp())
    >>> (root / ".out.old-999999999").mkdir()
    >>> recover_leftovers(root / "out")
    ['restored the previous results of a killed run from .out.old-999999999']
    >>> (root / "out").is_dir()
    True
    """
    out = Path(out)
    parent = out.parent
    done: list[str] = []
    try:
        entries = sorted(parent.iterdir()) if parent.is_dir() else []
    except OSError:
        return done
    for entry in entries:
        m = _LEFTOVER.fullmatch(entry.name)
        if not m or m["name"] != out.name or not entry.is_dir() or entry.is_symlink():
            continue
        pid = int(m["pid"])
        if pid != os.getpid() and alive(pid):
            continue
        if m["kind"] == "old" and not out.exists() and not out.is_symlink():
            os.rename(entry, out)
            done.append(f"restored the previous results of a killed run from {entry.name}")
        else:
            shutil.rmtree(entry, ignore_errors=True)
            done.append(f"deleted {entry.name}, left by a killed run")
    return done
