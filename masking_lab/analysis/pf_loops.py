"""Compiled loops (numba) for the psychometric climb of :mod:`masking_lab.analysis.pf_likelihood`.

Imported only through :func:`masking_lab.procedures.fused.compiled_loops`; the numpy route of
:func:`~masking_lab.analysis.pf_likelihood.refit` is the reference and these loops give its
numbers bit for bit, so ``psychometric.csv`` keeps its bytes whichever route made it. They fuse
the arithmetic between numpy's transcendental functions (``exp``, ``tanh``, ``log``,
``log1p`` stay numpy's: numba's are other implementations, rounded differently) and its
batched ``linalg.solve`` (LAPACK's rounding), one pass over the rows instead of one per
operation: the same IEEE operations in the same order (numba compiles without fast-math, so
no multiply-add is contracted), the score and information summed over the levels in
``np.einsum``'s order, 0, 1, …, and the steps' clipping and active set with numpy's signs of
zero (tests/test_pf_loops.py). numba
caches each loop by its own file: a change to ``update_loops.pairwise_sum`` alone reaches this
file's cache only once this file is touched too.
"""

from __future__ import annotations

import numba
import numpy as np

from masking_lab.procedures.update_loops import pairwise_sum


@numba.njit(cache=True, nogil=True)
def half_z(x, rows, alpha, inv_scale, out):
    """``out[i, l] = 0.5·((x[rows[i], l] − alpha[i])·inv_scale[i])``: half the logistic's
    argument as :func:`~masking_lab.analysis.pf_likelihood.nll` forms it, for numpy's ``tanh``."""
    n_r, n_l = out.shape
    for i in range(n_r):
        r = rows[i]
        a, e = alpha[i], inv_scale[i]
        for j in range(n_l):
            out[i, j] = 0.5 * ((x[r, j] - a) * e)


@numba.njit(cache=True, nogil=True)
def z_and_half(x, rows, alpha, scale, z, half):
    """``z[i, l] = (x[rows[i], l] − alpha[i])/scale[i]`` and ``half = 0.5·z``: the argument
    as the climb's step forms it, and half of it for numpy's ``tanh``."""
    n_r, n_l = z.shape
    for i in range(n_r):
        r = rows[i]
        a, s = alpha[i], scale[i]
        for j in range(n_l):
            v = (x[r, j] - a) / s
            z[i, j] = v
            half[i, j] = 0.5 * v


@numba.njit(cache=True, nogil=True)
def p_and_minus_p(t, rise, guess, p, minus_p):
    """From ``t`` = tanh(z/2): ``p`` = clip(γ + rise·(0.5 + 0.5·t), 1e-12, 1 − 1e-12) and its
    negation (for numpy's ``log`` and ``log1p``); ``rise[i]`` = (1 − γ) − λ of row i."""
    n_r, n_l = t.shape
    lo, hi = 1e-12, 1 - 1e-12
    for i in range(n_r):
        c = rise[i]
        for j in range(n_l):
            v = guess + c * (0.5 + 0.5 * t[i, j])
            if v < lo:
                v = lo
            elif v > hi:
                v = hi
            p[i, j] = v
            minus_p[i, j] = -v


@numba.njit(cache=True, nogil=True)
def minus_log_likelihoods(n, k, rows, log_p, log_q, out):
    """``out[i]`` = −Σ_l (k·ln p + (n − k)·ln(1 − p)) with the counts of row ``rows[i]``:
    the terms formed as numpy forms them and summed as numpy sums a row (pairwise)."""
    n_r, n_l = log_p.shape
    for i in range(n_r):
        r = rows[i]
        row = log_p[i]
        for j in range(n_l):
            kk = k[r, j]
            row[j] = kk * row[j] + (n[r, j] - kk) * log_q[i, j]
        out[i] = -pairwise_sum(row)


