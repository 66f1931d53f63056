"""Session locks (*shell*): one process writes a log, one runner per participant and protocol.

``run`` and ``resume`` hold an advisory ``flock`` on the log file for the life of the session,
so a second ``resume`` of the same log is refused at once instead of running beside the first
and interleaving duplicate trials. The lock belongs to the open file descriptor the writer
appends through, so it goes away with the process, however that ends (no stale lock files).

They also hold a :class:`RunnerLock` on ``DATA/<participant>/.<participant>.<experiment>.lock``
(beside the log a ``resume`` continues): a second
``run`` (or a ``resume`` of another log) of the same participant and protocol while one is
running would write a second log of the same sets at once, so it is refused. The lock file
stays (empty, hidden); only the ``flock`` on it matters, and it too ends with the process.
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from masking_lab.core.errors import LogError, LogLockedError

__all__ = ["LogLock", "RunnerLock"]


class _Lock:
    """An open descriptor holding an exclusive ``flock`` (the lock ends when it is closed)."""

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self.fd = fd

    def release(self) -> None:
        """Close the descriptor, releasing the lock (idempotent)."""
        if self.fd >= 0:
            fd, self.fd = self.fd, -1
            os.close(fd)


def _flock(fd: int, busy: str, cannot: str, advice: str) -> None:
    """Lock ``fd``, or close it and raise LogLockedError(``busy``) when another process holds
    the lock, LogError(``cannot`` (why); ``advice``) when the file system has no locks."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError as exc:
        os.close(fd)
        raise LogLockedError(busy) from exc
    except OSError as exc:  # a filesystem without flock (rare): say so, do not guess
        os.close(fd)
        raise LogError(f"{cannot} ({exc.strerror or exc}); {advice}") from exc


class LogLock(_Lock):
    """An open, exclusively locked session-log file descriptor (append mode).

    Use :meth:`create` for a new log and :meth:`acquire` for an existing one; :meth:`release`
    (idempotent) closes the descriptor and with it the lock.

    Attributes
    ----------
    path : Path
        The log file.
    fd : int
        The descriptor, opened ``O_RDWR | O_APPEND``; -1 once released.
    """

    @classmethod
    def create(cls, path: str | Path) -> LogLock:
        """Create ``path`` (it must not exist) and lock it.

        Raises
        ------
        FileExistsError
            The file exists (the caller says what to do).
        LogError
            It cannot be created (permissions, missing disk).
        """
        p = Path(path)
        try:
            fd = os.open(p, os.O_RDWR | os.O_APPEND | os.O_CREAT | os.O_EXCL | os.O_CLOEXEC, 0o666)
        except FileExistsError:
            raise
        except OSError as exc:
            raise LogError(f"{p}: cannot create the session log ({exc.strerror or exc})") from exc
        return cls._locked(p, fd)

    @classmethod
    def acquire(cls, path: str | Path) -> LogLock:
        """Open the existing log ``path`` for appending and lock it.

        Raises
        ------
        LogLockedError
            Another process holds the lock (a ``run`` or ``resume`` of this session).
        LogError
            The file cannot be opened.

        Examples
        --------
        >>> import tempfile, pathlib
        >>> p = pathlib.Path(tempfile.mkdtemp()) / "log.jsonl"
        >>> _ = p.write_bytes(b"")
        >>> lock = LogLock.acquire(p)
        >>> lock.release()
        """
        p = Path(path)
        try:
            fd = os.open(p, os.O_RDWR | os.O_APPEND | os.O_CLOEXEC)
        except OSError as exc:
            raise LogError(f"{p}: cannot read session log ({exc.strerror or exc})") from exc
        return cls._locked(p, fd)

    @classmethod
    def _locked(cls, path: Path, fd: int) -> LogLock:
        _flock(
            fd,
            f"{path}: another masking-lab process (a run or resume of this session) is "
            "writing this log; two processes would interleave their trials. Let it finish "
            "or stop it (Ctrl-C in its terminal), then resume",
            f"{path}: cannot lock the session log",
            "keep session logs on a local disk",
        )
        return cls(path, fd)


class RunnerLock(_Lock):
    """The exclusive lock of one participant's sessions of one protocol (experiment).

    Attributes
    ----------
    path : Path
        The lock file, ``<folder>/.<participant>.<experiment>.lock``.
    fd : int
        Its open, locked descriptor; -1 once released.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> data = pathlib.Path(tempfile.mkdtemp())
    >>> lock = RunnerLock.acquire(data / "P01", "P01", "experiment1")
    >>> RunnerLock.acquire(data / "P01", "P01", "experiment1")  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.LogLockedError: participant P01 is already running experiment1 ...
    >>> lock.release()
    """

    @classmethod
    def acquire(cls, folder: str | Path, participant: str, experiment: str) -> RunnerLock:
        """Lock ``participant``'s sessions of ``experiment`` whose logs are in ``folder``
        (``DATA/<participant>`` for ``run``; the log's folder for ``resume``).

        Raises
        ------
        LogLockedError
            Another process runs this participant and protocol (a ``run`` or ``resume``).
        LogError
            The lock file cannot be made (the data folder is not writable).
        """
        folder = Path(folder)
        path = folder / f".{participant}.{experiment}.lock"
        try:
            folder.mkdir(parents=True, exist_ok=True)
            fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o666)
        except OSError as exc:
            raise LogError(
                f"{path}: cannot make the session lock ({exc.strerror or exc}); choose a --data "
                "folder you can write to"
            ) from exc
        _flock(
            fd,
            f"participant {participant} is already running {experiment} in another "
            f"masking-lab process (lock {path}); two sessions of one protocol at once would "
            "measure the same sets twice. Let it finish or stop it (Ctrl-C in its terminal)",
            f"{path}: cannot lock",
            "keep the data folder on a local disk",
        )
        return cls(path, fd)
