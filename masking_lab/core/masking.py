"""Masking functions: the ramp ``shift = max(0, a + b·x)`` of paper Eq. (1)–(2).

``x`` is the masker level in dB SL; the result is the rise of the target's absolute threshold
(AL shift) in dB. Below the knee ``x = −a/b`` the masker does not mask at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def ramp(
    x: ArrayLike, intercept_db: float | NDArray[np.float64], slope: float | NDArray[np.float64]
) -> NDArray[np.float64]:
    """AL shift in dB for masker level(s) ``x`` in dB SL: ``max(0, intercept_db + slope·x)``.

    Parameters
    ----------
    x : array_like
        Masker level(s) in dB SL.
    intercept_db : float
        Ramp intercept a, dB of AL shift at a 0 dB SL masker (before the max with 0).
    slope : float
        Ramp slope b, dB of AL shift per dB SL of masker.

    Returns
    -------
    ndarray
        AL shift(s) of the target in dB (≥ 0), same shape as ``x``.

    Examples
    --------
    With a = −4 dB and b = 0.8 the knee is at 5 dB SL; above it the shift grows 0.8 dB/dB:

    >>> ramp([-10.0, 0.0, 10.0, 20.0], intercept_db=-4.0, slope=0.8).tolist()
    [0.0, 0.0, 4.0, 12.0]
    """
    return np.maximum(0.0, intercept_db + slope * np.asarray(x, dtype=float))


@dataclass(frozen=True)
class MaskingFunction:
    """The masking of ``target`` by ``masker``, as a ramp.

    Attributes
    ----------
    target : str
        Stimulus name of the masked stimulus (e.g. ``"EV270"``).
    masker : str
        Stimulus name of the masker (e.g. ``"MV120"``).
    intercept_db : float
        Ramp intercept a in dB (AL shift at a 0 dB SL masker, before the max with 0).
    slope : float
        Ramp slope b in dB of AL shift per dB SL of masker (≥ 0 in practice).

    Examples
    --------
    >>> f = MaskingFunction("EV270", "MV120", intercept_db=-4.0, slope=0.8)
    >>> f.knee_db_sl
    5.0
    >>> f.shift_db([0.0, 10.0, 20.0]).tolist()
    [0.0, 4.0, 12.0]
    """

    target: str
    masker: str
    intercept_db: float
    slope: float

    @property
    def knee_db_sl(self) -> float:
        """Masker level in dB SL where masking starts (−a/b); −inf/+inf for a flat ramp.

        Examples
        --------
        >>> MaskingFunction("EV270", "MV120", intercept_db=-4.0, slope=0.8).knee_db_sl
        5.0
        >>> MaskingFunction("EV270", "MV120", intercept_db=0.0, slope=0.0).knee_db_sl
        inf
        """
        if self.slope == 0:
            return -math.inf if self.intercept_db > 0 else math.inf
        return -self.intercept_db / self.slope

    def shift_db(self, masker_level_db_sl: ArrayLike) -> NDArray[np.float64]:
        """AL shift in dB at the given masker level(s) in dB SL.

        Parameters
        ----------
        masker_level_db_sl : array_like
            Masker level(s), dB SL.

        Returns
        -------
        ndarray
            AL shift(s) of the target, dB (≥ 0).

        Examples
        --------
        >>> f = MaskingFunction("EV270", "MV120", intercept_db=-4.0, slope=0.8)
        >>> float(f.shift_db(15.0))
        8.0
        """
        return ramp(masker_level_db_sl, self.intercept_db, self.slope)
