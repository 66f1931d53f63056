"""Psychometric functions for n-interval forced choice, on a dB axis.

p(correct | x) = γ + (1 − γ − λ) · F((x − α) / s)

with F the logistic CDF, γ the guess rate (1/3 for 3IFC), λ the lapse rate, α the location and
s the scale, all in dB. We parameterise by ``threshold_db``: the level at which p(correct) equals
``p_at_threshold`` (default Levitt's 1-up-3-down target 0.5^(1/3) ≈ 0.794), so that a staircase
that converges where Levitt says estimates exactly ``threshold_db``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import InputError

GUESS_3IFC = 1.0 / 3.0
LEVITT_1U3D = 0.5 ** (1.0 / 3.0)


@dataclass(frozen=True)
class Psychometric:
    """A logistic psychometric function for forced choice.

    Attributes
    ----------
    threshold_db : float
        Level (dB, any reference) at which p(correct) = ``p_at_threshold``.
    scale_db : float
        Logistic scale s in dB (> 0); 10–90 % of the rising part spans 2·ln(9)·s ≈ 4.4·s dB.
    guess : float
        Guess rate γ (1/3 for 3IFC).
    lapse : float
        Lapse rate λ, 0 ≤ λ < 1 − γ.
    p_at_threshold : float
        p(correct) that defines ``threshold_db``; must lie strictly between γ and 1 − λ.

    Raises
    ------
    InputError
        For a non-positive scale, or a guess, lapse or ``p_at_threshold`` out of range.

    Examples
    --------
    A 3IFC observer with an AL of −30 dB re 1 V: far below it p(correct) is the guess rate 1/3,
    at it Levitt's 0.794, far above it 1 − λ:

    >>> psy = Psychometric(threshold_db=-30.0)
    >>> np.round(psy.p_correct([-1e6, -30.0, 1e6]), 3).tolist()
    [0.333, 0.794, 0.98]
    """

    threshold_db: float
    scale_db: float = 1.5
    guess: float = GUESS_3IFC
    lapse: float = 0.02
    p_at_threshold: float = LEVITT_1U3D

    def __post_init__(self) -> None:
        if not self.scale_db > 0:
            raise InputError(f"scale_db must be > 0 dB, got {self.scale_db}")
        if not 0 <= self.guess < 1:
            raise InputError(f"guess must be in [0, 1), got {self.guess}")
        if not 0 <= self.lapse < 1 - self.guess:
            raise InputError(f"lapse must be in [0, 1 - guess), got {self.lapse}")
        if not self.guess < self.p_at_threshold < 1 - self.lapse:
            raise InputError(
                f"p_at_threshold={self.p_at_threshold} must lie between guess={self.guess} "
                f"and 1 - lapse={1 - self.lapse}"
            )

    @property
    def location_db(self) -> float:
        """α in dB: the logistic's midpoint (below ``threshold_db`` for Levitt's target).

        Examples
        --------
        >>> round(Psychometric(threshold_db=-30.0, scale_db=1.5).location_db, 3)
        -31.357
        """
        q = (self.p_at_threshold - self.guess) / (1.0 - self.guess - self.lapse)
        return self.threshold_db - self.scale_db * float(np.log(q / (1.0 - q)))

    def p_correct(self, level_db: ArrayLike) -> NDArray[np.float64]:
        """p(correct) at ``level_db`` (dB, same reference as ``threshold_db``); −inf gives γ.

        Parameters
        ----------
        level_db : array_like
            Stimulus level(s) in dB.

        Returns
        -------
        ndarray
            Probability of a correct answer, in [γ, 1 − λ], same shape as ``level_db``.

        Examples
        --------
        >>> psy = Psychometric(threshold_db=-30.0)
        >>> round(float(psy.p_correct(float("-inf"))), 4)
        0.3333
        >>> round(float(psy.p_correct(-20.0)), 3)
        0.98
        """
        x = np.asarray(level_db, dtype=float)
        z = (x - self.location_db) / self.scale_db
        # expit without overflow warnings at ±1e6 dB
        e = np.exp(-np.abs(z))
        f = np.where(z >= 0, 1.0 / (1.0 + e), e / (1.0 + e))
        return self.guess + (1.0 - self.guess - self.lapse) * f
