"""Compiled loops (numba) for the functional placement's products over the nuisance grid.

Imported only through :mod:`masking_lab.procedures.fused`, which falls back to numpy when numba
is missing or disabled. Each loop performs numpy's elementwise float32 operations in numpy's
order, one rounding per multiply and per add (no fused multiply-add: numba compiles without
fast-math, so LLVM does not contract them), so it gives numpy's results bit for bit while
reading the likelihood table once per pass instead of once per nuisance point. The loops are
untyped on purpose: numba infers their types from the arrays it is given.
"""

from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def nuisance_sums(p_correct, post, out):
    """``out[r, a, s] = Σ_n p_correct[n, a, s]·post[r, a, n]``, summed n = 0, 1, … (float32).

    ``p_correct`` has shape (N, A, S), ``post`` (R, A, N) and ``out`` (R, A, S); the (N, S)
    slice of the table for one ``a`` stays in cache while every track uses it.
    """
    n_nu, n_a, n_s = p_correct.shape
    for a in range(n_a):
        for r in range(post.shape[0]):
            w0 = post[r, a, 0]
            for s in range(n_s):
                out[r, a, s] = p_correct[0, a, s] * w0
            for n in range(1, n_nu):
                w = post[r, a, n]
                for s in range(n_s):
                    out[r, a, s] = out[r, a, s] + p_correct[n, a, s] * w


@numba.njit(cache=True, nogil=True)
def wrong_and_totals(m_c, row_sums, m_w, pk_c, pk_w):
    """``m_w = max(row_sums[:, None] − m_c, 0)`` (float32) and the column sums of ``m_c`` and
    ``m_w`` accumulated in float64 over a = 0, 1, … (numpy's order for ``sum(axis=0)``)."""
    n_a, n_s = m_c.shape
    zero = np.float32(0.0)
    for s in range(n_s):
        pk_c[s] = 0.0
        pk_w[s] = 0.0
    for a in range(n_a):
        total = row_sums[a]
        for s in range(n_s):
            c = m_c[a, s]
            w = total - c
            if not w > zero:  # np.maximum(w, 0): 0 also for -0.0; NaN cannot occur here
                w = zero
            m_w[a, s] = w
            pk_c[s] += np.float64(c)
            pk_w[s] += np.float64(w)
