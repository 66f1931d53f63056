"""The psychometric function's likelihood and its climb, for many data sets at once (pure).

The 3IFC logistic of :mod:`masking_lab.analysis.psychometric` in the parameters it is fitted in:
α (threshold, dB), log s (s = 1/β, the logistic scale, dB) and λ (lapse). :func:`nll` is the
negative log-likelihood of binomial counts at the levels; :func:`refit` maximises it by Fisher
scoring within bounds, every operation per row, so the rows of many sets' data sets (profile
starts, bootstrap samples) climb together and each row's fit is what it would be alone.
A study's climbs can run compiled (:mod:`masking_lab.analysis.pf_loops`: numpy's numbers bit for
bit in about half the time).
"""

from __future__ import annotations

from types import ModuleType

import numpy as np
from numpy.typing import NDArray

from masking_lab.procedures.fused import compiled_loops

__all__ = ["nll", "refit", "set_nll", "warm_compiled"]

_ITERATIONS = 25


def _loops() -> ModuleType | None:
    """The compiled loops (:mod:`masking_lab.analysis.pf_loops`); None: numba is unavailable."""
    return compiled_loops("pf_loops", "masking_lab.analysis")


def warm_compiled() -> bool:
    """Load the compiled climb now (numba and the loops' machine code from numba's cache:
    ~0.4 s and ~110 MB of a process), so that worker processes forked afterwards have it.

    Returns
    -------
    bool
        Whether :func:`refit` can run compiled (False: numba is unavailable; the numpy route
        gives the same numbers).

    Examples
    --------
    >>> isinstance(warm_compiled(), bool)
    True
    """
    if _loops() is None:
        return False
    # A tiny climb calls every loop with the argument types of a real one.
    bounds = np.array([[-10.0, 10.0], [-2.0, 3.0], [0.0, 0.1]])
    x, n, k = np.array([-1.0, 1.0]), np.array([4.0, 4.0]), np.array([[1.0, 3.0]])
    try:
        refit(x, n, k, np.array([0.0, 0.0, 0.02]), bounds, 1 / 3, True, compiled=True)
    except Exception:  # numba cannot compile here (versions, platform): numpy's route, the same
        return False
    return True


def nll(x: NDArray, n: NDArray, k: NDArray, th: NDArray, guess: float) -> NDArray:
    """Negative log-likelihood of each row's (α, log s, λ) for its counts ``k`` (rows).

    ``x`` and ``n`` are one set's levels (dB) and trials (1-D) or one row per data set (2-D).

    Examples
    --------
    >>> th = np.array([[0.0, 0.0, 0.0]])  # at x = α, p = 1/3 + (2/3)/2 = 2/3
    >>> round(float(nll(np.array([0.0]), np.array([10.0]), np.array([[5.0]]), th, 1 / 3)[0]), 4)
    7.5204
    """
    xs = x[None, :] if x.ndim == 1 else x
    z = (xs - th[:, :1]) * np.exp(-th[:, 1:2])
    p = guess + (1.0 - guess - th[:, 2:3]) * (0.5 + 0.5 * np.tanh(0.5 * z))
    p = np.clip(p, 1e-12, 1 - 1e-12)
    return -(k * np.log(p) + (n - k) * np.log1p(-p)).sum(axis=1)


def set_nll(
    x: NDArray, n: NDArray, k: NDArray, th: NDArray, guess: float, *, compiled: bool = False
) -> NDArray[np.float64]:
    """:func:`nll` of one set's counts (``x``, ``n``, ``k``: 1-D) at each row of ``th`` (a
    profile's grid), by the compiled loops when ``compiled`` and numba is available (the same
    numbers).

    Examples
    --------
    >>> th = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    >>> x, n, k = np.array([0.0]), np.array([10.0]), np.array([5.0])
    >>> bool((set_nll(x, n, k, th, 1 / 3) == nll(x, n, k[None, :], th, 1 / 3)).all())
    True
    """
    loops = _loops() if compiled else None
    if loops is None:
        return nll(x, n, k[None, :], th, guess)
    x1, n1, k1 = (np.ascontiguousarray(a, dtype=np.float64)[None, :] for a in (x, n, k))
    return _nll_rows(loops, (x1, n1, k1), np.zeros(th.shape[0], dtype=np.intp), th, guess)


