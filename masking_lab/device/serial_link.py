"""Reading and writing an open pyserial port with fewer system calls per frame.

pyserial's POSIX ``read(max(1, in_waiting))`` costs an ``ioctl`` (``in_waiting``), a ``select``
and a ``read`` per call, usually twice per reply (the first call takes one byte); its ``write``
follows every complete ``write`` with a ``select`` for writability when a write timeout is set.
On a POSIX port (an ``fd``) these helpers do what those calls do with one ``select`` and one
``read``, or one ``write``, in the common case, and hand every other case (a partial or
refused write, a port without an ``fd`` such as Windows', a closed port) to pyserial itself,
so timeouts and errors are pyserial's.
"""

from __future__ import annotations

import errno
import os
import select
from typing import Any

import serial

__all__ = ["read_some", "write_all"]

_RETRY = (errno.EAGAIN, errno.EALREADY, errno.EWOULDBLOCK, errno.EINPROGRESS, errno.EINTR)
_CHUNK = 4096


def _posix_fd(ser: Any) -> int | None:
    fd = getattr(ser, "fd", None)
    if not isinstance(fd, int) or not getattr(ser, "is_open", False):
        return None
    return fd


def read_some(ser: Any) -> bytes:
    """What has arrived on ``ser``, waiting at most its read timeout; ``b""`` on timeout.

    Raises
    ------
    serial.SerialException
        The port reported data but returned none (unplugged), or the read failed, as pyserial's
        ``read`` raises them.
    """
    fd = _posix_fd(ser)
    if fd is None:
        return bytes(ser.read(max(1, ser.in_waiting)))
    try:
        ready, _, _ = select.select([fd], [], [], ser.timeout)
        if not ready:
            return b""
        data = os.read(fd, _CHUNK)
    except OSError as e:
        if e.errno in _RETRY:
            return b""
        raise serial.SerialException(f"read failed: {e}") from e
    if not data:
        raise serial.SerialException(
            "device reports readiness to read but returned no data "
            "(device disconnected or multiple access on port?)"
        )
    return data


def write_all(ser: Any, data: bytes) -> None:
    """Write ``data`` to ``ser``; what one ``write`` does not take goes through pyserial's
    ``write`` (its write timeout and errors)."""
    fd = _posix_fd(ser)
    if fd is not None:
        try:
            n = os.write(fd, data)
        except OSError as e:
            if e.errno not in _RETRY:
                raise serial.SerialException(f"write failed: {e}") from e
            n = 0
        if n >= len(data):
            return
        data = data[n:]
    ser.write(data)
