"""Tail probabilities and quantiles of the t, F and chi-square distributions (pure).

The same numbers as ``scipy.stats`` (``t.sf``, ``t.ppf``, ``f.sf``, ``chi2.sf``) to the bit:
those call these very ``scipy.special`` functions and add only the edge rules reproduced
here (invalid degrees of freedom or a NaN give NaN; at or below the support's lower end the
survival function is 1). Importing ``scipy.stats`` costs about a second of every run of
``analyze`` (it builds every distribution and its docstrings); ``scipy.special`` a tenth of it,
so that is imported only when a tail is first asked for (a study of one participant has no
test to run).
"""

from __future__ import annotations

import math
from typing import Any

__all__ = ["chi2_sf", "f_sf", "t_ppf", "t_sf"]


def _special() -> Any:
    """``scipy.special``, imported at the first use."""
    from scipy import special

    return special


def _valid_df(*dfs: float) -> bool:
    return all(df > 0 for df in dfs)  # NaN compares False


def t_sf(x: float, df: float) -> float:
    """P(T > x) for Student's t with ``df`` degrees of freedom (as ``scipy.stats.t.sf``).

    Examples
    --------
    >>> round(t_sf(2.0, 10), 6)
    0.036694
    >>> t_sf(0.0, 3)
    0.5
    """
    if not _valid_df(df) or math.isnan(x):
        return math.nan
    if x == -math.inf:
        return 1.0
    if x == math.inf:
        return 0.0
    return float(_special().stdtr(df, -x))


def t_ppf(q: float, df: float) -> float:
    """The ``q`` quantile of Student's t with ``df`` degrees of freedom (as
    ``scipy.stats.t.ppf``; -inf at 0, inf at 1, NaN outside [0, 1]).

    Examples
    --------
    >>> round(t_ppf(0.975, 10), 6)
    2.228139
    """
    if not _valid_df(df) or not 0.0 <= q <= 1.0:  # NaN q fails the range test
        return math.nan
    if q == 0.0:
        return -math.inf
    if q == 1.0:
        return math.inf
    return float(_special().stdtrit(df, q) * 1.0 + 0.0)  # scipy's scale and loc, for -0.0


def f_sf(x: float, dfn: float, dfd: float) -> float:
    """P(F > x) for the F distribution with (``dfn``, ``dfd``) degrees of freedom (as
    ``scipy.stats.f.sf``).

    Examples
    --------
    >>> round(f_sf(4.0, 2, 12), 6)
    0.046656
    >>> f_sf(-1.0, 2, 12)
    1.0
    """
    if not _valid_df(dfn, dfd) or math.isnan(x):
        return math.nan
    if x <= 0.0:
        return 1.0
    if x == math.inf:
        return 0.0
    return float(_special().fdtrc(dfn, dfd, x))


def chi2_sf(x: float, df: float) -> float:
    """P(X > x) for the chi-square distribution with ``df`` degrees of freedom (as
    ``scipy.stats.chi2.sf``).

    Examples
    --------
    >>> round(chi2_sf(3.84, 1), 4)
    0.05
    >>> chi2_sf(0.0, 2)
    1.0
    """
    if not _valid_df(df) or math.isnan(x):
        return math.nan
    if x <= 0.0:
        return 1.0
    if x == math.inf:
        return 0.0
    return float(_special().chdtrc(df, x))
