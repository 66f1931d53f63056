"""Brent's root finder (pure): :func:`brentq`, the iterates of ``scipy.optimize.brentq``.

The package needs the root of a smooth scalar function in two places: a staircase rule's
target p(correct) (``procedures.staircase.implied_target_p_for``: every ``analyze`` that writes
``psychometric.csv``, the demo, ``plan``) and the down/up step ratio for a target
(``procedures.downup_ratio``). Importing ``scipy.optimize`` for it cost ~0.17 s of CPU per
process (after numpy, pandas and ``scipy.special``), more than a tenth of a small analysis.

This is Brent's method as SciPy's C ``brentq`` runs it (Charles Harris's variant: inverse
quadratic extrapolation or secant steps while they shrink the bracket fast enough, bisection
otherwise), with the same arithmetic in the same order, so it returns the same double bit for
bit (``tests/test_roots.py`` checks that against SciPy on thousands of functions and brackets).
Python's float division raises where C's gives ±inf or NaN (a difference of tiny values that
is 0): such a step is refused here as it is there, and the bracket bisected.
"""

from __future__ import annotations

import math
import sys
from collections.abc import Callable

__all__ = ["RTOL_MIN", "brentq"]

#: The smallest relative tolerance accepted (SciPy's limit: 4 ulp of 1).
RTOL_MIN = 4 * sys.float_info.epsilon


def brentq(
    f: Callable[[float], float],
    a: float,
    b: float,
    *,
    xtol: float = 2e-12,
    rtol: float = RTOL_MIN,
    maxiter: int = 100,
) -> float:
    """A root of ``f`` in the bracket [a, b] (``f(a)`` and ``f(b)`` of opposite signs).

    Parameters
    ----------
    f : callable
        A continuous function of one float returning a float (units are the caller's).
    a, b : float
        The bracket's ends.
    xtol, rtol : float
        The root is returned once it is known within ``xtol + rtol·|x|`` (units of x);
        ``xtol`` > 0 and ``rtol`` ≥ :data:`RTOL_MIN`, as in SciPy.
    maxiter : int
        Iterations (function values after the first two) before giving up.

    Returns
    -------
    float
        The root, the same double as ``scipy.optimize.brentq(f, a, b, xtol=xtol, rtol=rtol,
        maxiter=maxiter)``.

    Raises
    ------
    ValueError
        If a tolerance is out of range, ``f(a)`` and ``f(b)`` have the same sign, or ``f``
        gives NaN.
    RuntimeError
        If the root is not found within ``maxiter`` iterations.

    Examples
    --------
    >>> brentq(lambda x: x * x - 2.0, 0.0, 2.0) == 1.4142135623731364
    True
    >>> round(brentq(math.cos, 0.0, 3.0, xtol=1e-13), 12)
    1.570796326795
    """
    if not xtol > 0:
        raise ValueError(f"xtol must be > 0, got {xtol}")
    if not rtol >= RTOL_MIN:
        raise ValueError(f"rtol must be >= {RTOL_MIN:g}, got {rtol}")
    xpre, xcur = float(a), float(b)
    fpre, fcur = _value(f, xpre), _value(f, xcur)
    if fpre != 0 and fcur != 0 and (fpre < 0) == (fcur < 0):
        raise ValueError(
            f"f(a) and f(b) must have different signs: f({xpre!r}) = {fpre!r}, "
            f"f({xcur!r}) = {fcur!r}"
        )
    if fpre == 0:
        return xpre
    if fcur == 0:
        return xcur
    # xcur: the best estimate; xpre: the one before; xblk: the other end of the bracket.
    xblk = fblk = spre = scur = 0.0
    for _ in range(maxiter):
        if fpre != 0 and fcur != 0 and (fpre < 0) != (fcur < 0):
            xblk, fblk = xpre, fpre
            spre = scur = xcur - xpre
        if abs(fblk) < abs(fcur):  # keep the smaller value at xcur
            xpre, xcur, xblk = xcur, xblk, xcur
            fpre, fcur, fblk = fcur, fblk, fcur
        delta = (xtol + rtol * abs(xcur)) / 2
        sbis = (xblk - xcur) / 2
        if fcur == 0 or abs(sbis) < delta:
            return xcur
        if abs(spre) > delta and abs(fcur) < abs(fpre):
            if xpre == xblk:  # secant
                stry = _div(-fcur * (xcur - xpre), fcur - fpre)
            else:  # inverse quadratic extrapolation
                dpre = _div(fpre - fcur, xpre - xcur)
                dblk = _div(fblk - fcur, xblk - xcur)
                stry = _div(-fcur * (fblk * dblk - fpre * dpre), dblk * dpre * (fblk - fpre))
            if 2 * abs(stry) < min(abs(spre), 3 * abs(sbis) - delta):
                spre, scur = scur, stry  # a short enough step: take it
            else:
                spre = scur = sbis
        else:
            spre = scur = sbis
        xpre, fpre = xcur, fcur
        if abs(scur) > delta:
            xcur += scur
        else:
            xcur += delta if sbis > 0 else -delta
        fcur = _value(f, xcur)
    raise RuntimeError(f"no root found in {maxiter} iterations; the last estimate was {xcur!r}")


def _div(n: float, d: float) -> float:
    """``n / d`` as C divides doubles: ±inf or NaN for a zero ``d`` (which tiny values give),
    where Python raises; the step is then refused and the bracket bisected, as in SciPy."""
    if d != 0:
        return n / d
    if n == 0 or math.isnan(n):
        return math.nan
    return math.copysign(math.inf, n) * math.copysign(1.0, d)


def _value(f: Callable[[float], float], x: float) -> float:
    y = float(f(x))
    if math.isnan(y):
        raise ValueError(f"the function is NaN at x = {x!r}; no root can be bracketed")
    return y
