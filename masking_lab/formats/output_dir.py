"""Output folders that change all at once: write into a fresh sibling, swap it in when complete.

``analyze``, ``fit`` and ``usertest-report`` write a dozen files into one folder. Writing them in
place would leave a folder half from this run and half from the last one when a run fails
midway; :func:`staged_output` instead hands out a fresh hidden sibling folder, and only when the
``with`` block finishes does it rename the previous folder aside, rename the new one into its
place and delete the old one. A run that fails leaves the previous results untouched and says so
in its error; what it wrote (often the explanation, e.g. a report of which sets were completed)
goes to ``<OUT>.failed`` next to them, or into ``OUT`` itself when there was nothing to keep.

This is the shell: it touches the file system (``os.rename`` within one parent folder, which is
atomic on POSIX for each of the two steps).
"""

from __future__ import annotations

import os
import shutil
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from masking_lab.core.errors import MaskingLabError, OutputFolderError

__all__ = ["MARKER_FILES", "staged_output"]

# A folder holding one of these is a previous run's output and may be replaced as a whole.
MARKER_FILES = ("report.txt", "report.html")


def _check_replaceable(out: Path, protect: Sequence[Path]) -> bool:
    """Whether ``out`` holds previous results; raise if replacing it could lose other files."""
    if out.exists() and not out.is_dir():
        raise OutputFolderError(f"--out {out}: is a file; give a folder for the outputs")
    resolved = out.resolve()
    for p in protect:
        inside = Path(p).resolve()
        if inside == resolved or resolved in inside.parents:
            raise OutputFolderError(
                f"--out {out}: holds the input {p}; the output folder is replaced as a whole "
                "when a run completes, so give a folder outside the inputs (e.g. a sibling)"
            )
    if not out.is_dir() or not any(out.iterdir()):
        return False
    if any((out / name).is_file() for name in MARKER_FILES):
        return True
    raise OutputFolderError(
        f"--out {out}: holds files that are not masking-lab outputs (no report.txt); the output "
        "folder is replaced as a whole when a run completes, so give a new or empty folder"
    )


@contextmanager
def staged_output(out: str | Path, *, protect: Sequence[str | Path] = ()) -> Iterator[Path]:
    """A fresh folder to write into, swapped in as ``out`` when the ``with`` block completes.

    Parameters
    ----------
    out : str or Path
        The output folder: missing, empty, or holding a previous run's outputs (a
        ``report.txt`` or ``report.html``), which are replaced as a whole.
    protect : sequence of path
        Inputs of the run; ``out`` must not contain them.

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
    had_results = _check_replaceable(out, [Path(p) for p in protect])
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.parent / f".{out.name}.partial-{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        yield staging
    except MaskingLabError as exc:
        message = f"{exc}\n{_keep_failed(out, staging, had_results)}"
        try:
            again = type(exc)(message)
        except TypeError:  # an error type built from more than a message (ProtocolError)
            again = MaskingLabError(message)
        raise again from exc
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    _swap_in(out, staging)


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
    """Rename ``staging`` to ``out``, moving an existing ``out`` aside and deleting it after."""
    old = out.parent / f".{out.name}.old-{os.getpid()}"
    if out.exists():
        shutil.rmtree(old, ignore_errors=True)
        os.rename(out, old)
    os.rename(staging, out)
    shutil.rmtree(old, ignore_errors=True)