def refit(
    x: NDArray[np.float64],
    n: NDArray[np.float64],
    k: NDArray[np.float64],
    start: NDArray[np.float64],
    bounds: NDArray[np.float64],
    guess: float,
    fit_lapse: bool,
    *,
    compiled: bool = False,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Maximum-likelihood fits of many data sets at once (rows of ``k``) by Fisher scoring.

    Parameters are (α, log scale, λ); ``start`` is one row or one per data set. Steps are
    halved while the likelihood falls and clipped to ``bounds`` (rows: α, log scale, λ;
    columns low, high; or one such block per data set); a λ held on a bound by the score is
    kept there (active set). ``x`` and ``n`` are shared levels and trials (1-D) or one row
    per data set, so the data sets of many psychometric functions with the same number of
    levels climb together: every operation is per row, so a row's fit does not depend on
    the rows beside it. Returns the parameters and which rows converged inside the α and
    scale bounds. ``compiled`` climbs with the compiled loops where numba is available (the
    same numbers; worth it for a study's hundreds of thousands of data sets, see
    :func:`warm_compiled`).

    Examples
    --------
    >>> x, n, k = np.array([-4.0, 0.0, 4.0]), np.full(3, 100.0), np.array([[40.0, 67.0, 97.0]])
    >>> bounds = np.array([[-20.0, 20.0], [np.log(0.1), np.log(20.0)], [0.0, 0.1]])
    >>> theta, inside = refit(x, n, k, np.array([0.0, 0.0, 0.02]), bounds, 1 / 3, False)
    >>> bool(inside[0]), np.round(theta[0], 2).tolist()  # α dB, log s, λ held
    (True, [-0.19, 0.18, 0.02])
    """
    b = k.shape[0]
    loops = _loops() if compiled else None
    xr = np.broadcast_to(x, k.shape)
    nr = np.broadcast_to(n, k.shape)
    if loops is not None:  # the loops read rows in place: one contiguous float64 layout
        xr, nr, k = (np.ascontiguousarray(a, dtype=np.float64) for a in (xr, nr, k))
    br = np.broadcast_to(bounds, (b, 3, 2))
    lo_all, hi_all = br[:, :, 0], br[:, :, 1]
    theta = np.array(np.broadcast_to(start, (b, 3)), dtype=float)
    n_par = 3 if fit_lapse else 2
    if loops is None:
        cur = nll(xr, nr, k, theta, guess)
    else:
        cur = _nll_rows(loops, (xr, nr, k), np.arange(b), theta, guess)
    active = np.ones(b, dtype=bool)
    for _ in range(_ITERATIONS):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        th = theta[idx]
        lo, hi = lo_all[idx], hi_all[idx]  # fresh C-ordered copies, as the compiled loops read them
        if loops is None:
            score, info = _scoring(xr[idx], nr[idx], k[idx], th, guess, n_par)
        else:
            score, info = _scoring_rows(loops, (xr, nr, k), idx, th, guess, n_par)
        info += 1e-9 * np.eye(n_par)
        # A parameter on a bound with the score pushing outwards is held there (active set)
        # and the others step alone: clipping the joint step would stall the climb.
        if loops is None:
            on = th[:, :n_par]
            held = ((on <= lo[:, :n_par]) & (score < 0)) | ((on >= hi[:, :n_par]) & (score > 0))
            if held.any():
                free = (~held).astype(float)
                info = info * free[:, :, None] * free[:, None, :] + held[:, :, None] * np.eye(n_par)
                score = score * free
        else:
            loops.hold(th, lo, hi, score, info, n_par)
        step = np.zeros_like(th)
        step[:, :n_par] = np.linalg.solve(info, score[..., None])[..., 0]
        # Halve the step of the rows whose likelihood fell, and only theirs.
        was = cur[idx]
        new, val = _halved(loops, (xr, nr, k), idx, th, step, (lo, hi), was, guess)
        gain = was - val
        theta[idx], cur[idx] = new, val
        active[idx] = gain > 1e-6  # log-likelihood units: far below any difference that matters
    inside = (theta[:, 0] > lo_all[:, 0] + 1e-6) & (theta[:, 0] < hi_all[:, 0] - 1e-6)
    inside &= theta[:, 1] < hi_all[:, 1] - 1e-6
    return theta, inside  # a row still climbing after _ITERATIONS sits on a flat ridge


def _scoring(
    x: NDArray, n: NDArray, k: NDArray, th: NDArray, guess: float, n_par: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The Fisher step's score and expected information of each row, less the ridge."""
    s = np.exp(th[:, 1:2])
    z = (x - th[:, :1]) / s
    f = 0.5 + 0.5 * np.tanh(0.5 * z)
    amp = 1.0 - guess - th[:, 2:3]
    p = np.clip(guess + amp * f, 1e-9, 1 - 1e-9)
    dfdz = f * (1.0 - f)
    g = np.stack([-amp * dfdz / s, -amp * dfdz * z, -f][:n_par], axis=-1)  # dp/dθ
    v = p * (1.0 - p)
    score = np.einsum("bl,blp->bp", (k - n * p) / v, g)
    return score, np.einsum("bl,blp,blq->bpq", n / v, g, g)


_Counts = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]
"""Levels x (dB), trials n and correct answers k of every data set: C-contiguous (B, L) rows."""


