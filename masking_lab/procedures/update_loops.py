"""Compiled loops (numba) for the Bayesian update of many QUEST+ posteriors at once.

Imported only through :func:`masking_lab.procedures.fused.compiled_loops`; the numpy route in
:func:`masking_lab.procedures.quest_plus_batch.run_quest_plus` is the reference. Unlike the
screen's loops, these must give numpy's numbers bit for bit (a track's levels and posterior
means are pinned by the tables and by replays of single tracks): the products and quotients
are the same operations, and the normalising sum is numpy's pairwise summation of a contiguous
row, written out (tests/test_update_loops.py compares both on random rows and whole tracks).
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def _block_sum(a, first, n):
    """Σ a[first : first + n], n ≤ 128, as numpy sums a block: eight running sums, then the rest."""
    if n < 8:
        total = 0.0
        for i in range(n):
            total += a[first + i]
        return total
    r0, r1, r2, r3 = a[first], a[first + 1], a[first + 2], a[first + 3]
    r4, r5, r6, r7 = a[first + 4], a[first + 5], a[first + 6], a[first + 7]
    i = 8
    while i < n - n % 8:
        j = first + i
        r0 += a[j]
        r1 += a[j + 1]
        r2 += a[j + 2]
        r3 += a[j + 3]
        r4 += a[j + 4]
        r5 += a[j + 5]
        r6 += a[j + 6]
        r7 += a[j + 7]
        i += 8
    total = ((r0 + r1) + (r2 + r3)) + ((r4 + r5) + (r6 + r7))
    while i < n:
        total += a[first + i]
        i += 1
    return total


@numba.njit(cache=True, nogil=True)
def pairwise_sum(a):
    """Σ a (1-D float64) as numpy sums it: pairwise, in blocks of ≤ 128 (each longer run
    split at half its length, rounded down to a multiple of 8, left + right), added to the
    reduction's identity 0.0 (so that a sum of negative zeros is +0.0, as numpy's is).

    Short rows (a psychometric function's levels) take one block, without the stacks.
    """
    if a.size <= 128:
        return 0.0 + _block_sum(a, 0, a.size)
    return 0.0 + _long_sum(a)


@numba.njit(cache=True, nogil=True)
def _long_sum(a):
    """The pairwise sum of more than 128 values, with explicit stacks: numba's cache
    mishandles a recursive function."""
    firsts = np.empty(192, dtype=np.int64)
    sizes = np.empty(192, dtype=np.int64)
    joins = np.empty(192, dtype=np.bool_)
    values = np.empty(96)
    top, held = 0, 0
    firsts[0], sizes[0], joins[0] = 0, a.size, False
    top = 1
    while top > 0:
        top -= 1
        first, n, join = firsts[top], sizes[top], joins[top]
        if join:
            held -= 1
            values[held - 1] = values[held - 1] + values[held]
        elif n <= 128:
            values[held] = _block_sum(a, first, n)
            held += 1
        else:
            half = n // 2
            half -= half % 8
            # popped in the order: left half, right half, then their sum
            firsts[top], sizes[top], joins[top] = first, n, True
            firsts[top + 1], sizes[top + 1], joins[top + 1] = first + half, n - half, False
            firsts[top + 2], sizes[top + 2], joins[top + 2] = first, half, False
            top += 3
    return values[0]


@numba.njit(cache=True, nogil=True)
def update_posteriors(post, answer_tables, answer, level):
    """``post[r] *= answer_tables[answer[r], level[r]]``, then ``post[r] /= post[r].sum()``.

    ``post``: (R, T, N) float64, C-contiguous, updated in place; ``answer_tables``: (2, S, T,
    N) float64 (p(wrong), p(correct)); ``answer``, ``level``: (R,) integer indices.
    """
    n_r = post.shape[0]
    size = post.shape[1] * post.shape[2]
    rows = post.reshape(n_r, size)
    tables = answer_tables.reshape(answer_tables.shape[0], answer_tables.shape[1], size)
    for r in range(n_r):
        row = rows[r]
        like = tables[answer[r], level[r]]
        for i in range(size):
            row[i] *= like[i]
        total = pairwise_sum(row)
        for i in range(size):
            row[i] /= total
