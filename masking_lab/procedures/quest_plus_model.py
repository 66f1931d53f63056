"""The QUEST+ grids, likelihood table and placement rule: the forced-choice logistic on a (level
× threshold × nuisance) grid, in dB, and the expected posterior entropy of each level. Used by
:mod:`masking_lab.procedures.quest_plus` (which re-exports :func:`expected_entropy`)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import numpy as np
from numpy.typing import NDArray

from masking_lab.procedures.base import TrackState

if TYPE_CHECKING:
    from masking_lab.procedures.quest_plus import Tables

EntropyOver = Literal["threshold", "all"]

#: Elements of the (tracks × stimuli × thresholds) work array per chunk in
#: :func:`expected_entropy`; bounds its memory to ~50 MB whatever the batch size.
_CHUNK_ELEMENTS = 6_000_000


class PosteriorTrack(TrackState):
    """A track that holds a posterior array: equal by value (arrays compared element-wise),
    unhashable on purpose."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        mine, theirs = vars(self), vars(other)
        return mine.keys() == theirs.keys() and all(
            np.array_equal(v, theirs[k]) if isinstance(v, np.ndarray) else v == theirs[k]
            for k, v in mine.items()
        )

    __hash__ = None  # type: ignore[assignment]  # it holds arrays; equality is by value


def grid_db(lo: float, hi: float, step: float) -> NDArray[np.float64]:
    """lo, lo + step, … up to hi (inclusive within 1e-9 dB), dB.

    Rounded to 1e-9 dB so that the levels are the decimal numbers a protocol writes (−20.0,
    −19.5, …), not their 0.1-ulp neighbours.

    Examples
    --------
    >>> grid_db(-1.0, 0.0, 0.5).tolist()
    [-1.0, -0.5, 0.0]
    """
    n = math.floor((hi - lo) / step + 1e-9) + 1
    return np.round(lo + step * np.arange(n), 9)


def psychometric_table(
    levels_db: NDArray[np.float64],
    thresholds_db: NDArray[np.float64],
    nuisance: NDArray[np.float64],
    guess: float,
    p_at_threshold: float,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """p(correct) and p(wrong), shape (S, T, N), of the forced-choice logistic.

    Parameters
    ----------
    levels_db : ndarray, shape (S,)
        Stimulus levels, dB.
    thresholds_db : ndarray, shape (T,)
        Thresholds (level where p(correct) = ``p_at_threshold``), dB.
    nuisance : ndarray, shape (N, 2)
        (logistic scale in dB, lapse rate) pairs.
    guess, p_at_threshold : float
        γ and the p defining the threshold.

    Examples
    --------
    >>> from masking_lab.core.psychometric import LEVITT_1U3D
    >>> pc, pw = psychometric_table(np.array([0.0]), np.array([0.0]), np.array([[1.5, 0.02]]),
    ...                             1 / 3, LEVITT_1U3D)
    >>> round(float(pc[0, 0, 0]), 4), round(float(pc[0, 0, 0] + pw[0, 0, 0]), 12)
    (0.7937, 1.0)
    """
    scale, lapse = nuisance[:, 0], nuisance[:, 1]
    rise = 1.0 - guess - lapse
    q = (p_at_threshold - guess) / rise
    location = thresholds_db[:, None] - scale[None, :] * np.log(q / (1.0 - q))  # (T, N)
    z = (levels_db[:, None, None] - location[None]) / scale[None, None, :]
    e = np.exp(-np.abs(z))
    small, big = e / (1.0 + e), 1.0 / (1.0 + e)
    f = np.where(z >= 0, big, small)  # F(z)
    g = np.where(z >= 0, small, big)  # 1 − F(z), without cancellation
    return guess + rise * f, lapse + rise * g


def expected_entropy(
    t: Tables, posterior: NDArray[np.float64], entropy_over: EntropyOver = "threshold"
) -> NDArray[np.float64]:
    """Expected posterior entropy (nats) after one trial at each stimulus level, per track.

    Parameters
    ----------
    t : Tables
        From :func:`masking_lab.procedures.quest_plus.tables`.
    posterior : ndarray, shape (R, T, N)
        Current posteriors of R tracks (each summing to 1).
    entropy_over : {"threshold", "all"}
        Entropy of the threshold's marginal posterior (psi-marginal) or of the joint one.

    Returns
    -------
    ndarray, shape (R, S)
        Σ over answers of p(answer) · H(posterior after that answer).

    Examples
    --------
    >>> from masking_lab.procedures.quest_plus import QuestPlusSettings, tables
    >>> t = tables(QuestPlusSettings(0.0, 5.0, max_trials=5))
    >>> expected_entropy(t, t.prior[None]).shape
    (1, 11)
    """
    r, n_t, n_n = posterior.shape
    out = np.zeros((r, t.levels_db.size))
    if n_n == 1 or entropy_over == "all":
        # Σ j·log j over the grid with j = post·L is linear in post·log post and in post, so the
        # entropies for all levels come from two matrix products (no (R, S, P) array).
        flat = posterior.reshape(r, -1)
        plogp = xlogx(flat)
        for like, llogl in zip((t.p_correct, t.p_wrong), t.xlogx_tables, strict=True):
            lf = like.reshape(like.shape[0], -1)
            pk = flat @ lf.T
            sj = plogp @ lf.T + flat @ llogl.T
            out += pk * np.log(pk) - sj
        return out
    # psi-marginal: the threshold's marginal after the answer needs the (R, S, T) array.
    per_row = max(1, _CHUNK_ELEMENTS // (t.levels_db.size * n_t))
    for a in range(0, r, per_row):
        post_t = np.ascontiguousarray(posterior[a : a + per_row].transpose(1, 0, 2))  # (T, R, N)
        for like in (t.p_correct, t.p_wrong):
            m = post_t @ like.transpose(1, 2, 0)  # (T, R, S): Σ_n post·L
            pk = m.sum(axis=0)
            out[a : a + per_row] += pk * np.log(pk) - xlogx(m).sum(axis=0)
    return out


def xlogx(a: NDArray[np.float64]) -> NDArray[np.float64]:
    """a·ln a (nats) element by element, with 0·ln 0 = 0 (posterior cells that underflowed).

    Examples
    --------
    >>> xlogx(np.array([0.0, 1.0, 0.5])).tolist() == [0.0, 0.0, 0.5 * np.log(0.5)]
    True
    """
    if a.size and a.min() > 0:
        # The usual case, no cell underflowed: a plain log, the same values as the masked one
        # below (element by element) in about two thirds of its time, on the hot path of
        # every Bayesian placement.
        out = np.log(a)
        out *= a
        return out
    out = np.zeros_like(a)
    np.log(a, out=out, where=a > 0)  # no log of the cells that stay 0: one pass fewer
    out *= a
    return out