def _scoring_rows(
    loops: ModuleType,
    counts: _Counts,
    rows: NDArray[np.intp],
    th: NDArray,
    guess: float,
    n_par: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """:func:`_scoring` of the data sets ``rows`` of ``counts`` by the compiled loops: numpy's
    ``exp`` and ``tanh`` on arrays shaped as there, the arithmetic between them fused (the
    same numbers)."""
    x, n, k = counts
    s = np.exp(th[:, 1])  # a fresh C-ordered row of scales, as the loops read it
    z = np.empty((rows.size, x.shape[1]))
    t = np.empty_like(z)
    loops.z_and_half(x, rows, th[:, 0].copy(), s, z, t)
    np.tanh(t, out=t)
    amp = 1.0 - guess - th[:, 2]
    score = np.empty((rows.size, n_par))
    info = np.empty((rows.size, n_par, n_par))
    loops.scoring_terms(z, t, k, n, rows, amp, s, guess, n_par, score, info)
    return score, info


def _halved(
    loops: ModuleType | None,
    counts: _Counts,
    idx: NDArray[np.intp],
    th: NDArray,
    step: NDArray,
    bounds: tuple[NDArray, NDArray],
    was: NDArray,
    guess: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The climbing rows' (``idx``) next parameters and likelihoods: each row's step within
    its ``bounds`` (low, high), halved up to ten times while its likelihood falls below
    ``was``; on numpy's route or, the same numbers, the compiled loops' (the candidates and
    their acceptance fused, the likelihood by :func:`_nll_rows`)."""
    scale = np.ones(idx.size)
    new, val = th.copy(), was.copy()
    lo, hi = bounds
    x, n, k = counts
    pending = np.arange(idx.size)
    for _half in range(10):
        if loops is None:
            cand = np.clip(
                th[pending] + scale[pending, None] * step[pending], lo[pending], hi[pending]
            )
            rows = idx[pending]
            cv = nll(x[rows], n[rows], k[rows], cand, guess)
            ok = cv <= was[pending] + 1e-12
            new[pending[ok]] = cand[ok]
            val[pending[ok]] = cv[ok]
            pending = pending[~ok]
            scale[pending] /= 2
        else:
            cand = np.empty((pending.size, th.shape[1]))
            loops.candidates(th, scale, step, lo, hi, pending, cand)
            cv = _nll_rows(loops, counts, idx[pending], cand, guess)
            pending = loops.accept(cand, cv, was, pending, new, val, scale)
        if pending.size == 0:
            break
    return new, val


def _nll_rows(
    loops: ModuleType, counts: _Counts, rows: NDArray[np.intp], th: NDArray, guess: float
) -> NDArray[np.float64]:
    """:func:`nll` of the data sets ``rows`` of ``counts`` (parameters ``th``, one row each)
    by the compiled loops."""
    x, n, k = counts
    e = np.exp(-th[:, 1:2])
    t = np.empty((rows.size, x.shape[1]))
    loops.half_z(x, rows, th[:, 0].copy(), e[:, 0].copy(), t)
    np.tanh(t, out=t)
    rise = 1.0 - guess - th[:, 2:3]
    p, q = np.empty_like(t), np.empty_like(t)
    loops.p_and_minus_p(t, rise[:, 0].copy(), guess, p, q)
    np.log(p, out=p)
    np.log1p(q, out=q)
    out = np.empty(rows.size)
    loops.minus_log_likelihoods(n, k, rows, p, q, out)
    return out
