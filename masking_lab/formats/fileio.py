"""Durable file writes for outputs that matter (calibrations, exported parameters, figures).

:func:`kill_point` is a test hook: with ``MASKING_LAB_TEST_KILL_AT`` set to a step's name the
process sends itself ``SIGKILL`` there, so tests can kill a real command at each step of its
output swap (:mod:`masking_lab.formats.output_dir`); ``file:N`` names the N-th atomic file write
of the process, killed after its temp file is written and before its rename. Unset (always, in
normal use), it costs one environment lookup.
"""

from __future__ import annotations

import os
import signal
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

_KILL_ENV = "MASKING_LAB_TEST_KILL_AT"
_files_written = 0


def kill_point(step: str) -> None:
    """Test hook: ``SIGKILL`` this process if ``MASKING_LAB_TEST_KILL_AT`` names ``step``.

    Examples
    --------
    >>> kill_point("written")  # the variable is unset: nothing happens
    """
    if os.environ.get(_KILL_ENV) == step:
        os.kill(os.getpid(), signal.SIGKILL)


def _write_data(fh: BinaryIO, data: bytes) -> None:  # tests inject disk errors here
    fh.write(data)


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically: temp file in the same folder, fsync, rename.

    A crash leaves either the old file or the new one, never a half-written file.
    """
    return write_chunks_atomic(path, (data,))


def write_chunks_atomic(path: str | Path, chunks: Iterable[bytes]) -> Path:
    """:func:`write_bytes_atomic` of the concatenated ``chunks``, written as they come (a
    large table need not be held whole)."""
    global _files_written
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    _files_written += 1
    fd, tmp = tempfile.mkstemp(prefix=f".{p.name}.", suffix=".tmp", dir=p.parent)
    try:
        # mkstemp makes the file 0600; give it the permissions a plain open() would.
        os.fchmod(fd, 0o666 & ~_umask())
        with os.fdopen(fd, "wb") as fh:
            for data in chunks:
                _write_data(fh, data)
            fh.flush()
            os.fsync(fh.fileno())
        kill_point(f"file:{_files_written}")
        os.replace(tmp, p)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    fsync_dir(p.parent)  # make the rename itself durable
    return p


def fsync_dir(directory: str | Path) -> None:
    """Fsync a folder, so renames and new entries in it survive a power cut.

    Examples
    --------
    >>> fsync_dir(".")
    """
    dfd = os.open(directory, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


def _umask() -> int:
    # Read, never set: flipping os.umask to read it races with other threads creating files.
    try:
        with open("/proc/self/status", encoding="ascii") as fh:
            for line in fh:
                if line.startswith("Umask:"):
                    return int(line.split()[1], 8)
    except OSError:
        pass
    return 0o022  # no /proc (not Linux): the common default


def write_text_atomic(path: str | Path, text: str) -> Path:
    """Text twin of :func:`write_bytes_atomic` (UTF-8, ``\\n`` line endings)."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_text_chunks_atomic(path: str | Path, texts: Iterable[str]) -> Path:
    """Text twin of :func:`write_chunks_atomic` (UTF-8, ``\\n`` line endings)."""
    return write_chunks_atomic(path, (t.encode("utf-8") for t in texts))
