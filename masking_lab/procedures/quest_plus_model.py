"""The QUEST+ grids and likelihood table: the forced-choice logistic on a (level × threshold ×
nuisance) grid, in dB. Used by :mod:`masking_lab.procedures.quest_plus`."""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


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
