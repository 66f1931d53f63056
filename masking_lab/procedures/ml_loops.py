"""Compiled loops (numba) for the staircase maximum-likelihood fits of ``plan``.

Imported only through :func:`masking_lab.procedures.fused.compiled_loops`; the numpy route of
:class:`masking_lab.procedures.ml_counts.LogisticModel` is the reference and these loops give
its numbers bit for bit, so ``plan``'s tables keep their bytes whichever route made them. They
fuse the arithmetic around numpy's ``exp`` and ``log`` (numba's are other implementations,
rounded differently) into one pass over the levels instead of one per operation: the same
IEEE operations in the same order (numba compiles without fast-math, so no multiply-add is
contracted), and each track's sums are numpy's pairwise summation of a contiguous row
(tests/test_ml_loops.py). ``error_model="numpy"``: a quotient follows IEEE rules, as numpy's
does, instead of a Python check for division by zero, which kept LLVM from vectorising the loops
(about twice the time). numba caches each loop by its own file: a change to
``update_loops.pairwise_sum`` alone reaches this file's cache only once this file is touched too.
"""

from __future__ import annotations

import numba
import numpy as np

from masking_lab.procedures.update_loops import pairwise_sum

_TINY = np.finfo(np.float64).tiny


@numba.njit(cache=True, nogil=True, error_model="numpy")
def logistic_args(level, threshold, scale, c, step, minus_abs):
    """From z = (level[i, l] − threshold[i])/scale[i] + c: ``step`` = heaviside(z, 1) (1 where
    z ≥ 0, else 0) and ``minus_abs`` = −|z| (for numpy's ``exp``). Returns whether some z is
    NaN: the caller then takes the numpy route, which says what such a level weighs."""
    n_r, n_l = step.shape
    nan = False
    for i in range(n_r):
        t, s = threshold[i], scale[i]
        for j in range(n_l):
            v = (level[i, j] - t) / s + c
            nan |= v != v
            step[i, j] = 1.0 if v >= 0.0 else 0.0
            minus_abs[i, j] = -abs(v)
    return nan


@numba.njit(cache=True, nogil=True, error_model="numpy")
def answer_probabilities(step, e, n_correct, n_wrong, rise, guess, lapse, p, q):
    """p(correct) and p(wrong) at every level from :func:`logistic_args`' step and
    e = exp(−|z|), each floored at the smallest normal float where its answers are weighed and
    at 1 elsewhere (ln 1 = +0), for numpy's ``log``."""
    n_r, n_l = e.shape
    tiny = _TINY
    for i in range(n_r):
        for j in range(n_l):
            h, ev = step[i, j], e[i, j]
            d = ev + 1.0
            # F(z) and 1 − F(z): max(e, h) and max(e, 1 − h) are 1 or e (0 ≤ e ≤ 1)
            a = max(ev, h) / d
            b = max(ev, 1.0 - h) / d
            a = a * rise + guess
            b = b * rise + lapse
            p[i, j] = max(a, 1.0 if n_correct[i, j] == 0.0 else tiny)
            q[i, j] = max(b, 1.0 if n_wrong[i, j] == 0.0 else tiny)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def weighed_sums(log_p, log_q, n_correct, n_wrong, out):
    """``out[i] = Σ_l (log_p·n_correct + log_q·n_wrong)[i, l]``, summed as numpy sums a row."""
    n_r, n_l = log_p.shape
    row = np.empty(n_l)
    for i in range(n_r):
        for j in range(n_l):
            row[j] = log_p[i, j] * n_correct[i, j] + log_q[i, j] * n_wrong[i, j]
        out[i] = pairwise_sum(row)


@numba.njit(cache=True, nogil=True, error_model="numpy")
def _slopes(h0, ev, k, m, rise, guess, lapse):
    """At one level: p, q, dp/dz, d²p/dz², the score weight and the curvature weight, as
    :meth:`~masking_lab.procedures.ml_counts.LogisticModel._slopes` forms them."""
    d = ev + 1.0
    f = max(ev, h0) / d
    g = max(ev, 1.0 - h0) / d
    p = max(rise * f + guess, _TINY)
    q = max(rise * g + lapse, _TINY)
    h = rise * f * g
    h2 = (g - f) * h
    w = k / p - m / q
    curv = -(k / (p * p) + m / (q * q))
    return p, q, h, h2, w, curv


@numba.njit(cache=True, nogil=True, error_model="numpy")
def slope_sums(level, threshold, scale, step, e, n_trials, n_correct, n_wrong, rise, guess, lapse,
               out):  # fmt: skip
    """Score, observed Hessian and expected information of the log-likelihood in (t, u = ln s)
    per track, as :meth:`~masking_lab.procedures.ml_counts.LogisticModel.derivatives` forms
    and sums them, from :func:`logistic_args`' step and e = exp(−|z|).

    ``out``: (8, R): g_t, g_u, H_tt, H_tu, H_uu, I_tt, I_tu, I_uu.
    """
    n_r, n_l = e.shape
    rows = np.empty((8, n_l))
    for i in range(n_r):
        t, s = threshold[i], scale[i]
        s2 = s * s
        for j in range(n_l):
            y = (level[i, j] - t) / s
            k, m = n_correct[i, j], n_wrong[i, j]
            p, q, h, h2, w, curv = _slopes(step[i, j], e[i, j], k, m, rise, guess, lapse)
            info = n_trials[i, j] / (p * q)
            dt = -h / s
            du = -h * y
            dtt = h2 / s2
            dtu = (h2 * y + h) / s
            duu = y * y * h2 + h * y
            rows[0, j] = w * dt
            rows[1, j] = w * du
            rows[2, j] = w * dtt + curv * dt * dt
            rows[3, j] = w * dtu + curv * dt * du
            rows[4, j] = w * duu + curv * du * du
            rows[5, j] = info * dt * dt
            rows[6, j] = info * dt * du
            rows[7, j] = info * du * du
        for k in range(8):
            out[k, i] = pairwise_sum(rows[k])


@numba.njit(cache=True, nogil=True, error_model="numpy")
def threshold_slope_sums(scale, step, e, n_correct, n_wrong, rise, guess, lapse, out):
    """Score and observed curvature in t alone per track (``out``: (2, R), g_t and H_tt of
    :func:`slope_sums`, the same numbers)."""
    n_r, n_l = e.shape
    rows = np.empty((2, n_l))
    for i in range(n_r):
        s = scale[i]
        s2 = s * s
        for j in range(n_l):
            k, m = n_correct[i, j], n_wrong[i, j]
            _, _, h, h2, w, curv = _slopes(step[i, j], e[i, j], k, m, rise, guess, lapse)
            dt = -h / s
            rows[0, j] = w * dt
            rows[1, j] = w * (h2 / s2) + curv * dt * dt
        out[0, i] = pairwise_sum(rows[0])
        out[1, i] = pairwise_sum(rows[1])
