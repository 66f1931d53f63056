"""The session log's exclusive lock (*shell*): one process writes a log at a time.

``run`` and ``resume`` hold an advisory ``flock`` on the log file for the life of the session,
so a second ``resume`` of the same log is refused at once instead of running beside the first
and interleaving duplicate trials. The lock belongs to the open file descriptor the writer
appends through, so it goes away with the process, however that ends (no stale lock files).
"""

from __future__ import annotations

import fcntl
import os
from pathlib import Path

from masking_lab.core.errors import LogError, LogLockedError

__all__ = ["LogLock"]


class LogLock:
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

    def __init__(self, path: Path, fd: int) -> None:
        self.path = path
        self.fd = fd

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
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError as exc:
            os.close(fd)
            raise LogLockedError(
                f"{path}: another masking-lab process (a run or resume of this session) is "
                "writing this log; two processes would interleave their trials. Let it finish "
                "or stop it (Ctrl-C in its terminal), then resume"
            ) from exc
        except OSError as exc:  # a filesystem without flock (rare): say so, do not guess
            os.close(fd)
            raise LogError(
                f"{path}: cannot lock the session log ({exc.strerror or exc}); keep session "
                "logs on a local disk"
            ) from exc
        return cls(path, fd)

    def release(self) -> None:
        """Close the descriptor, releasing the lock (idempotent)."""
        if self.fd >= 0:
            fd, self.fd = self.fd, -1
            os.close(fd)
