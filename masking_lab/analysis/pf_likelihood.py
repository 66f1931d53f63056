"""The psychometric function's likelihood and its climb, for many data sets at once (pure).

The 3IFC logistic of :mod:`masking_lab.analysis.psychometric` in the parameters it is fitted in:
α (threshold, dB), log s (s = 1/β, the logistic scale, dB) and λ (lapse). :func:`nll` is the
negative log-likelihood of binomial counts at the levels; :func:`refit` maximises it by Fisher
scoring within bounds, every operation per row, so the rows of many sets' data sets (profile
starts, bootstrap samples) climb together and each row's fit is what it would be alone.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

__all__ = ["nll", "refit"]

_ITERATIONS = 25


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


def refit(
    x: NDArray[np.float64],
    n: NDArray[np.float64],
    k: NDArray[np.float64],
    start: NDArray[np.float64],
    bounds: NDArray[np.float64],
    guess: float,
    fit_lapse: bool,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Maximum-likelihood fits of many data sets at once (rows of ``k``) by Fisher scoring.

    Parameters are (α, log scale, λ); ``start`` is one row or one per data set. Steps are
    halved while the likelihood falls and clipped to ``bounds`` (rows: α, log scale, λ;
    columns low, high; or one such block per data set); a λ held on a bound by the score is
    kept there (active set). ``x`` and ``n`` are shared levels and trials (1-D) or one row
    per data set, so the data sets of many psychometric functions with the same number of
    levels climb together: every operation is per row, so a row's fit does not depend on
    the rows beside it. Returns the parameters and which rows converged inside the α and
    scale bounds.

    Examples
    --------
    >>> x, n, k = np.array([-4.0, 0.0, 4.0]), np.full(3, 100.0), np.array([[40.0, 67.0, 97.0]])
    >>> bounds = np.array([[-20.0, 20.0], [np.log(0.1), np.log(20.0)], [0.0, 0.1]])
    >>> theta, inside = refit(x, n, k, np.array([0.0, 0.0, 0.02]), bounds, 1 / 3, False)
    >>> bool(inside[0]), np.round(theta[0], 2).tolist()  # α dB, log s, λ held
    (True, [-0.19, 0.18, 0.02])
    """
    b = k.shape[0]
    xr = np.broadcast_to(x, k.shape)
    nr = np.broadcast_to(n, k.shape)
    br = np.broadcast_to(bounds, (b, 3, 2))
    lo_all, hi_all = br[:, :, 0], br[:, :, 1]
    theta = np.array(np.broadcast_to(start, (b, 3)), dtype=float)
    n_par = 3 if fit_lapse else 2
    cur = nll(xr, nr, k, theta, guess)
    active = np.ones(b, dtype=bool)
    for _ in range(_ITERATIONS):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        th, kk, xx, nn = theta[idx], k[idx], xr[idx], nr[idx]
        lo, hi = lo_all[idx], hi_all[idx]
        s = np.exp(th[:, 1:2])
        z = (xx - th[:, :1]) / s
        f = 0.5 + 0.5 * np.tanh(0.5 * z)
        amp = 1.0 - guess - th[:, 2:3]
        p = np.clip(guess + amp * f, 1e-9, 1 - 1e-9)
        dfdz = f * (1.0 - f)
        g = np.stack([-amp * dfdz / s, -amp * dfdz * z, -f][:n_par], axis=-1)  # dp/dθ
        v = p * (1.0 - p)
        score = np.einsum("bl,blp->bp", (kk - nn * p) / v, g)
        info = np.einsum("bl,blp,blq->bpq", nn / v, g, g) + 1e-9 * np.eye(n_par)
        # A parameter on a bound with the score pushing outwards is held there (active set)
        # and the others step alone: clipping the joint step would stall the climb.
        on = th[:, :n_par]
        held = ((on <= lo[:, :n_par]) & (score < 0)) | ((on >= hi[:, :n_par]) & (score > 0))
        if held.any():
            free = (~held).astype(float)
            info = info * free[:, :, None] * free[:, None, :] + held[:, :, None] * np.eye(n_par)
            score = score * free
        step = np.zeros_like(th)
        step[:, :n_par] = np.linalg.solve(info, score[..., None])[..., 0]
        # Halve the step of the rows whose likelihood fell, and only theirs.
        scale = np.ones(idx.size)
        new, val, was = th.copy(), cur[idx], cur[idx]
        pending = np.arange(idx.size)
        for _half in range(10):
            cand = np.clip(
                th[pending] + scale[pending, None] * step[pending], lo[pending], hi[pending]
            )
            cv = nll(xx[pending], nn[pending], kk[pending], cand, guess)
            ok = cv <= was[pending] + 1e-12
            new[pending[ok]] = cand[ok]
            val[pending[ok]] = cv[ok]
            pending = pending[~ok]
            if pending.size == 0:
                break
            scale[pending] /= 2
        gain = was - val
        theta[idx], cur[idx] = new, val
        active[idx] = gain > 1e-6  # log-likelihood units: far below any difference that matters
    inside = (theta[:, 0] > lo_all[:, 0] + 1e-6) & (theta[:, 0] < hi_all[:, 0] - 1e-6)
    inside &= theta[:, 1] < hi_all[:, 1] - 1e-6
    return theta, inside  # a row still climbing after _ITERATIONS sits on a flat ridge
