"""Level conversions: volts ↔ dB re 1 V ↔ dB SL.

All staircase, masking and solver arithmetic is in dB. A drive amplitude in volts (peak) maps to
dB re 1 V as ``20·log10(V / 1 V)``. A sensation level (dB SL) is the level in dB above the
participant's unmasked absolute threshold (AL) for the same stimulus, so
``level_db_sl = level_db_v − unmasked_al_db_v``.

Guards: 0 V is −inf dB and is only accepted where the caller says so (``allow_zero=True``, which
returns ``-inf`` explicitly); NaN and +inf are always refused, so no NaN leaks downstream.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from masking_lab.core.errors import LevelError


def volts_to_db_v(volts: float, *, allow_zero: bool = False) -> float:
    """Convert a peak amplitude in volts to dB re 1 V.

    Parameters
    ----------
    volts : float
        Peak amplitude in V, ≥ 0.
    allow_zero : bool
        If True, 0 V returns ``-inf`` dB re 1 V (silence); otherwise 0 V raises.

    Returns
    -------
    float
        Level in dB re 1 V (``-inf`` only for 0 V with ``allow_zero``).

    Raises
    ------
    LevelError
        For negative, NaN or infinite volts, or 0 V without ``allow_zero``.

    Examples
    --------
    Halving the amplitude lowers the level by about 6 dB:

    >>> round(volts_to_db_v(0.5), 2)
    -6.02
    >>> volts_to_db_v(0.0, allow_zero=True)
    -inf
    """
    v = float(volts)
    if math.isnan(v) or math.isinf(v):
        raise LevelError(f"amplitude must be a finite number of volts, got {volts!r}")
    if v < 0:
        raise LevelError(f"amplitude must be ≥ 0 V (it is a peak amplitude), got {v} V")
    if v == 0:
        if allow_zero:
            return -math.inf
        raise LevelError("0 V is −inf dB re 1 V: pass allow_zero=True where silence is meant")
    return 20.0 * math.log10(v)


def db_v_to_volts(level_db_v: float) -> float:
    """Convert dB re 1 V to a peak amplitude in volts; ``-inf`` dB gives exactly 0 V.

    Parameters
    ----------
    level_db_v : float
        Drive level in dB re 1 V (finite, or ``-inf`` for silence).

    Returns
    -------
    float
        Peak amplitude in V.

    Raises
    ------
    LevelError
        For NaN or +inf.

    Examples
    --------
    >>> round(db_v_to_volts(-20.0), 6)
    0.1
    >>> db_v_to_volts(float("-inf"))
    0.0
    """
    x = float(level_db_v)
    if math.isnan(x) or x == math.inf:
        raise LevelError(f"level must be a finite dB re 1 V value (or -inf for 0 V), got {x!r}")
    if x == -math.inf:
        return 0.0
    return 10.0 ** (x / 20.0)


def db_sl_to_db_v(level_db_sl: float, unmasked_al_db_v: float) -> float:
    """Sensation level (dB SL) → drive level (dB re 1 V), given the unmasked AL in dB re 1 V.

    Parameters
    ----------
    level_db_sl : float
        Level in dB above the participant's unmasked absolute threshold (AL).
    unmasked_al_db_v : float
        That participant's unmasked AL for the same stimulus, dB re 1 V.

    Returns
    -------
    float
        Drive level in dB re 1 V.

    Raises
    ------
    LevelError
        If either value is not finite.

    Examples
    --------
    A masker 10 dB above an AL of −32.5 dB re 1 V is driven at −22.5 dB re 1 V:

    >>> db_sl_to_db_v(10.0, -32.5)
    -22.5
    """
    _finite("level_db_sl", level_db_sl)
    _finite("unmasked_al_db_v", unmasked_al_db_v)
    return float(level_db_sl) + float(unmasked_al_db_v)


def db_v_to_db_sl(level_db_v: float, unmasked_al_db_v: float) -> float:
    """Drive level (dB re 1 V) → sensation level (dB SL), given the unmasked AL in dB re 1 V.

    Parameters
    ----------
    level_db_v : float
        Drive level in dB re 1 V.
    unmasked_al_db_v : float
        The participant's unmasked AL for the same stimulus, dB re 1 V.

    Returns
    -------
    float
        Sensation level in dB SL (negative below the AL).

    Raises
    ------
    LevelError
        If either value is not finite.

    Examples
    --------
    >>> db_v_to_db_sl(-22.5, -32.5)
    10.0
    """
    _finite("level_db_v", level_db_v)
    _finite("unmasked_al_db_v", unmasked_al_db_v)
    return float(level_db_v) - float(unmasked_al_db_v)


def check_within_rating(level_db_v: float, max_volts: float, *, what: str = "level") -> float:
    """Return ``level_db_v`` if its amplitude is within ``max_volts``; raise otherwise.

    Parameters
    ----------
    level_db_v : float
        Requested drive level in dB re 1 V.
    max_volts : float
        The device's rated (or configured) maximum peak amplitude in V.
    what : str
        Name used in the error message (e.g. ``"masker MV120 at 25 dB SL"``).

    Returns
    -------
    float
        ``level_db_v`` unchanged, dB re 1 V.

    Raises
    ------
    LevelError
        If the level's amplitude exceeds ``max_volts``.

    Examples
    --------
    >>> check_within_rating(-6.0, 1.0)
    -6.0
    >>> check_within_rating(6.0, 1.0, what="MV120 at 30 dB SL")
    Traceback (most recent call last):
    ...
    masking_lab.core.errors.LevelError: MV120 at 30 dB SL: 6.00 dB re 1 V (1.995 V) exceeds ...
    """
    limit_db = volts_to_db_v(max_volts)
    if not level_db_v <= limit_db + 1e-9:
        raise LevelError(
            f"{what}: {level_db_v:.2f} dB re 1 V ({db_v_to_volts(level_db_v):.4g} V) exceeds the "
            f"device limit of {max_volts:g} V ({limit_db:.2f} dB re 1 V); lower the level or "
            "check the participant's calibration"
        )
    return level_db_v


def volts_to_db_v_array(volts: ArrayLike) -> NDArray[np.float64]:
    """Vectorised :func:`volts_to_db_v` with ``allow_zero`` semantics (0 V → −inf dB).

    Parameters
    ----------
    volts : array_like
        Peak amplitudes in V, ≥ 0.

    Returns
    -------
    ndarray
        Levels in dB re 1 V, same shape.

    Raises
    ------
    LevelError
        If any amplitude is negative, NaN or infinite.

    Examples
    --------
    >>> volts_to_db_v_array([0.0, 0.1, 1.0]).tolist()
    [-inf, -20.0, 0.0]
    """
    v = np.asarray(volts, dtype=float)
    bad = ~np.isfinite(v) | (v < 0)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise LevelError(f"amplitude at index {idx} is {v[idx]!r}: must be finite and ≥ 0 V")
    with np.errstate(divide="ignore"):
        return 20.0 * np.log10(v)


def db_v_to_volts_array(level_db_v: ArrayLike) -> NDArray[np.float64]:
    """Vectorised :func:`db_v_to_volts` (−inf dB → 0 V; NaN or +inf raise).

    Parameters
    ----------
    level_db_v : array_like
        Levels in dB re 1 V (finite or ``-inf``).

    Returns
    -------
    ndarray
        Peak amplitudes in V, same shape.

    Raises
    ------
    LevelError
        If any level is NaN or +inf.

    Examples
    --------
    >>> np.round(db_v_to_volts_array([float("-inf"), -20.0, 0.0]), 6).tolist()
    [0.0, 0.1, 1.0]
    """
    x = np.asarray(level_db_v, dtype=float)
    bad = np.isnan(x) | (x == np.inf)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise LevelError(f"level at index {idx} is {x[idx]!r}: must be finite dB re 1 V or -inf")
    return np.power(10.0, x / 20.0)


def _finite(name: str, value: float) -> None:
    x = float(value)
    if not math.isfinite(x):
        raise LevelError(f"{name} must be a finite number of dB, got {value!r}")