@numba.njit(cache=True, nogil=True)
def scoring_terms(z, t, k, n, rows, amp, scale, guess, n_par, score, info):
    """The Fisher-scoring step's score and expected information of each climbing row.

    From z = (x − α)/s and ``t`` = tanh(z/2) (numpy's): f = 0.5 + 0.5·t, p = clip(γ + amp·f,
    1e-9, 1 − 1e-9), dp/dθ = (−amp·f(1 − f)/s, −amp·f(1 − f)·z, −f) for θ = (α, log s, λ),
    v = p(1 − p); ``score[i, a]`` = Σ_l (k − n·p)/v·g_a and ``info[i, a, b]`` =
    Σ_l (n/v·g_a)·g_b over the first ``n_par`` parameters, summed l = 0, 1, … as ``np.einsum``
    sums them (counts of row ``rows[i]``).
    """
    n_r, n_l = z.shape
    lo, hi = 1e-9, 1 - 1e-9
    for i in range(n_r):
        r = rows[i]
        a, s = amp[i], scale[i]
        neg = -a
        s0 = s1 = s2 = 0.0
        i00 = i01 = i02 = i10 = i11 = i12 = i20 = i21 = i22 = 0.0
        for j in range(n_l):
            f = 0.5 + 0.5 * t[i, j]
            p = guess + a * f
            if p < lo:
                p = lo
            elif p > hi:
                p = hi
            dfdz = f * (1.0 - f)
            g0 = neg * dfdz / s
            g1 = neg * dfdz * z[i, j]
            g2 = -f
            v = p * (1.0 - p)
            nn = n[r, j]
            ws = (k[r, j] - nn * p) / v
            wi = nn / v
            s0 += ws * g0
            s1 += ws * g1
            w0, w1 = wi * g0, wi * g1
            i00 += w0 * g0
            i01 += w0 * g1
            i10 += w1 * g0
            i11 += w1 * g1
            if n_par == 3:
                s2 += ws * g2
                w2 = wi * g2
                i02 += w0 * g2
                i12 += w1 * g2
                i20 += w2 * g0
                i21 += w2 * g1
                i22 += w2 * g2
        score[i, 0], score[i, 1] = s0, s1
        info[i, 0, 0], info[i, 0, 1], info[i, 1, 0], info[i, 1, 1] = i00, i01, i10, i11
        if n_par == 3:
            score[i, 2] = s2
            info[i, 0, 2], info[i, 1, 2] = i02, i12
            info[i, 2, 0], info[i, 2, 1], info[i, 2, 2] = i20, i21, i22


@numba.njit(cache=True, nogil=True)
def candidates(th, scale, step, lo, hi, pending, cand):
    """``cand[i]`` = clip(th[p] + scale[p]·step[p], lo[p], hi[p]) for p = ``pending[i]``: a
    halved step's parameters as ``np.clip`` makes them (NaN kept; a value not above ``lo``
    becomes ``lo`` and one not below ``hi`` becomes ``hi``, which decides the sign of a zero
    as numpy's clip does)."""
    for i in range(pending.size):
        p = pending[i]
        s = scale[p]
        for c in range(th.shape[1]):
            v = th[p, c] + s * step[p, c]
            if v == v:
                if not v > lo[p, c]:
                    v = lo[p, c]
                if not v < hi[p, c]:
                    v = hi[p, c]
            cand[i, c] = v


@numba.njit(cache=True, nogil=True)
def accept(cand, cv, was, pending, new, val, scale):
    """Keep each pending row's candidate whose likelihood did not fall (``cv`` ≤ ``was`` +
    1e-12, in ``new`` and ``val``); returns the rows still pending, their ``scale`` halved."""
    left = np.empty(pending.size, dtype=pending.dtype)
    n_left = 0
    for i in range(pending.size):
        p = pending[i]
        if cv[i] <= was[p] + 1e-12:
            for c in range(cand.shape[1]):
                new[p, c] = cand[i, c]
            val[p] = cv[i]
        else:
            left[n_left] = p
            n_left += 1
            scale[p] /= 2
    return left[:n_left]


@numba.njit(cache=True, nogil=True)
def hold(th, lo, hi, score, info, n_par):
    """The active set, in place: a parameter on a bound with the score pushing outwards is
    held (its score 0, its row and column of ``info`` those of the identity), as the numpy
    route does it: ``info·f_a·f_b + h_a·I_ab`` and ``score·f`` (f = 1 − h) for every row once
    any row holds one (so that a −0.0 becomes +0.0 as there). Returns whether any did."""
    n_r = th.shape[0]
    held = np.zeros((n_r, n_par), dtype=np.bool_)
    anyheld = False
    for i in range(n_r):
        for a in range(n_par):
            s = score[i, a]
            h = (th[i, a] <= lo[i, a] and s < 0) or (th[i, a] >= hi[i, a] and s > 0)
            held[i, a] = h
            anyheld |= h
    if not anyheld:
        return False
    for i in range(n_r):
        for a in range(n_par):
            fa = 0.0 if held[i, a] else 1.0
            ha = 1.0 if held[i, a] else 0.0
            for b in range(n_par):
                fb = 0.0 if held[i, b] else 1.0
                eye = 1.0 if a == b else 0.0
                info[i, a, b] = info[i, a, b] * fa * fb + ha * eye
            score[i, a] = score[i, a] * fa
    return True
