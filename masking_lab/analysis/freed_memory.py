"""Give freed memory back to the system during a large analysis (*shell*: process-wide).

A large study's analysis frees most of what it builds (each log's rows once the thresholds
table holds them, the shift figures' data once handed to their worker, the bootstrap's blocks),
but glibc's allocator keeps freed memory for reuse: the process's resident size only grows, so
its peak is the sum of the phases rather than the largest. :func:`return_early` makes freed
large blocks go back at once (fixed mmap and trim thresholds instead of glibc's adaptive ones,
which rise to 32 MB after numpy frees its first large arrays); :func:`trim` returns the free
pages inside the heap between phases. Elsewhere (no glibc) both do nothing. Neither changes a
value, only where memory comes from.
"""

from __future__ import annotations

import ctypes
from functools import cache
from typing import Any

__all__ = ["return_early", "trim"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_THRESHOLD = 128 * 1024  # glibc's initial value of both


@cache
def _libc() -> Any:
    try:
        libc = ctypes.CDLL(None)
        libc.mallopt  # noqa: B018 - glibc only
        libc.malloc_trim  # noqa: B018
    except (OSError, AttributeError):
        return None
    return libc


def return_early() -> None:
    """From now on, return freed blocks of 128 kB or more to the system at once.

    Examples
    --------
    >>> return_early()
    """
    libc = _libc()
    if libc is not None:
        libc.mallopt(_M_MMAP_THRESHOLD, _THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, _THRESHOLD)


def trim() -> None:
    """Return the free pages of the heap to the system (between the phases of a run).

    Examples
    --------
    >>> trim()
    """
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)
