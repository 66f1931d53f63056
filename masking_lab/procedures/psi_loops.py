"""Compiled loops (numba) for the psi-marginal placement's screen and its float64 check.

Imported only through :mod:`masking_lab.procedures.psi_screen`, which has numpy routes for
both when numba is missing or disabled. Unlike :mod:`masking_lab.procedures.jit_loops`, these
loops need not match numpy bit for bit: the screen only bounds the entropies, and the check's
entropies choose among levels whose entropies differ by far more than their rounding.
"""

from __future__ import annotations

import math

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def add_column_sums(m, log_m, pk, h):
    """``pk[r, s] += Σ_t m[t, r, s]`` and ``h[r, s] += Σ_t m·log_m``, accumulated in float64,
    with 0·log 0 taken as 0 (``log_m`` is -inf where ``m`` is 0; elsewhere above -1e30).

    ``m`` and ``log_m`` are float32 arrays of shape (T, R, S); ``pk`` and ``h`` float64 (R, S).
    """
    n_t, n_r, n_s = m.shape
    floor = np.float32(-1e30)
    for t in range(n_t):
        for r in range(n_r):
            for s in range(n_s):
                x = np.float64(m[t, r, s])
                pk[r, s] += x
                h[r, s] += x * np.float64(max(log_m[t, r, s], floor))


@numba.njit(cache=True, nogil=True)
def entropy_bounds(pk, h, rel, floor, tail, tail_mass, safety, low, high):
    """The screen's bounds from its float64 sums (:func:`~masking_lab.procedures.psi_screen.
    screen`, whose numpy route computes the same): per track r and level s, with both answers'
    ``pk`` and ``h`` side by side in (R, 2S), the entropy ± ``safety``·(``rel``·spread +
    ``floor`` + ``tail`` + ``tail_mass``·max |ln p|) into ``low`` and ``high`` (R, S).
    """
    n_r, n_s = low.shape
    for r in range(n_r):
        for s in range(n_s):
            entropy = 0.0
            spread = 0.0
            worst = 0.0
            for k in (s, s + n_s):
                p = pk[r, k]
                log_p = math.log(max(p, 1e-300))  # an answer no m reaches adds 0·ln 0 = 0
                entropy += p * log_p - h[r, k]
                spread += -h[r, k] + p * (2.0 - log_p)
                worst = max(worst, abs(log_p))
            margin = safety * (rel * spread + floor + tail + tail_mass * worst)
            low[r, s] = entropy - margin
            high[r, s] = entropy + margin


@numba.njit(cache=True, nogil=True)
def trimmed_float32(post, flush, tail, out):
    """``out[t, r, n]`` = ``post[r, t, n]`` in float32, 0 where that is below ``flush`` and at
    the thresholds of track r's two tails that hold at most ``tail`` of its mass each; returns
    (first, stop) of the thresholds where some track's value is not 0 ((0, 0) if none).

    ``post`` is float64 of shape (R, T, N), ``out`` float32 of shape (T, R, N).
    """
    n_r, n_t, n_n = post.shape
    lo, hi = n_t, 0
    cut = np.float32(flush)
    out[:] = 0.0
    for r in range(n_r):
        first, held = 0, 0.0
        while first < n_t:
            mass = 0.0
            for n in range(n_n):
                mass += post[r, first, n]
            if held + mass > tail:
                break
            held += mass
            first += 1
        stop, held = n_t, 0.0
        while stop > first:
            mass = 0.0
            for n in range(n_n):
                mass += post[r, stop - 1, n]
            if held + mass > tail:
                break
            held += mass
            stop -= 1
        for t in range(first, stop):
            for n in range(n_n):
                v = np.float32(post[r, t, n])
                if v >= cut:
                    out[t, r, n] = v
                    lo = min(lo, t)
                    hi = max(hi, t + 1)
    return (lo, hi) if hi > 0 else (0, 0)


@numba.njit(cache=True, nogil=True)
def _answer_term(post, like, r, s):
    """p·ln p of one answer's probability minus Σ_t m·ln m, m the joint (nats, float64)."""
    n_t, n_n = post.shape[1], post.shape[2]
    pk = 0.0
    h = 0.0
    for t in range(n_t):
        m = 0.0
        for n in range(n_n):
            m += post[r, t, n] * like[s, t, n]
        pk += m
        if m > 0.0:
            h += m * math.log(m)
    return (pk * math.log(pk) if pk > 0.0 else 0.0) - h


@numba.njit(cache=True, nogil=True)
def pair_entropies(post, p_correct, p_wrong, rows, levels, out):
    """``out[k]``: expected entropy of track ``rows[k]`` after a trial at level ``levels[k]``.

    ``post`` has shape (R, T, N) and the tables (S, T, N), all float64.
    """
    for k in range(rows.size):
        r, s = rows[k], levels[k]
        out[k] = _answer_term(post, p_correct, r, s) + _answer_term(post, p_wrong, r, s)
