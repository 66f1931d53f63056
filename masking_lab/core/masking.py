"""Masking functions: the ramp ``shift = max(0, a + b·x)`` of paper Eq. (1)–(2).

``x`` is the masker level in dB SL; the result is the rise of the target's absolute threshold
(AL shift) in dB. Below the knee ``x = −a/b`` the masker does not mask at all.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray


def ramp(x: ArrayLike, intercept_db: float, slope: float) -> NDArray[np.float64]:
    """AL shift in dB for masker level(s) ``x`` in dB SL: ``max(0, intercept_db + slope·x)``."""
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
    """

    target: str
    masker: str
    intercept_db: float
    slope: float

    @property
    def knee_db_sl(self) -> float:
        """Masker level in dB SL where masking starts (−a/b); −inf/+inf for a flat ramp."""
        if self.slope == 0:
            return -math.inf if self.intercept_db > 0 else math.inf
        return -self.intercept_db / self.slope

    def shift_db(self, masker_level_db_sl: ArrayLike) -> NDArray[np.float64]:
        """AL shift in dB at the given masker level(s) in dB SL."""
        return ramp(masker_level_db_sl, self.intercept_db, self.slope)
