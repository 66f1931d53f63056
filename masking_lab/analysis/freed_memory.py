"""Give freed memory back to the system during a large analysis (*shell*: process-wide).

A large study's analysis frees most of what it builds (each log's rows once the thresholds
table holds them, the shift figures' data once handed to their worker, the bootstrap's blocks),
but glibc's allocator keeps freed memory for reuse: the process's resident size only grows, so
its peak is the sum of the phases rather than the largest. :func:`return_early` makes freed
large blocks go back at once (fixed mmap and trim thresholds instead of glibc's adaptive ones,
which rise to 32 MB after numpy frees its first large arrays); :func:`trim` returns the free
pages inside the heap between phases. Elsewhere (no glibc) both do nothing. Neither changes a
value, only where memory comes from.

Giving blocks back at once has a price where numpy allocates and frees the same large
temporaries thousands of times (the psychometric bootstrap's batched climbs): every one is a
fresh mapping whose pages the kernel zeroes on first touch, which made those fits 1.6x slower
(a third of their time in the kernel). :func:`reused_blocks` keeps freed blocks in the heap for
the length of such a computation and gives them back when it ends.
"""

from __future__ import annotations

import ctypes
from collections.abc import Iterator
from contextlib import contextmanager
from functools import cache
from typing import Any

__all__ = ["return_early", "reused_blocks", "trim"]

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_THRESHOLD = 128 * 1024  # glibc's initial value of both
_REUSE_THRESHOLD = 32 * 1024 * 1024  # glibc's ceiling for the mmap threshold (64-bit)
_early = False  # return_early was called in this process (or the one it was forked from)


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
    global _early
    libc = _libc()
    if libc is not None:
        libc.mallopt(_M_MMAP_THRESHOLD, _THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, _THRESHOLD)
        _early = True


@contextmanager
def reused_blocks() -> Iterator[None]:
    """Within the block, freed blocks of up to 32 MB stay in the heap for reuse; on leaving
    it, the heap's free pages go back and :func:`return_early`'s thresholds hold again.

    Does nothing unless :func:`return_early` was called (glibc's adaptive thresholds already
    keep such blocks) or without glibc.

    Examples
    --------
    >>> import numpy as np
    >>> with reused_blocks():
    ...     total = sum(float(np.ones(100_000).sum()) for _ in range(3))
    >>> total
    300000.0
    """
    libc = _libc()
    if libc is None or not _early:
        yield
        return
    libc.mallopt(_M_MMAP_THRESHOLD, _REUSE_THRESHOLD)
    libc.mallopt(_M_TRIM_THRESHOLD, 2 * _REUSE_THRESHOLD)
    try:
        yield
    finally:
        libc.mallopt(_M_MMAP_THRESHOLD, _THRESHOLD)
        libc.mallopt(_M_TRIM_THRESHOLD, _THRESHOLD)
        libc.malloc_trim(0)


def trim() -> None:
    """Return the free pages of the heap to the system (between the phases of a run).

    Examples
    --------
    >>> trim()
    """
    libc = _libc()
    if libc is not None:
        libc.malloc_trim(0)
