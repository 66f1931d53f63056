"""The functional placement's sums over the nuisance grid, compiled when numba is available.

The functional procedure's placement (:func:`~masking_lab.procedures.functional.expected_entropy`)
needs, for every (a, b) point and stimulus, the posterior-weighted sum of the likelihood over
the nuisance points: 27 products and sums per cell of a 899 × 230 table for the shipped grids.
numpy makes one pass over the 22 MB float32 table per nuisance point; the compiled loops of
:mod:`masking_lab.procedures.jit_loops` read it once, with the same float32 operations in the
same order, so both routes give the same numbers bit for bit (tests/test_fused.py). numba is a
dependency; without it (or with ``NUMBA_DISABLE_JIT=1``) the numpy route runs, slower.

:func:`compiled_loops` loads any such module of compiled loops (the QUEST+ screen's and update's
too), and :data:`COMPILED_FROM` says how many tracks make loading numba worth it.
"""

from __future__ import annotations

import functools
import importlib
import os
from types import ModuleType

import numpy as np
from numpy.typing import NDArray

__all__ = ["COMPILED_FROM", "compiled", "compiled_loops", "nuisance_sums", "wrong_and_totals"]

#: Fewer QUEST+ tracks than this (a session's one) take the numpy routes: the compiled loops
#: gain little there, and loading numba costs ~0.5 s and a BLAS pool of its own (scipy's) that
#: a session's one-thread limit (core/blas_threads.py) would not cover.
COMPILED_FROM = 4


@functools.cache
def compiled_loops(name: str, package: str = "masking_lab.procedures") -> ModuleType | None:
    """The module ``<package>.<name>`` of numba loops, or None when numba is missing, too old
    or too new for this numpy, has no writable cache directory, or runs with
    ``NUMBA_DISABLE_JIT=1`` (it would run the loops as Python, far slower than numpy).
    ``package`` is the caller's own (the analysis's loops live in ``masking_lab.analysis``).

    Examples
    --------
    >>> compiled_loops("jit_loops") is None or hasattr(compiled_loops("jit_loops"), "nuisance_sums")
    True
    """
    if os.environ.get("NUMBA_DISABLE_JIT", "0") not in ("", "0"):
        return None
    try:
        return importlib.import_module(f"{package}.{name}")
    except (ImportError, RuntimeError, OSError):
        return None  # every caller has a numpy route


def _loops() -> ModuleType | None:
    """This module's compiled loops (None: the numpy route, the same numbers)."""
    return compiled_loops("jit_loops")


def compiled() -> bool:
    """Whether the compiled loops run (numba importable and its JIT enabled).

    Examples
    --------
    >>> isinstance(compiled(), bool)
    True
    """
    return _loops() is not None


def nuisance_sums(
    p_correct: NDArray[np.float32], post: NDArray[np.float32], *, use_compiled: bool = True
) -> NDArray[np.float32]:
    """m[r, a, s] = Σ_n p_correct[n, a, s]·post[r, a, n], summed over n in order, in float32.

    Parameters
    ----------
    p_correct : ndarray, shape (N, A, S), float32
        p(correct) of every stimulus s under every (a, b) point a and nuisance point n.
    post : ndarray, shape (R, A, N), float32
        The posteriors of R tracks.
    use_compiled : bool
        False forces the numpy route (the tests compare the two).

    Returns
    -------
    ndarray, shape (R, A, S), float32
        Each track's joint probability of a correct answer and (a, b), per stimulus.

    Examples
    --------
    >>> p = np.array([[[0.5, 1.0]], [[0.25, 0.5]]], dtype=np.float32)   # N=2, A=1, S=2
    >>> q = np.array([[[0.5, 0.5]]], dtype=np.float32)                  # R=1
    >>> nuisance_sums(p, q).tolist()
    [[[0.375, 0.75]]]
    """
    loops = _loops() if use_compiled else None
    r, n_a, n_nu = post.shape
    out = np.empty((r, n_a, p_correct.shape[2]), dtype=np.float32)
    if loops is not None:
        loops.nuisance_sums(p_correct, np.ascontiguousarray(post), out)
        return out
    tmp = np.empty(out.shape[1:], dtype=np.float32)
    for k in range(r):
        m = out[k]
        np.multiply(p_correct[0], post[k, :, 0, None], out=m)
        for n in range(1, n_nu):
            np.multiply(p_correct[n], post[k, :, n, None], out=tmp)
            np.add(m, tmp, out=m)
    return out


def wrong_and_totals(
    m_c: NDArray[np.float32], row_sums: NDArray[np.float32], *, use_compiled: bool = True
) -> tuple[NDArray[np.float32], NDArray[np.float64], NDArray[np.float64]]:
    """The wrong answer's joint probability and both answers' probabilities per stimulus.

    Parameters
    ----------
    m_c : ndarray, shape (A, S), float32
        Joint probability of a correct answer and each (a, b) point (:func:`nuisance_sums`).
    row_sums : ndarray, shape (A,), float32
        The posterior's (a, b) marginal.
    use_compiled : bool
        False forces the numpy route.

    Returns
    -------
    m_w : ndarray, shape (A, S), float32
        ``max(row_sums − m_c, 0)``.
    pk_c, pk_w : ndarray, shape (S,), float64
        Column sums of ``m_c`` and ``m_w`` (p(correct), p(wrong) per stimulus), in float64.

    Examples
    --------
    >>> m_w, pc, pw = wrong_and_totals(np.array([[0.25, 0.5]], dtype=np.float32),
    ...                                np.array([0.5], dtype=np.float32))
    >>> m_w.tolist(), pc.tolist(), pw.tolist()
    ([[0.25, 0.0]], [0.25, 0.5], [0.25, 0.0])
    """
    loops = _loops() if use_compiled else None
    if loops is not None:
        m_w = np.empty_like(m_c)
        pk_c = np.empty(m_c.shape[1])
        pk_w = np.empty(m_c.shape[1])
        loops.wrong_and_totals(m_c, row_sums, m_w, pk_c, pk_w)
        return m_w, pk_c, pk_w
    m_w = np.maximum(row_sums[:, None] - m_c, np.float32(0.0))
    return m_w, m_c.sum(axis=0, dtype=np.float64), m_w.sum(axis=0, dtype=np.float64)
